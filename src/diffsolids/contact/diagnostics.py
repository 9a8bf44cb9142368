"""Diagnostics of the contact term: step records, forces per body, failure reports, hints."""

import logging
from dataclasses import dataclass

import numpy as np

from diffsolids.contact.detection.step_bound import _GAP_FLOOR_ULPS
from diffsolids.contact.energy.evaluation import Evaluation
from diffsolids.contact.geometry.surface import CollisionSurface
from diffsolids.contact.partition import CollisionPartition
from diffsolids.errors import IntersectionError

__all__ = [
    "ContactRecord",
    "body_forces",
    "continuation_schedule",
    "failure_report",
    "obstacle_move_error",
    "step_record",
]

logger = logging.getLogger("diffsolids")


@dataclass
class ContactRecord:
    """Contact summary of one converged step.

    Attributes:
        step: Step index.
        num_collisions: Active primitive pairs (distance below dhat).
        min_distance: Smallest distance between active pairs (inf when there are none).
        normal_force: (num_bodies, dim) total barrier force on each body (rows: ``body_ids``,
            the domain's bodies, then the obstacles: the force on an obstacle is its reaction).
        friction_force: (num_bodies, dim) total friction force on each body.
    """

    step: int
    num_collisions: int
    min_distance: float
    normal_force: np.ndarray
    friction_force: np.ndarray


def step_record(
    i: int,
    partition: CollisionPartition,
    surface: CollisionSurface,
    num_bodies: int,
    ev: Evaluation,
    gradient: np.ndarray,
    barrier_gradient: np.ndarray,
) -> ContactRecord:
    """The record of the converged step ``i`` at ev, logged (collective).

    Args:
        i: Step index.
        partition: The collision counts and distances over the ranks.
        surface: The collision surface.
        num_bodies: Number of bodies (obstacles included).
        ev: The evaluation at the converged state.
        gradient: Gradient of the contact potential at ev (summed over the ranks).
        barrier_gradient: Its barrier part.
    """
    normal, friction = body_forces(surface.body_index, num_bodies, gradient, barrier_gradient)
    C = ev.collisions
    count = partition.count(C)
    dist = partition.minimum_distance(C, surface.mesh, ev.x)
    rec = ContactRecord(i, count, dist, normal, friction)
    logger.info(
        "contact step %4d  pairs=%d  min_distance=%.3e  |normal force|=%.3e  |friction force|=%.3e",
        i,
        rec.num_collisions,
        rec.min_distance,
        np.linalg.norm(normal, axis=1).max(initial=0.0),
        np.linalg.norm(friction, axis=1).max(initial=0.0),
    )
    return rec


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


def settling_gap(stiffness: float, dhat: float, force: float) -> float:
    """The gap at which a pair carrying ``force`` settles, for gaps far inside dhat."""
    # kappa b(d^2, dhat^2) with b = -(s - t)^2 ln(s / t) pushes with ~2 kappa dhat^4 / d at
    # d << dhat: a pair carrying force f settles at d ~ 2 kappa dhat^4 / f
    return 2.0 * stiffness * dhat**4 / max(force, 1e-300)


# a continuation starts where the most loaded pair settles at this fraction of dhat, and
# divides the stiffness by at most _CONTINUATION_RATIO per stage
_CONTINUATION_GAP = 1e-2
_CONTINUATION_RATIO = 100.0
_CONTINUATION_MAX_FACTOR = 1e10


def continuation_schedule(stiffness: float, dhat: float, force: float) -> tuple[float, ...]:
    """Barrier-stiffness factors, decreasing to (not including) 1, for a too soft barrier.

    A barrier of stiffness kappa holds a pair carrying force f at d ~ 2 kappa dhat^4 / f.
    Far inside dhat every Newton step is cut by the collision check (the pairs' gaps are
    orders of magnitude below the tangential motion of the step); the minimiser of the step
    potential is reached instead from the minimiser for a stiffer barrier, where the pairs
    rest at ``_CONTINUATION_GAP`` dhat, dividing the stiffness by about
    ``_CONTINUATION_RATIO`` per stage: each stage starts next to its own minimiser.

    Returns:
        The factors (empty: the barrier is not too soft for the force).
    """
    gap = settling_gap(stiffness, dhat, force)
    start = min(_CONTINUATION_GAP * dhat / gap, _CONTINUATION_MAX_FACTOR)
    if not start > _CONTINUATION_RATIO:
        return ()
    stages = int(np.ceil(np.log(start) / np.log(_CONTINUATION_RATIO)))
    return tuple(start ** (k / stages) for k in range(stages, 0, -1))


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
    gap = settling_gap(stiffness, dhat, force)
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


def obstacle_move_error(
    surface: CollisionSurface, i: int, move: np.ndarray, dynamic: bool
) -> IntersectionError:
    """The error of an obstacle move that is not admissible in step ``i`` (names the obstacles).

    Args:
        surface: The collision surface.
        i: The step.
        move: (num_vertices, dim) the obstacles' move O^i - O^{i-1} (zero body rows).
        dynamic: Whether the step is dynamic (static load steps get a hint of their own).
    """
    surf = surface
    names = []
    for o, a, b in zip(
        surf.obstacles, surf.obstacle_offsets[:-1], surf.obstacle_offsets[1:], strict=True
    ):
        d = float(np.linalg.norm(move[a:b], axis=1).max(initial=0.0))
        if d > 0:
            names.append(f"{o.label} (moves {d:.3e})")
    return IntersectionError(
        f"step {i}: {', '.join(names)} moves into the bodies faster than they can follow: "
        "the move from t_{i-1} to t_i is not collision-free with the bodies held at "
        "u^{i-1}, nor together with the body's initial guess (obstacles move before the "
        "Newton solve of a step, which then keeps them at t_i); use a smaller time step "
        "(an obstacle pressing a body may move at most about the contact gap per step "
        "unless the body already moves with it) or a slower motion"
        + (
            ""
            if dynamic
            else "; load steps have no velocity for the guess to move with, so an "
            "obstacle cannot push a body quasi-statically: drive a clamped volume by "
            "Dirichlet values instead (reached by continuation)"
        )
    )
