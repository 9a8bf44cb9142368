"""Adjoint gradients of BDF1/2/3/6 runs in 2D vs finite differences and Taylor tests."""

import pytest
from gradient_scenes import DYNAMIC_CASES, SCENES, check_case

CASES = [c for c in DYNAMIC_CASES if SCENES[c.scene].dim == 2]


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_dynamic_gradient_2d(case):
    check_case(case)
