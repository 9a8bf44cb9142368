"""InversionGuard.max_step against cell volumes computed independently from moved vertices."""

import re

import numpy as np
import pytest
from dolfinx import fem
from mpi4py import MPI

import diffsolids  # noqa: F401  (loads MPI before the DOLFINx bindings)
from diffsolids.errors import ParameterError
from diffsolids.mesh import create_box, create_rectangle
from diffsolids.mesh.quality import signed_cell_volumes
from diffsolids.solvers.inversion import InversionGuard


def _domain(dim):
    if dim == 2:
        return create_rectangle(MPI.COMM_WORLD, [[0, 0], [1, 1]], [4, 4])
    return create_box(MPI.COMM_WORLD, [[0, 0, 0], [1, 1, 1]], [3, 3, 3])


def _volumes(mesh, V, u):
    """Signed P1 cell volumes of the mesh moved by the nodal displacement u (P1, blocked)."""
    d = mesh.geometry.dim
    x = mesh.geometry.x.copy()
    nodes = mesh.geometry.dofmaps[0].ravel()
    dofs = V.dofmap.list.ravel()
    x[nodes, :d] += u.reshape(-1, d)[dofs]
    return signed_cell_volumes(mesh, x)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_max_step_is_the_first_inversion(dim, seed):
    dom = _domain(dim)
    mesh = dom.mesh
    V = fem.functionspace(mesh, ("Lagrange", 1, (dim,)))
    rng = np.random.default_rng(seed)
    u, du = fem.Function(V), fem.Function(V)
    u.x.array[:] = 0.02 * rng.standard_normal(u.x.array.size)
    du.x.array[:] = 0.3 * rng.standard_normal(du.x.array.size)
    rest = np.sign(signed_cell_volumes(mesh))
    assert np.all(_volumes(mesh, V, u.x.array) * rest > 0)

    bound = InversionGuard(V, 2).max_step(u.x.petsc_vec, du.x.petsc_vec)
    assert 0 < bound < np.inf  # large random directions invert some cell
    inside = _volumes(mesh, V, u.x.array + (1 - 1e-6) * bound * du.x.array) * rest
    beyond = _volumes(mesh, V, u.x.array + (1 + 1e-6) * bound * du.x.array) * rest
    assert inside.min() > 0
    assert beyond.min() <= 0
    # det along the segment: no inversion before the bound (sampled)
    for s in np.linspace(0, 1 - 1e-6, 7) * bound:
        assert (_volumes(mesh, V, u.x.array + s * du.x.array) * rest).min() > 0

    # a limit only hides bounds at or above it
    assert InversionGuard(V, 2, limit=0.5 * bound).max_step(
        u.x.petsc_vec, du.x.petsc_vec
    ) == pytest.approx(np.inf)
    assert InversionGuard(V, 2, limit=(1 + 1e-9) * bound).max_step(
        u.x.petsc_vec, du.x.petsc_vec
    ) == pytest.approx(bound, rel=1e-12)


def test_inverted_state_and_bad_limit():
    dom = _domain(2)
    V = fem.functionspace(dom.mesh, ("Lagrange", 1, (2,)))
    u, du = fem.Function(V), fem.Function(V)
    x = V.tabulate_dof_coordinates()
    u.x.array[::2] = -2.0 * x[:, 0]  # F = diag(-1, 1): every cell inverted
    assert InversionGuard(V, 2).max_step(u.x.petsc_vec, du.x.petsc_vec) == 0.0
    assert InversionGuard(V, 2).max_step(du.x.petsc_vec, du.x.petsc_vec) == np.inf
    with pytest.raises(ParameterError, match="limit"):
        InversionGuard(V, 2, limit=0.0)


def test_a_solve_cut_by_the_inversion_guard_says_so():
    """A load far beyond what the mesh can carry in one step: the failure counts the cuts by
    their bound and advises smaller steps and a finer mesh, not a stiffer contact barrier."""
    import diffsolids as ds

    facets = {1: lambda x: np.isclose(x[0], 0)}
    domain = create_rectangle(MPI.COMM_WORLD, [[0, 0], [2, 0.2]], [20, 2], facets=facets)
    model = ds.Model(domain, ds.NeoHookean(E=1e2, nu=0.3, density=10.0))
    model.add_gravity(9.81e3)
    model.add_dirichlet(1, 0.0)
    sim = ds.Simulation(model, ds.BDF(1, 0.5, 3), progress=False)
    with pytest.raises(ds.NewtonConvergenceError) as failure:
        sim.run()
    text = str(failure.value)
    assert re.search(r"cut by a step bound \(\d+ to an inversion-free, 0 to a collision-free", text)
    assert "the steps would invert elements: a smaller time or load step" in text
    assert "barrier" not in text
