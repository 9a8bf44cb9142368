"""The tutorial's gradient, checked as a pytest test (``python -m pytest docs/examples``).

Two checks that can fail: a Taylor test (the remainder |J(q + h dq) - J(q) - h dJ.dq| must
fall as h^2) along a random direction, and central differences along the gradient itself,
where a wrong sign or scale cannot hide.
"""

import numpy as np
from tutorial_2d import build

import diffsolids as ds


def test_gradient_of_the_throw():
    """Taylor rate 2 along a random direction, central differences along the gradient."""
    rf, _ = build(steps=8, dt=0.04)  # a short run: the check does not need the whole slide
    q = np.array([0.8, 0.1])
    g = rf.gradient(q)
    # 1. Taylor test along a random direction: second-order remainders, rate ~2
    dq = np.random.default_rng(0).standard_normal(2)
    taylor = ds.taylor_test(rf, q, dq, h0=0.01, num=3)
    print(taylor)
    assert taylor.min_rate > 1.8
    # 2. central differences along the gradient
    check = ds.finite_difference_check(rf, q, 0.05 * g / np.linalg.norm(g), [1e-2, 1e-3])
    print(check)
    assert check.relative_error < 1e-5
