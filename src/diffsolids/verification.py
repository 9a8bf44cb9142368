"""Gradient verification: Taylor tests, central finite differences, reproducibility, scans.

Usable from pytest and from users' scripts; every function returns a result object with a
readable report (``print(result)``).
"""

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from diffsolids.reduced_functional import ReducedFunctional

__all__ = [
    "DifferentiableFunctional",
    "FiniteDifferenceResult",
    "LineScan",
    "TaylorResult",
    "check_reproducible",
    "finite_difference_check",
    "line_scan",
    "taylor_test",
]


class DifferentiableFunctional(Protocol):
    """What the checks need of a functional: ``J(q)`` and ``gradient(q)``.

    A :class:`~diffsolids.reduced_functional.ReducedFunctional` is one; so is any object with
    these two methods (an analytic test function, a wrapped or penalised functional).
    """

    def __call__(self, q: np.ndarray) -> float:
        """The value J(q)."""
        ...

    def gradient(self, q: np.ndarray) -> np.ndarray:
        """The gradient dJ/dq at q."""
        ...


@dataclass
class TaylorResult:
    """Remainders of J(q + h dq) around q for decreasing h.

    Attributes:
        steps: The h values (with the default steps, the last ``num`` tried).
        first_order: |J(q + h dq) - J(q)| (rate ~1).
        second_order: |J(q + h dq) - J(q) - h dJ.dq| (rate ~2 if dJ is right).
        rates_first: log2 ratios of consecutive first-order remainders.
        rates_second: log2 ratios of consecutive second-order remainders.
        directional_derivative: dJ(q).dq from the gradient.
        note: Why the rates do not show 2 with the default steps (empty when they do).
    """

    steps: np.ndarray
    first_order: np.ndarray
    second_order: np.ndarray
    rates_first: np.ndarray
    rates_second: np.ndarray
    directional_derivative: float
    note: str = ""

    @property
    def min_rate(self) -> float:
        """Smallest second-order rate."""
        return float(np.min(self.rates_second))

    def __str__(self) -> str:
        lines = [
            f"Taylor test (dJ.dq = {self.directional_derivative:.6e})",
            f"{'h':>10} {'|R0|':>12} {'rate':>6} {'|R1|':>12} {'rate':>6}",
        ]
        for k, h in enumerate(self.steps):
            r0 = f"{self.rates_first[k - 1]:6.2f}" if k else " " * 6
            r1 = f"{self.rates_second[k - 1]:6.2f}" if k else " " * 6
            lines.append(
                f"{h:10.3e} {self.first_order[k]:12.4e} {r0} {self.second_order[k]:12.4e} {r1}"
            )
        if self.note:
            lines.append(self.note)
        return "\n".join(lines)


@contextlib.contextmanager
def _parameters_restored(rf: DifferentiableFunctional, q: np.ndarray) -> Iterator[None]:
    """Put a ReducedFunctional's controls back at q after the perturbed evaluations."""
    from diffsolids.reduced_functional import ReducedFunctional

    try:
        yield
    finally:
        if isinstance(rf, ReducedFunctional):
            rf.controls.assign(q)


def taylor_test(
    rf: DifferentiableFunctional,
    q: npt.ArrayLike,
    dq: npt.ArrayLike,
    h0: float | None = None,
    num: int = 4,
    factor: float = 0.5,
) -> TaylorResult:
    """Taylor remainder test of a ReducedFunctional (or any object with __call__ and gradient).

    Args:
        rf: Callable J(q) with ``gradient(q)`` (a :class:`DifferentiableFunctional`).
        q: Expansion point.
        dq: Direction.
        h0: Largest step. Given, exactly ``num`` steps h0 factor^k are tried. By default the
            steps start at 1e-2 (1 + |q|) / |dq| and go on shrinking (at most
            ``MAX_EXTRA_STEPS`` more) until the last ``num`` show second-order rates within
            ``RATE_WINDOW`` of 2, or the remainder reaches round-off; the result holds the
            last ``num`` steps and a ``note`` when rate 2 did not show.
        num: Number of steps.
        factor: Ratio of consecutive steps.

    The parameters of a ReducedFunctional are restored to ``q`` afterwards.
    """
    q = np.asarray(q, dtype=float)
    dq = np.asarray(dq, dtype=float)
    with _parameters_restored(rf, q):
        return _taylor(rf, q, dq, h0, num, factor)


