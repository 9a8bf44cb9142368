"""The outcomes every demo run checks: the objective decreased, no state inverts or intersects."""

from common import DemoReport, check_decrease

from diffsolids.optimize import StateChecks

__all__ = ["check_invariants"]


def check_invariants(report: DemoReport, *checks: StateChecks, intersections: bool = True) -> None:
    """Record the outcomes every run checks: objective decreased, no inverted element.

    With ``intersections``, also: no checked state intersects.

    Args:
        report: The DemoReport.
        checks: Results of :func:`~diffsolids.optimize.check_trajectories` for the reported runs.
        intersections: Whether the runs have a contact surface to check.
    """
    states = sum(c.states for c in checks)
    inverted = sum(c.inverted for c in checks)
    check_decrease(report)
    report.check("no inverted element", inverted, 0, inverted == 0, f"(of {states} states)")
    if intersections:
        intersecting = sum(c.intersecting for c in checks)
        gap = min(c.min_distance for c in checks)
        report.check(
            "no intersection",
            intersecting,
            0,
            intersecting == 0,
            f"(intersecting states of {states}; smallest gap {gap:.2e} m)",
        )
