"""Dirichlet conditions on a whole body (``OnBody``): a driven part of a multi-body scene.

Scene: a strip [0, 2] x [0, 0.4] meshed as two bodies, "soft" (x < 1) and "driver" (x > 1).
The driver's every node follows a prescribed rigid motion; the soft body is clamped at x = 0
and is stretched by the driver through their shared interface nodes.
"""

import numpy as np
import pytest
import ufl
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import ParameterControl
from diffsolids.objectives import Integral, final_value
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.verification import finite_difference_check

SOFT, DRIVER = 1, 2
N = (8, 2)


def _model(comm: MPI.Comm, motion) -> ds.Model:
    domain = ds.mesh.create_rectangle(
        comm,
        [[0, 0], [2, 0.4]],
        list(N),
        facets={1: lambda x: np.isclose(x[0], 0.0)},
        bodies={DRIVER: lambda x: x[0] > 1.0},
        names={"soft": SOFT, "driver": DRIVER, "left": 1},
    )
    model = ds.Model(domain, ds.NeoHookean(E=100.0, nu=0.3, density=1.0), degree=1)
    model.add_dirichlet("left", 0.0)
    model.add_dirichlet(ds.OnBody("driver"), motion)
    return model


def _global_count(comm: MPI.Comm, local: int) -> int:
    return ds.parallel.collective_comm(comm).allreduce(local, op=MPI.SUM)


def test_every_node_of_the_body_is_constrained():
    model = _model(MPI.COMM_WORLD, [0.1, 0.0])
    bc = model.dirichlet[1]
    V = model.V
    owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
    constrained = _global_count(model.domain.comm, int(np.sum(bc.dofs < owned)))
    # the driver covers columns x >= 1 of the (N[0] + 1) x (N[1] + 1) grid of vertices
    nodes = (N[0] // 2 + 1) * (N[1] + 1)
    assert constrained == model.dim * nodes


def test_the_body_follows_its_motion_and_pulls_the_other():
    model = _model(MPI.COMM_WORLD, lambda t: [0.1 * t, -0.05 * t])
    sim = ds.Simulation(model, ds.Static(num_steps=2, dt=0.5), progress=False)
    traj = sim.run()
    u = traj.u[-1].reshape(-1, model.dim)
    x = model.V.tabulate_dof_coordinates()[:, : model.dim]
    driver = x[:, 0] >= 1.0 - 1e-12
    assert np.allclose(u[driver], [0.1, -0.05], atol=1e-14)
    inside = (x[:, 0] > 0.1) & (x[:, 0] < 0.9)
    # the soft body is stretched: its displacement grows from the clamp towards the driver
    assert np.all(u[inside, 0] > 0.0) and np.all(u[inside, 0] < 0.1)


def test_an_unknown_body_is_named():
    with pytest.raises(ds.TagError, match="'hull'"):
        _model(MPI.COMM_WORLD, 0.0).add_dirichlet(ds.OnBody("hull"), 0.0)


def driven_body_functional(comm: MPI.Comm) -> ReducedFunctional:
    model = _model(comm, lambda t: [0.4 * t, 0.2 * t])
    sim = ds.Simulation(model, ds.BDF(2, 0.05, 3), ds.SolverOptions(rtol=1e-13), progress=False)
    objective = final_value(Integral(lambda f: ufl.inner(f.u, f.u) * f.dx(SOFT), "soft_u2"))
    control = ParameterControl(model, "E", "field", log=True)
    return ReducedFunctional(sim, objective, control)


@pytest.mark.parametrize("direction", ["random", "gradient"])
def test_gradient_with_a_driven_body(direction):
    """The soft body's E field under a driven body: adjoint against central differences."""
    rf = driven_body_functional(MPI.COMM_WORLD)
    q = rf.initial_parameters()
    q = q + 0.1 * np.random.default_rng(3).standard_normal(q.size)
    J, g = rf.value_and_gradient(q)
    assert np.linalg.norm(g) > 1e-6 * abs(J)
    d = np.random.default_rng(4).standard_normal(q.size) if direction == "random" else g
    fd = finite_difference_check(rf, q, d / np.linalg.norm(d), [1e-2, 1e-3, 1e-4], gradient=g)
    assert fd.relative_error < 1e-6, str(fd)
