"""Run under ``mpiexec -n 2``: the distributed solve equals a serial solve of the same problem.

Each test runs the problem on COMM_WORLD and on COMM_SELF in the same process and compares
the gathered global fields (matched by dof coordinates), the energies and the Newton iterations.
"""

import numpy as np
import pytest
from mpi4py import MPI

import diffsolids as ds
from diffsolids.mesh import create_box, create_rectangle

RTOL = 1e-10


def _tip_and_energy(comm):
    dom = create_box(
        comm, [[0, 0, 0], [4, 0.5, 0.5]], [8, 2, 2], facets={1: lambda x: np.isclose(x[0], 0)}
    )
    model = ds.Model(dom, ds.NeoHookean(E=1e5, nu=0.3, density=100.0))
    model.add_gravity(9.81)
    model.add_dirichlet(1, 0.0)
    traj = ds.Simulation(model, ds.BDF(2, 0.02, 5), ds.SolverOptions(rtol=1e-12)).run()
    x = model.V.tabulate_dof_coordinates()
    u = traj.u[-1].reshape(-1, 3)
    tip = np.isclose(x[:, 0], 4.0) & np.isclose(x[:, 1], 0.0) & np.isclose(x[:, 2], 0.0)
    local = u[tip][0] if tip.any() else None
    vals = [v for v in comm.allgather(local) if v is not None]
    return vals[0], traj.records[-1].energy


def test_parallel_matches_serial():
    comm = MPI.COMM_WORLD
    tip_par, e_par = _tip_and_energy(comm)
    tip_ser, e_ser = _tip_and_energy(MPI.COMM_SELF)
    assert np.allclose(tip_par, tip_ser, rtol=1e-10, atol=1e-14)
    assert abs(e_par - e_ser) <= 1e-10 * abs(e_ser)


# -- whole fields of static and BDF2 runs ---------------------------------------------------------
def _gathered(model: ds.Model, arrays: list[np.ndarray]):
    """Owned dof coordinates and values of several fields, gathered and sorted by coordinates."""
    V = model.V
    comm = model.domain.comm
    n = V.dofmap.index_map.size_local
    bs = V.dofmap.index_map_bs
    x = np.concatenate(comm.allgather(V.tabulate_dof_coordinates()[:n]))
    values = [np.concatenate(comm.allgather(a[: n * bs].reshape(n, bs))) for a in arrays]
    order = np.lexsort(np.round(x, 10).T[::-1])
    return x[order], [v[order] for v in values]


def _model(comm, dim: int, degree: int) -> ds.Model:
    """A damped Neo-Hookean bar clamped at x = 0 with a traction at x = 2 (and gravity)."""
    facets = {1: lambda x: np.isclose(x[0], 0.0), 2: lambda x: np.isclose(x[0], 2.0)}
    mat = ds.NeoHookean(E=200.0, nu=0.35, density=2.0, damping_psi=0.5, damping_phi=0.2)
    if dim == 2:
        dom = create_rectangle(comm, [[0, 0], [2, 0.5]], [8, 2], facets=facets)
        traction = lambda t: [0.0, -8.0 * min(t, 0.1) / 0.1]  # noqa: E731
    else:
        dom = create_box(comm, [[0, 0, 0], [2, 0.5, 0.4]], [6, 2, 2], facets=facets)
        traction = lambda t: [2.0, -8.0 * min(t, 0.1) / 0.1, 1.0]  # noqa: E731
    model = ds.Model(dom, mat, degree=degree)
    model.add_dirichlet(1, 0.0)
    model.add_traction(2, traction)
    model.add_gravity(1.0)
    return model


def _run(comm, dim: int, degree: int, integrator):
    model = _model(comm, dim, degree)
    traj = ds.Simulation(model, integrator, progress=False).run()
    x, fields = _gathered(model, traj.u[1:] + traj.v[1:])
    return x, fields, traj.records


@pytest.mark.parametrize(
    ("dim", "degree", "integrator"),
    [
        (2, 2, ds.Static(num_steps=2, dt=0.05)),
        (3, 1, ds.Static(num_steps=2, dt=0.05)),
        (2, 2, ds.BDF(2, 0.05, 4)),
        (3, 1, ds.BDF(2, 0.05, 4)),
    ],
    ids=["static-2d-p2", "static-3d-p1", "bdf2-2d-p2", "bdf2-3d-p1"],
)
def test_world_equals_self(dim, degree, integrator):
    assert MPI.COMM_WORLD.size > 1, "run with mpiexec -n 2"
    x_par, par, rec_par = _run(MPI.COMM_WORLD, dim, degree, integrator)
    x_ser, ser, rec_ser = _run(MPI.COMM_SELF, dim, degree, integrator)
    assert x_par.shape == x_ser.shape and np.allclose(x_par, x_ser, rtol=0, atol=1e-12)
    assert len(par) == len(ser) == 2 * integrator.num_steps
    differences = []
    for a, b in zip(par, ser, strict=True):
        scale = np.abs(b).max()
        assert scale > 0.0
        differences.append(np.abs(a - b).max() / scale)
    print(f"max relative difference world vs self: {max(differences):.2e}")
    assert max(differences) <= RTOL
    # the loads deform the bar (a non-trivial comparison)
    assert np.abs(ser[integrator.num_steps - 1]).max() > 1e-2
    for r_par, r_ser in zip(rec_par, rec_ser, strict=True):
        assert r_par.energy == pytest.approx(r_ser.energy, rel=RTOL, abs=0.0)
        assert r_par.iterations == r_ser.iterations
        assert r_par.order == r_ser.order
    # every rank holds the same records
    energies = MPI.COMM_WORLD.allgather([r.energy for r in rec_par])
    assert all(e == energies[0] for e in energies)


def test_a_gmsh_failure_on_rank_0_raises_on_every_rank(file_from_rank_0):
    """Rank 0 meshes; the other ranks wait in a broadcast and must not hang when it fails."""
    from diffsolids.mesh import from_geo

    path = file_from_rank_0("broken.geo", "Point(1) = {0, 0, 0;\n")
    with pytest.raises(ds.MeshError, match=r"broken\.geo"):
        from_geo(path)
