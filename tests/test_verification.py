"""The default steps of taylor_test: rate 2 for a correct gradient, a note when it cannot show.

Toy functionals (J, gradient) whose behaviour at large steps, with a wrong gradient or with
noise is known in closed form; the contact scene of the issue is in test_flat_contact.
"""

import numpy as np
import pytest

import diffsolids as ds


class Wavy:
    """J(q) = sum sin(k q): the default first step (k h = 0.65) is far from asymptotic."""

    def __init__(self, k: float = 50.0, wrong: float = 1.0, noise: float = 0.0) -> None:
        self.k, self.wrong, self.noise = k, wrong, noise
        self.rng = np.random.default_rng(0)
        self.calls = 0

    def __call__(self, q: np.ndarray) -> float:
        self.calls += 1
        return float(np.sum(np.sin(self.k * q))) + self.noise * self.rng.standard_normal()

    def gradient(self, q: np.ndarray) -> np.ndarray:
        return self.wrong * self.k * np.cos(self.k * q)


Q, DQ = np.array([0.3]), np.array([1.0])


def test_default_steps_shrink_until_a_correct_gradient_shows_rate_2():
    fixed = ds.taylor_test(Wavy(), Q, DQ, h0=1e-2 * 1.3, num=4)  # the old default steps
    assert fixed.min_rate < 1.75
    wavy = Wavy()
    taylor = ds.taylor_test(wavy, Q, DQ)
    assert np.all(np.abs(taylor.rates_second - 2.0) <= 0.15), taylor
    assert taylor.min_rate >= 1.75 and taylor.note == ""
    assert len(taylor.steps) == 4 and taylor.steps[0] < fixed.steps[0]
    assert wavy.calls <= 1 + 4 + 6


def test_a_wrong_gradient_is_reported_as_such():
    taylor = ds.taylor_test(Wavy(wrong=1.05), Q, DQ)
    assert taylor.min_rate < 1.5
    assert "the gradient is wrong" in taylor.note and "the gradient is wrong" in str(taylor)
    assert "(4.7% of it)" in taylor.note  # 5% of dJ.dq off: 0.05 / 1.05 of the wrong value


def test_noise_in_j_stops_the_search_with_its_reason():
    taylor = ds.taylor_test(Wavy(k=30.0, noise=1e-4), Q, DQ)
    assert "noise of J" in taylor.note, taylor

    class Affine(Wavy):
        def __call__(self, q):
            return float(2.0 * q[0] + 1.0)

        def gradient(self, q):
            return np.array([2.0])

    exact = ds.taylor_test(Affine(), Q, DQ)  # R1 is round-off at once
    assert "round-off" in exact.note, exact


@pytest.mark.parametrize("num", [3, 5])
def test_a_given_first_step_gives_exactly_num_steps(num):
    wavy = Wavy()
    taylor = ds.taylor_test(wavy, Q, DQ, h0=1e-3, num=num)
    assert np.allclose(taylor.steps, 1e-3 * 0.5 ** np.arange(num))
    assert wavy.calls == 1 + num and taylor.note == ""
