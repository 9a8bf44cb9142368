"""Run under ``mpiexec -n 2``: objectives and adjoint gradients of a distributed run equal those
of a serial run of the same problem (COMM_SELF in the same process), parameter by parameter:
the parameter vector is in canonical (partition-independent) order. Objectives reading the
history fields of a step (``u_prev``, ``u_tilde``) also agree with central differences of the
distributed run."""

import numpy as np
import pytest
from gradient_scenes import (
    CONTROLS,
    SCENES,
    assert_world_equals_self,
    build_model,
    model_simulation,
    objective,
)
from mpi4py import MPI

import diffsolids as ds
from diffsolids.objectives import BoundarySmoothing, MaterialSmoothing
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.verification import finite_difference_check

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
    parallel = _value_and_gradient(comm, case)
    assert_world_equals_self(comm, parallel, _value_and_gradient(MPI.COMM_SELF, case), RTOL)


# objectives on the history fields: serial == 2 ranks, and FD of the distributed run
HISTORY_CASES = {
    "bdf2-u_prev": ("2d-p1-nh-damped", ds.BDF(2, 0.05, 3), "u_prev"),
    "bdf3-u_tilde": ("2d-p1-nh-damped", ds.BDF(3, 0.05, 4), "u_tilde"),
    "static-u_prev": ("2d-p1-nh-damped-ramp", ds.Static(num_steps=2, dt=0.5), "u_prev"),
}


def _history_value_and_gradient(comm, case: str, fd: bool = False):
    scene_name, integrator, kind = HISTORY_CASES[case]
    scene = SCENES[scene_name]
    model = build_model(scene, comm)
    sim = model_simulation(model, integrator)
    keys = ["young-field-log", "initial-u0"] + (["initial-v0"] if integrator.dynamic else [])
    rf = ReducedFunctional(
        sim, objective(kind, model, integrator.dynamic), [CONTROLS[k](sim) for k in keys]
    )
    q0 = rf.initial_parameters()
    rng = np.random.default_rng(5)
    q = q0 + 1e-3 * np.maximum(np.abs(q0), 1e-2) * rng.standard_normal(q0.size)
    value, gradient = rf.value_and_gradient(q)
    check = None
    if fd:  # along a random direction (the same on every rank: canonical order)
        d = 1e-2 * np.maximum(np.abs(q0), 1e-2) * rng.standard_normal(q0.size)
        check = finite_difference_check(rf, q, d, [1e-2, 1e-3], gradient=gradient)
    return q0, value, gradient, check


@pytest.mark.parametrize("case", list(HISTORY_CASES))
def test_history_gradient_world_equals_self(case):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    q_par, J_par, g_par, fd = _history_value_and_gradient(comm, case, fd=True)
    q_ser, J_ser, g_ser, _ = _history_value_and_gradient(MPI.COMM_SELF, case)
    assert fd.relative_error <= 1e-6, str(fd)
    assert_world_equals_self(comm, (q_par, J_par, g_par), (q_ser, J_ser, g_ser), RTOL)
