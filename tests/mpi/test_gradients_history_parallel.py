"""Run under ``mpiexec -n 2``: objectives reading the history fields of a step (``u_prev``,
``u_tilde``) have the serial value and adjoint gradient on 2 ranks (canonical parameter order),
and that gradient agrees with central differences of the distributed run."""

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
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.verification import finite_difference_check

RTOL = 1e-8

CASES = {
    "bdf2-u_prev": ("2d-p1-nh-damped", ds.BDF(2, 0.05, 3), "u_prev"),
    "bdf3-u_tilde": ("2d-p1-nh-damped", ds.BDF(3, 0.05, 4), "u_tilde"),
    "static-u_prev": ("2d-p1-nh-damped-ramp", ds.Static(num_steps=2, dt=0.5), "u_prev"),
}


def _value_and_gradient(comm, case: str, fd: bool = False):
    scene_name, integrator, kind = CASES[case]
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


@pytest.mark.parametrize("case", list(CASES))
def test_history_gradient_world_equals_self(case):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    q_par, J_par, g_par, fd = _value_and_gradient(comm, case, fd=True)
    q_ser, J_ser, g_ser, _ = _value_and_gradient(MPI.COMM_SELF, case)
    assert fd.relative_error <= 1e-6, str(fd)
    assert_world_equals_self(comm, (q_par, J_par, g_par), (q_ser, J_ser, g_ser), RTOL)
