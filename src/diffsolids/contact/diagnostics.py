"""Diagnostics of the contact term: forces per body and the report of a failed Newton solve."""

import numpy as np

from diffsolids.contact.step_bound import _GAP_FLOOR_ULPS

__all__ = ["body_forces", "failure_report"]


def body_forces(
    body_index: np.ndarray, num_bodies: int, gradient: np.ndarray, barrier_gradient: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(num_bodies, dim) total barrier and friction forces on each body.

    Args:
        body_index: Body index of each collision vertex.
        num_bodies: Number of bodies (obstacles included).
        gradient: Gradient of the contact potential in collision dofs (barrier + friction).
        barrier_gradient: Its barrier part.
    """
    d = gradient.size // len(body_index)
    normal = np.zeros((num_bodies, d))
    friction = np.zeros((num_bodies, d))
    np.add.at(normal, body_index, -barrier_gradient.reshape(-1, d))
    np.add.at(friction, body_index, -(gradient - barrier_gradient).reshape(-1, d))
    return normal, friction


def failure_report(
    stiffness: float,
    dhat: float,
    num_pairs: int = 0,
    distance: float = np.inf,
    force: float = 0.0,
    floor: float | None = None,
) -> str:
    """The contact part of a NewtonConvergenceError's message, with hints.

    Args:
        stiffness: Barrier stiffness kappa.
        dhat: Barrier activation distance.
        num_pairs: Active pairs at the last iterate (0: no contact).
        distance: Their smallest distance.
        force: The largest contact force on a collision vertex.
        floor: The smallest gap floor that held a near pair in the last step bound, or None.
    """
    head = f"contact: kappa = {stiffness:.3g}, dhat = {dhat:.3g}"
    if num_pairs == 0:
        return f"{head}, no pair within dhat at the last iterate"
    d = distance
    # kappa b(d^2, dhat^2) with b = -(s - t)^2 ln(s / t) pushes with ~2 kappa dhat^4 / d at
    # d << dhat: a pair carrying force f settles at d ~ 2 kappa dhat^4 / f
    gap = 2.0 * stiffness * dhat**4 / max(force, 1e-300)
    hint = (
        "; the barrier is too soft for this load (pairs settle far inside dhat, where the "
        "collision check cuts every Newton step): raise kappa, e.g. to "
        "suggest_barrier_stiffness(...)"
        if gap < 1e-3 * dhat
        else ""
    )
    if floor is not None and d < 10.0 * floor:
        hint += (
            f"; the collision check holds pairs at ~{floor:.1e} (about {_GAP_FLOOR_ULPS:g} "
            "ulps of the coordinates; closer, round-off decides the side of an edge): a "
            "barrier that must come closer to carry the load cannot in double precision, so "
            "raise kappa until 2 kappa dhat^4 / f exceeds that gap (or place the contact "
            "nearer the origin, where coordinates have smaller ulps)"
        )
    return (
        f"{head}, {num_pairs} active pairs, smallest distance {d:.3e} "
        f"({d / dhat:.2e} dhat), largest contact force {force:.3e}; a pair carrying "
        f"it settles at a distance ~2 kappa dhat^4 / f = {gap:.2e}{hint}"
    )