def _taylor(
    rf: DifferentiableFunctional,
    q: np.ndarray,
    dq: np.ndarray,
    h0: float | None,
    num: int,
    factor: float,
) -> TaylorResult:
    J0 = rf(q)
    g = rf.gradient(q)
    dJ = float(g @ dq)
    adaptive = h0 is None
    if adaptive:
        h0 = 1e-2 * (1.0 + np.linalg.norm(q[dq != 0])) / max(np.linalg.norm(dq), 1e-300)
    hs, r0, r1 = [], [], []
    note = ""
    noise = ROUND_OFF * max(abs(J0), 1e-300)
    for k in range(num + (MAX_EXTRA_STEPS if adaptive else 0)):
        h = h0 * factor**k
        Jh = rf(q + h * dq)
        hs.append(h)
        r0.append(abs(Jh - J0))
        r1.append(abs(Jh - J0 - h * dJ))
        if not adaptive or len(hs) < num:
            continue
        rates = _rates(np.array(r1[-num:]), factor)
        if np.all(np.abs(rates - 2.0) <= RATE_WINDOW):
            break
        if r1[-1] <= noise:
            note = (
                f"the second-order remainder reached round-off (|R1| <= {ROUND_OFF:g} |J|) "
                "before rate 2 showed: J is not computed precisely enough for these steps "
                "(a tighter solver rtol), or dJ is exact to the digits J has"
            )
            break
    else:
        if adaptive:
            note = _why_no_rate_2(np.array(r1), factor, hs[-1], dJ)
    hs, r0, r1 = (np.array(a[-num:]) for a in (hs, r0, r1))
    return TaylorResult(hs, r0, r1, _rates(r0, factor), _rates(r1, factor), dJ, note)


#: How far each second-order rate may lie from 2 for the default steps to stop shrinking.
RATE_WINDOW = 0.15
#: Steps the default Taylor test may add after the first ``num``.
MAX_EXTRA_STEPS = 6
#: Remainders below this fraction of |J| are taken as round-off.
ROUND_OFF = 1e-11


def _why_no_rate_2(r1: np.ndarray, factor: float, h_last: float, dJ: float) -> str:
    rates = _rates(r1, factor)
    tail = rates[-2:]
    if np.all(np.abs(tail - 1.0) < 0.2):
        off = r1[-1] / h_last
        return (
            f"the remainder falls at rate 1 down to h = {h_last:.3g}: dJ.dq is off by about "
            f"{off:.3g} ({off / max(abs(dJ), 1e-300):.1%} of it): the gradient is wrong"
        )
    if np.nanmax(rates) >= 2.0 - RATE_WINDOW and np.any(tail < 0.5):
        return (
            f"rate 2 showed, then the remainder stopped falling near h = {h_last:.3g}: it "
            "reached the noise of J (solver tolerances); a larger h0 shows rate 2"
        )
    return (
        f"no rate 2 down to h = {h_last:.3g}: J is not smooth on this scale (see line_scan), "
        "or the gradient is wrong"
    )


def _rates(r: np.ndarray, factor: float) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log(r[:-1] / r[1:]) / np.log(1.0 / factor)


@dataclass
class FiniteDifferenceResult:
    """Central finite differences of J along dq for a sweep of steps.

    Attributes:
        adjoint: dJ.dq from the gradient.
        steps: Step sizes tried.
        finite_differences: (J(q + h dq) - J(q - h dq)) / (2h) per step.
        relative_errors: |fd - adjoint| / max(|adjoint|, |fd|) per step.
        best_step: Step with the smallest error.
        relative_error: Smallest relative error over the sweep.
    """

    adjoint: float
    steps: np.ndarray
    finite_differences: np.ndarray
    relative_errors: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def best_index(self) -> int:
        """Index of the best step."""
        return int(np.argmin(self.relative_errors))

    @property
    def best_step(self) -> float:
        """Step with the smallest error."""
        return float(self.steps[self.best_index])

    @property
    def relative_error(self) -> float:
        """Smallest relative error over the sweep."""
        return float(self.relative_errors[self.best_index])

    def __str__(self) -> str:
        lines = [
            f"central differences vs adjoint dJ.dq = {self.adjoint:.10e}",
            f"{'h':>10} {'fd':>18} {'rel. error':>11}",
        ]
        for h, fd, e in zip(self.steps, self.finite_differences, self.relative_errors, strict=True):
            mark = "  <- best" if h == self.best_step else ""
            lines.append(f"{h:10.3e} {fd:18.10e} {e:11.3e}{mark}")
        return "\n".join(lines)


def finite_difference_check(
    rf: DifferentiableFunctional,
    q: npt.ArrayLike,
    dq: npt.ArrayLike,
    steps: npt.ArrayLike | None = None,
    gradient: np.ndarray | None = None,
) -> FiniteDifferenceResult:
    """Compare dJ.dq from the adjoint with central differences over a sweep of steps.

    Args:
        rf: Callable J(q) with ``gradient(q)`` (a :class:`DifferentiableFunctional`).
        q: Point.
        dq: Direction.
        steps: Step sizes (default: 1e-2 .. 1e-7 relative to (1 + |q|) / |dq|).
        gradient: Precomputed gradient at q (else computed).

    The parameters of a ReducedFunctional are restored to ``q`` afterwards.
    """
    q = np.asarray(q, dtype=float)
    dq = np.asarray(dq, dtype=float)
    with _parameters_restored(rf, q):
        return _central_differences(rf, q, dq, steps, gradient)


