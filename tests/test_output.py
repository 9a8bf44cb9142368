"""TrajectoryWriter: VTX and XDMF for P1-P3 in 2D and 3D, read back and compared with the input."""

import numpy as np
import pytest
from dolfinx import fem
from mpi4py import MPI
from output_checks import (
    TIMES,
    expected_von_mises,
    gradient,
    model_on,
    read_vtx,
    read_xdmf,
    write_affine,
)

import diffsolids as ds
from diffsolids.errors import ParameterError
from diffsolids.io import TrajectoryWriter, von_mises_field
from diffsolids.mesh import create_box, create_rectangle

E_LIN = 200.0


def _domain(dim, comm=MPI.COMM_SELF):
    if dim == 2:
        return create_rectangle(comm, [[0, 0], [1, 2]], [3, 4])
    return create_box(comm, [[0, 0, 0], [1, 1, 2]], [2, 2, 3])


def _written(tmp_path, dim: int, degree: int, name: str):
    """The model whose affine motion ``write_affine`` wrote to ``tmp_path / name``."""
    model = model_on(_domain(dim), degree)
    write_affine(model, tmp_path / name)
    return model


def _num_cells(domain):
    imap = domain.mesh.topology.index_map(domain.mesh.topology.dim)
    return imap.size_global


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("degree", [1, 2, 3])
def test_xdmf_round_trip(tmp_path, dim, degree):
    dom = _written(tmp_path, dim, degree, "run.xdmf").domain
    data = read_xdmf(tmp_path / "run.xdmf")

    x = data["geometry"]
    assert x.shape == (dom.mesh.topology.index_map(0).size_global, dim)
    assert data["topology"].shape == (_num_cells(dom), dim + 1)
    assert set(data["fields"]) == {"displacement", "velocity", "von_mises"}
    G = gradient(dim)
    for t in TIMES:
        center, u = data["fields"]["displacement"][t]
        assert center == "Node"
        # vector fields are stored with 3 components; P2/P3 interpolated into P1 at vertices
        assert np.allclose(u[:, :dim], (1 + t) * x @ G.T, atol=1e-13)
        assert np.allclose(u[:, dim:], 0.0)
        _, v = data["fields"]["velocity"][t]
        assert np.allclose(v[:, :dim], x @ G.T, atol=1e-13)
        center, vm = data["fields"]["von_mises"][t]
        assert center == "Cell"
        assert vm.shape == (_num_cells(dom), 1)
        assert np.allclose(vm, expected_von_mises(dim, 1 + t), rtol=1e-10)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("degree", [1, 2, 3])
def test_vtx_round_trip(tmp_path, dim, degree):
    model = _written(tmp_path, dim, degree, "run.bp")
    dom = model.domain
    for name in ("run.bp", "run_cells.bp"):
        assert (tmp_path / name / "md.idx").exists()
        assert (tmp_path / name / "data.0").stat().st_size > 0

    nodes = read_vtx(tmp_path / "run.bp")
    assert {"displacement", "velocity", "geometry"} <= set(nodes["names"])
    assert [s["time"] for s in nodes["steps"]] == list(TIMES)
    G = gradient(dim)
    num_nodes = model.V.dofmap.index_map.size_global  # the nodes of the P-degree space
    for t, step in zip(TIMES, nodes["steps"], strict=True):
        x = step["geometry"][:, :dim]
        assert x.shape[0] == num_nodes
        assert np.allclose(step["displacement"][:, :dim], (1 + t) * x @ G.T, atol=1e-13)
        assert np.allclose(step["velocity"][:, :dim], x @ G.T, atol=1e-13)

    cells = read_vtx(tmp_path / "run_cells.bp")
    for t, step in zip(TIMES, cells["steps"], strict=True):
        vm = step["von_mises"]
        assert vm.size == _num_cells(dom)
        assert np.allclose(vm, expected_von_mises(dim, 1 + t), rtol=1e-10)


@pytest.mark.parametrize("plane_stress", [False, True])
def test_von_mises_2d_includes_out_of_plane_stress(plane_stress):
    dom = _domain(2)
    model = model_on(dom, 1, plane_stress=plane_stress)
    G = gradient(2)
    u = fem.Function(model.V)
    u.interpolate(lambda x: 1.5 * G @ x[:2])
    vm = von_mises_field(model, u.x.array).x.array
    assert np.allclose(vm, expected_von_mises(2, 1.5, plane_stress), rtol=1e-10)


def test_uniaxial_plane_stress_von_mises_is_the_axial_stress():
    # linear elasticity, plane stress, uniaxial stress state sigma_xx = E e: von Mises = E e
    dom = _domain(2)
    model = ds.Model(dom, ds.LinearElastic(E=E_LIN, nu=0.25), plane_stress=True)
    e = 1e-3
    u = fem.Function(model.V)
    u.interpolate(lambda x: np.stack([e * x[0], -0.25 * e * x[1]]))
    vm = von_mises_field(model, u.x.array).x.array
    assert np.allclose(vm, E_LIN * e, rtol=1e-12)


