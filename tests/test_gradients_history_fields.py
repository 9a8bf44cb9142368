"""Objectives reading the history fields of a step (``u_prev``, ``u_tilde``).

Adjoint gradients of static and BDF runs vs central differences along random directions (per
control block) and along the gradient, with a Taylor test; objectives reading a history field
where it is undefined are refused.
"""

import numpy as np
import pytest
import ufl
from gradient_scenes import HISTORY_CASES, check_case, simulation

import diffsolids as ds
from diffsolids.controls import ParameterControl
from diffsolids.objectives import Integral, final_value, time_integral
from diffsolids.reduced_functional import ReducedFunctional


@pytest.mark.parametrize("case", HISTORY_CASES, ids=lambda c: c.id)
def test_history_field_gradient(case):
    check_case(case)


def test_predictor_of_a_static_run_is_refused():
    sim = simulation("2d-p1-nh-damped-ramp", "static2")
    control = [ParameterControl(sim.model, "E", "bodies")]
    tilde = Integral(lambda f: ufl.dot(f.u_tilde, f.u) * f.dx, "predicted")
    with pytest.raises(ds.ParameterError, match="'predicted' reads the field u_tilde"):
        ReducedFunctional(sim, final_value(tilde), control)


@pytest.mark.parametrize("field", ["u_prev", "u_tilde"])
def test_history_field_at_step_zero_is_refused(field):
    sim = simulation("2d-p1-nh-damped", "bdf2")
    control = [ParameterControl(sim.model, "E", "bodies")]
    leaf = Integral(lambda f: ufl.dot(getattr(f, field), f.u) * f.dx, "history")
    for weights in ("trapezoidal", [0, 2], np.ones(4)):
        with pytest.raises(ds.ParameterError, match=f"reads the field {field} at step 0"):
            ReducedFunctional(sim, time_integral(leaf, weights), control)
    # without step 0 the objective is accepted
    rf = ReducedFunctional(sim, time_integral(leaf, [1, 2, 3]), control)
    assert np.isfinite(rf(rf.initial_parameters()))
