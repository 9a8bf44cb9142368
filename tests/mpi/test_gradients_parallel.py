"""Run under ``mpiexec -n 2``: objectives and adjoint gradients of a distributed run equal those
of a serial run of the same problem (COMM_SELF in the same process), parameter by parameter:
the parameter vector is in canonical (partition-independent) order."""

import numpy as np
import pytest
from gradient_scenes import CONTROLS, SCENES, build_model, model_simulation, objective
from mpi4py import MPI

import diffsolids as ds
from diffsolids.objectives import BoundarySmoothing, MaterialSmoothing
from diffsolids.reduced_functional import ReducedFunctional

RTOL = 1e-8

CASES = {
    "bdf2-2d-p2-nh-damped": (
        "2d-p2-nh-damped-lame-ps",
        ds.BDF(2, 0.05, 3),
        "target",
        "shape-all mu-field-log lmbda-bodies psi-bodies initial-u0 rigid-velocity "
        "dirichlet-per-step",
    ),
    "static-3d-p1-lin-cg1": (
        "3d-p1-lin-cg1",
        ds.Static(),
        "stress",
        "young-field-log poisson-field shape-boundary traction-scale gravity-uniform",
    ),
    "bdf1-3d-p1-nh-damped": (
        "3d-p1-nh-damped-lame",
        ds.BDF(1, 0.05, 2),
        "com",
        "shape-linear-map mu-field-log phi-field density-field initial-v0 dirichlet",
    ),
    "bdf2-2d-p1-maps": (
        "2d-p1-lin-damped-lame",
        ds.BDF(2, 0.05, 3),
        "target",
        "mu-bodies-log-affine gravity-power shape-all",
    ),
    "static-2d-p1-simp": ("2d-p1-lin-cg1-ps", ds.Static(), "stress", "young-field-simp"),
}


def _value_and_gradient(comm, case: str):
    scene_name, integrator, kind, controls = CASES[case]
    scene = SCENES[scene_name]
    model = build_model(scene, comm)
    sim = model_simulation(model, integrator)
    J = objective(kind, model, integrator.dynamic)
    J = J + 1e-2 * BoundarySmoothing(model, 2.0, exclude_facets=[1])
    J = J + 1e-3 * MaterialSmoothing(model, ["density"])
    rf = ReducedFunctional(sim, J, [CONTROLS[k](sim) for k in controls.split()])
    q0 = rf.initial_parameters()
    rng = np.random.default_rng(11)
    sizes = np.maximum(np.abs(q0), 1e-2)
    q = q0 + 1e-3 * sizes * rng.standard_normal(q0.size)
    value, gradient = rf.value_and_gradient(q)
    return q0, value, gradient


@pytest.mark.parametrize("case", list(CASES))
def test_gradient_world_equals_self(case):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    q_par, J_par, g_par = _value_and_gradient(comm, case)
    q_ser, J_ser, g_ser = _value_and_gradient(MPI.COMM_SELF, case)
    # canonical parameter order: a wrong order moves values by O(1); a field interpolated at dof
    # coordinates (pushed forward from a different cell on each partition) differs by rounding
    np.testing.assert_allclose(q_par, q_ser, rtol=4 * np.finfo(float).eps, atol=0)
    assert J_par == pytest.approx(J_ser, rel=RTOL)
    assert np.abs(g_ser).max() > 0
    assert np.abs(g_par - g_ser).max() <= RTOL * np.abs(g_ser).max()
    # every rank holds the same value and gradient
    for value in comm.allgather(J_par):
        assert value == J_par
    for gradient in comm.allgather(g_par):
        assert np.array_equal(gradient, g_par)