def test_extra_functions_and_bad_input(tmp_path):
    dom = _domain(2)
    model = model_on(dom, 2)
    mesh = dom.mesh
    scalar_p2 = fem.Function(fem.functionspace(mesh, ("Lagrange", 2)), name="phi")
    scalar_p1 = fem.Function(fem.functionspace(mesh, ("Lagrange", 1)), name="psi")
    cellwise = fem.Function(fem.functionspace(mesh, ("DG", 0)), name="eta")
    extra = [scalar_p2, scalar_p1, cellwise]
    write_affine(model, tmp_path / "x.bp", extra)
    for name, var in (("x.bp", "phi"), ("x_p1.bp", "psi"), ("x_cells.bp", "eta")):
        steps = read_vtx(tmp_path / name)["steps"]
        assert [s[var].ravel()[0] for s in steps] == list(TIMES)  # written at each time
    write_affine(model, tmp_path / "x.xdmf", extra)
    data = read_xdmf(tmp_path / "x.xdmf")
    for var, center in (("phi", "Node"), ("psi", "Node"), ("eta", "Cell")):
        for t in TIMES:
            c, values = data["fields"][var][t]
            assert c == center
            assert np.allclose(values, t)

    with pytest.raises(ParameterError, match=r"\.bp"):
        TrajectoryWriter(model, tmp_path / "run.vtu")
    with pytest.raises(ParameterError, match="distinct names"):
        TrajectoryWriter(model, tmp_path / "d.bp", [fem.Function(model.V, name="velocity")])
    other = _domain(2)
    alien = fem.Function(fem.functionspace(other.mesh, ("DG", 0)), name="alien")
    with pytest.raises(ParameterError, match="another mesh"):
        TrajectoryWriter(model, tmp_path / "a.bp", [alien])
    writer = TrajectoryWriter(model, tmp_path / "c.bp")
    writer.close()
    writer.close()  # idempotent
    with pytest.raises(ParameterError, match="closed"):
        writer.write(0.0, model.fields.u.x.array, model.fields.v.x.array)


def test_simulation_writes_every_step(tmp_path):
    dom = create_box(
        MPI.COMM_SELF, [[0, 0, 0], [4, 0.5, 0.5]], [8, 2, 2], {1: lambda x: np.isclose(x[0], 0)}
    )
    model = ds.Model(dom, ds.NeoHookean(E=1e5, nu=0.3, density=100.0))
    model.add_gravity(9.81)
    model.add_dirichlet(1, 0.0)
    traj = ds.Simulation(model, ds.BDF(2, 0.02, 3), output=str(tmp_path / "sim.bp")).run()
    steps = read_vtx(tmp_path / "sim.bp")["steps"]
    assert [s["time"] for s in steps] == pytest.approx(traj.times)
    # nodal values in VTX order: compare through the written geometry and dof coordinates
    x_dofs = model.V.tabulate_dof_coordinates()
    order = np.lexsort(x_dofs.T)
    for step, u in zip(steps, traj.u, strict=True):
        written = step["displacement"][np.lexsort(step["geometry"].T)]
        assert np.allclose(written, u.reshape(-1, 3)[order], atol=1e-14)


@pytest.mark.parametrize("law", ["linear", "st_venant_kirchhoff"])
def test_plane_strain_von_mises_of_uniaxial_strain(law):
    # u = (a x, 0): sigma_yy = sigma_zz, so von Mises = |sigma_xx - sigma_yy|
    dom = _domain(2)
    lmbda, mu, a = 30.0, 20.0, 0.05
    model = ds.Model(dom, ds.Material(law, lmbda=lmbda, mu=mu))
    u = fem.Function(model.V)
    u.interpolate(lambda x: np.stack([a * x[0], 0 * x[1]]))
    vm = von_mises_field(model, u.x.array).x.array
    if law == "linear":
        expected = 2 * mu * a
    else:
        g = ((1 + a) ** 2 - 1) / 2  # Green strain E_xx
        expected = (1 + a) * (lmbda + 2 * mu) * g - lmbda * g / (1 + a)
    assert np.allclose(vm, expected, rtol=1e-12)


@pytest.mark.parametrize("suffix", [".bp", ".xdmf"])
def test_each_trajectory_is_written_on_its_own_rest_shape(tmp_path, suffix):
    from output_checks import read_vtx, read_xdmf

    from diffsolids.controls import ShapeControl
    from diffsolids.io import write_trajectory

    facets = {1: lambda x: np.isclose(x[0], 0.0)}
    domain = create_rectangle(MPI.COMM_WORLD, [[0, 0], [2, 1]], [4, 2], facets=facets)
    model = ds.Model(domain, ds.LinearElastic(E=1e3, nu=0.3))
    model.add_gravity(1.0)
    model.add_dirichlet(1, 0.0)
    sim = ds.Simulation(model, ds.Static(), progress=False)
    control = ShapeControl(model)
    before = sim.run()
    X0 = model.domain.mesh.geometry.x.copy()
    control.assign(0.1 * np.ones(control.size))  # every vertex moves by (0.1, 0.1)
    after = sim.run()
    X1 = model.domain.mesh.geometry.x.copy()

    def geometry(path):
        if suffix == ".bp":
            return read_vtx(path)["steps"][0]["geometry"]
        return read_xdmf(path)["geometry"]

    write_trajectory(model, before, tmp_path / f"initial{suffix}")
    write_trajectory(model, after, tmp_path / f"final{suffix}")
    assert np.array_equal(model.domain.mesh.geometry.x, X1)  # the mesh is left as it was
    if MPI.COMM_WORLD.size == 1:
        initial, final = (
            geometry(tmp_path / f"initial{suffix}"),
            geometry(tmp_path / f"final{suffix}"),
        )
        assert np.allclose(np.sort(initial[:, 0]), np.sort(X0[:, 0]))
        assert np.allclose(np.sort(final[:, 0]), np.sort(X1[:, 0]))
        assert np.allclose(final[:, :2] - initial[:, :2], 0.1)
    other = ds.Model(create_rectangle(MPI.COMM_WORLD, [[0, 0], [2, 1]], [8, 4]), model.materials[1])
    with pytest.raises(ParameterError, match="computed on another mesh"):
        write_trajectory(other, before, tmp_path / f"wrong{suffix}")