def _central_differences(
    rf: DifferentiableFunctional,
    q: np.ndarray,
    dq: np.ndarray,
    steps: npt.ArrayLike | None,
    gradient: np.ndarray | None,
) -> FiniteDifferenceResult:
    g = rf.gradient(q) if gradient is None else gradient
    dJ = float(g @ dq)
    if steps is None:
        support = dq != 0
        scale = (1.0 + np.linalg.norm(q[support])) / max(np.linalg.norm(dq), 1e-300)
        steps = scale * 10.0 ** -np.arange(2.0, 7.5, 0.5)
    steps = np.asarray(steps, dtype=float)
    fds = np.array([(rf(q + h * dq) - rf(q - h * dq)) / (2 * h) for h in steps])
    denom = np.maximum(np.maximum(abs(dJ), np.abs(fds)), 1e-300)
    errors = np.abs(fds - dJ) / denom
    return FiniteDifferenceResult(dJ, steps, fds, errors)


def check_reproducible(rf: "ReducedFunctional", q: npt.ArrayLike) -> float:
    """Run the forward problem twice at q and require bit-identical J.

    Returns:
        J(q).

    Raises:
        AssertionError: The two runs differ (a derivative check would be meaningless).
    """
    q = np.asarray(q, dtype=float)
    J1 = rf.forward(q)
    J2 = rf.forward(q)
    if J1 != J2:
        raise AssertionError(f"forward runs are not reproducible: J = {J1!r} then {J2!r}")
    return J1


@dataclass
class LineScan:
    """J on points q + t dq of a line: is J a smooth function there?

    A jump is a sample off the mean of its two neighbours by more than ``threshold`` times the
    range of J over the scan (a smooth J sampled densely is off by its second difference, far
    less). Jumps show a forward that lands on different states for nearby parameters; a
    gradient is then no use to an optimiser or a finite-difference check.

    Attributes:
        offsets: The t values (sorted, equally spaced).
        values: J at each point.
        threshold: The jump threshold, a fraction of the range of J.
    """

    offsets: np.ndarray
    values: np.ndarray
    threshold: float = 0.05

    @property
    def value_range(self) -> float:
        """The largest J minus the smallest over the scan."""
        return float(self.values.max() - self.values.min())

    @property
    def deviations(self) -> np.ndarray:
        """|J_k - (J_{k-1} + J_{k+1}) / 2| / range of J, for the interior samples."""
        J = self.values
        scale = self.value_range if self.value_range > 0 else 1.0
        return np.abs(J[1:-1] - 0.5 * (J[:-2] + J[2:])) / scale

    @property
    def jumps(self) -> np.ndarray:
        """Indices (into ``offsets``) of the samples that jump."""
        return 1 + np.flatnonzero(self.deviations > self.threshold)

    def __str__(self) -> str:
        dev = self.deviations
        worst = float(dev.max()) if len(dev) else 0.0
        return (
            f"J on {len(self.values)} points, range {self.value_range:.6e}: "
            f"{len(self.jumps)} jumps (> {self.threshold:g} of the range), "
            f"worst deviation {worst:.3e} of the range"
        )


def line_scan(
    rf: DifferentiableFunctional,
    q: npt.ArrayLike,
    dq: npt.ArrayLike,
    radius: float,
    num: int = 41,
    threshold: float = 0.05,
) -> LineScan:
    """Evaluate J at ``num`` equally spaced points q + t dq, t in [-radius, radius].

    Each point is evaluated from scratch, in order; J must not depend on the order (the
    forward is a function of q alone). The parameters of a ReducedFunctional are restored
    to ``q`` afterwards.

    Args:
        rf: Callable J(q).
        q: Centre of the line.
        dq: Direction.
        radius: Half length of the line, in units of dq.
        num: Number of points (at least 3).
        threshold: Jump threshold, a fraction of the range of J (:class:`LineScan`).
    """
    if num < 3 or not radius > 0:
        raise ValueError(f"line_scan: need num >= 3 and radius > 0, got {num} and {radius}")
    q = np.asarray(q, dtype=float)
    dq = np.asarray(dq, dtype=float)
    offsets = np.linspace(-radius, radius, num)
    with _parameters_restored(rf, q):
        values = np.array([rf(q + t * dq) for t in offsets], dtype=float)
    return LineScan(offsets, values, threshold)
