"""Collision-free step bounds of the contact surface (CCD), the same on all ranks.

The Newton line search and the obstacles' moves are capped by the fraction of a straight path
x0 -> x1 of the collision surface that is collision-free (ipctk's broad phase and narrow-phase
CCD, AdditiveCCD or Tight Inclusion), reduced with a min over ranks. The CCD is the same
computation on every rank (the replicated part of distributed contact: handing candidates over
from ipctk costs more than its narrow phase, see :mod:`diffsolids.contact.partition`); the
collision sets it reads at x0 are this rank's share, and their minimum distance is taken over
the ranks. In 2D the vertex-edge pairs
that rest a tiny gap above an edge while they slide along it get the exact bound of
:func:`_edge_vertex_bounds` instead of ipctk's narrow phase (see
:meth:`StepBound._near_pairs_2d`).
"""

from collections.abc import Callable

import ipctk
import numpy as np
from mpi4py import MPI

from diffsolids.contact.partition import CollisionPartition
from diffsolids.contact.surface import CollisionSurface
from diffsolids.parallel import collective_comm

__all__ = ["StepBound"]

# the CCD checks the step extended by this factor, so that a free full step reports > 1
_CCD_REACH = 2.0
# 2D: vertex-edge pairs whose gap d is below sqrt(_DRIFT_ULPS |motion| ulp) or _NEAR_RATIO
# |motion| (AdditiveCCD would take ~|motion| / d steps, whose round-off adds up to the gap), or
# below the gap floor over (1 - conservative rescaling), get the exact bound of
# _edge_vertex_bounds instead of ipctk's narrow phase; no pair may come closer than
# _GAP_FLOOR_ULPS ulps of its coordinates
_DRIFT_ULPS = 1e3
_NEAR_RATIO = 1e-6
_GAP_FLOOR_ULPS = 1e2


class StepBound:
    """Collision-free fraction of straight paths of a collision surface.

    Args:
        surface: The collision surface (its mesh is read at each query: shape changes are seen).
        ccd: ipctk narrow phase (AdditiveCCD or TightInclusionCCD).
        broad_phase: ipctk broad phase.
        dhat: Barrier activation distance (the candidates' inflation).
        comm: Communicator of the ranks that must agree.
        partition: Which collisions the cached collision sets hold (default: all of them).

    Attributes:
        floor_held: After a query, the smallest gap floor that held a near pair (2D), or None.
    """

    def __init__(
        self,
        surface: CollisionSurface,
        ccd: ipctk.NarrowPhaseCCD,
        broad_phase: ipctk.BroadPhase,
        dhat: float,
        comm: MPI.Comm,
        partition: CollisionPartition | None = None,
    ) -> None:
        self.surface = surface
        self.ccd = ccd
        self.broad_phase = broad_phase
        self.dhat = float(dhat)
        self.comm = comm
        self.partition = partition if partition is not None else CollisionPartition(MPI.COMM_SELF)
        self.floor_held: float | None = None

    def fraction(
        self,
        x0: np.ndarray,
        x1: np.ndarray,
        cached: Callable[[], ipctk.NormalCollisions | None] = lambda: None,
        with_candidates: bool = False,
    ) -> float | tuple[float, ipctk.Candidates]:
        """Collision-free fraction of x0 -> x1 (collective; the same on all ranks).

        Args:
            x0: (num_vertices, dim) start positions (Fortran order), intersection-free.
            x1: (num_vertices, dim) end positions (Fortran order).
            cached: This rank's share of the collision set at x0 if one is at hand (else None),
                asked only when needed (by all ranks alike).
            with_candidates: Also return the broad-phase candidates of the path.

        Returns:
            The fraction, or (fraction, candidates).
        """
        self.floor_held = None
        candidates = ipctk.Candidates()
        candidates.build(self.surface.mesh, x0, x1, self.dhat, self.broad_phase)
        near, far = np.inf, candidates
        if self.surface.dim == 2 and not len(candidates.vv_candidates):
            near, far = self._near_pairs_2d(candidates, x0, x1, cached)
        toi = far.compute_collision_free_stepsize(self.surface.mesh, x0, x1, 0.0, self.ccd)
        toi = collective_comm(self.comm).allreduce(min(float(toi), near), op=MPI.MIN)
        return (toi, candidates) if with_candidates else toi

    def _near_pairs_2d(
        self,
        candidates: ipctk.Candidates,
        x0: np.ndarray,
        x1: np.ndarray,
        cached: Callable[[], ipctk.NormalCollisions | None],
    ) -> tuple[float, ipctk.Candidates]:
        """The collision-free fraction of x0 -> x1 for the near pairs, and the other candidates.

        A vertex resting a tiny gap d above an edge while it slides along it (soft barriers:
        ~1e-11 m apart, sliding ~1e-2 m per step) is beyond ipctk's narrow phases. AdditiveCCD
        advances by ~0.9 d / |motion| per iteration: at its 1e7-iteration cap (~1 s) it returns
        the fraction reached, orders of magnitude below the time of impact, and the Newton solve
        stalls with every step cut to it; before the cap the round-off of its ~|motion| / d
        position updates can exceed the gap, and it reports no impact where there is one
        (measured: 7e-12 m above an edge, sliding 4e-6 m, crossing at 0.49 of the step: no
        impact). Tight Inclusion refines its interval just as slowly. Such pairs (see
        ``_DRIFT_ULPS``, ``_NEAR_RATIO``) get the exact bound of :func:`_edge_vertex_bounds`
        instead: in 2D a vertex meets an edge only on the edge's line. The others keep ipctk's
        narrow phase (without near pairs, exactly as before). No near pair gets closer than
        ``_GAP_FLOOR_ULPS`` ulps of its coordinates, where round-off would decide which side of
        an edge a vertex is on.
        """
        eta = 1.0 - float(self.ccd.conservative_rescaling)
        # no pair is near if the closest pair at x0 is farther than a near pair can be (the
        # collision set at x0 is usually cached): skips the per-candidate work in most queries
        eps = np.finfo(float).eps
        motion = 4.0 * float(np.linalg.norm(x1 - x0, axis=1).max())
        coord = max(float(np.abs(x0).max()), float(np.abs(x1).max()))
        reach = max(
            np.sqrt(_DRIFT_ULPS * eps * coord * motion),
            _NEAR_RATIO * motion,
            _GAP_FLOOR_ULPS * eps * coord / eta,
        )
        if reach < self.dhat:
            mesh, C = self.surface.mesh, cached()
            if C is None:  # the whole set, the same on every rank
                C = ipctk.NormalCollisions()
                C.build(candidates, mesh, x0, self.dhat, 0.0)
                d2 = C.compute_minimum_distance(mesh, x0) if len(C) else np.inf
            else:  # this rank's share (the same decision on all ranks: collective)
                d2 = self.partition.minimum_distance(C, mesh, x0) ** 2
            if not np.isfinite(d2) or np.sqrt(d2) > reach:
                return np.inf, candidates
        ev = candidates.ev_candidates
        if not len(ev):
            return np.inf, candidates
        pairs = np.array([(c.edge_id, c.vertex_id) for c in ev], dtype=np.int64)
        bound, near, floored, floor = _edge_vertex_bounds(
            x0, x1, self.surface.mesh.edges, pairs, eta
        )
        if not near.any():
            return np.inf, candidates
        held = floored & (bound < 1.0)
        if held.any():  # for failure_report: the floor, not the barrier, holds pairs
            self.floor_held = float(floor[held].min())
        far = ipctk.Candidates()
        far.ev_candidates = [ev[int(k)] for k in np.flatnonzero(~near)]
        return float(bound[near].min()), far


def _edge_vertex_bounds(
    x0: np.ndarray, x1: np.ndarray, edges: np.ndarray, pairs: np.ndarray, eta: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per (edge, vertex) pair in 2D: a lower bound of the fraction of x0 -> x1 it stays apart.

    With p, a, b (vertex, edge ends) moving linearly in t in [0, 1], the vertex is on the
    edge's line where N(t) = (p - a) x (b - a) = c0 + c1 t + c2 t^2 vanishes; distance d(t) to
    the line is |N(t)| / |b - a|. Two lower bounds of the first t at which the distance falls to
    the margin m = max(eta d0, floor) (eta d0: ipctk's own margin, AdditiveCCD and Tight
    Inclusion keep (1 - conservative_rescaling) of the gap d0): the first root of
    |N(t)| = m |b - a|_max + err, err bounding the round-off of N including a few ulps of every
    coordinate, and (d0 - m) / (largest relative displacement), AdditiveCCD's first step. The
    larger one is returned (inf: not within the step). The floor is ``_GAP_FLOOR_ULPS`` ulps
    of the pair's largest coordinate.

    Returns:
        (bound, near, floored, floor): the bound, the pairs for which it replaces ipctk's
        (``_DRIFT_ULPS``, ``_NEAR_RATIO``, or floored), the pairs whose margin is the floor
        (eta d0 < floor) and the floor.
    """
    eps = np.finfo(float).eps
    e, v = pairs[:, 0], pairs[:, 1]
    a, b = edges[e, 0], edges[e, 1]
    p0, a0, b0 = x0[v], x0[a], x0[b]
    dp, da, db = x1[v] - p0, x1[a] - a0, x1[b] - b0
    r0, dr, s0, ds = p0 - a0, dp - da, b0 - a0, db - da

    def cross(u: np.ndarray, w: np.ndarray) -> np.ndarray:
        return u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]

    c0, c1, c2 = cross(r0, s0), cross(r0, ds) + cross(dr, s0), cross(dr, ds)
    nr, ns = np.hypot(*r0.T) + np.hypot(*dr.T), np.hypot(*s0.T) + np.hypot(*ds.T)
    ends = np.concatenate([p0, a0, b0, x1[v], x1[a], x1[b]], axis=1)
    coord = np.abs(ends).max(axis=1)
    err = 8.0 * eps * nr * ns + 8.0 * eps * coord * (nr + ns)
    floor = _GAP_FLOOR_ULPS * eps * coord
    # distance to the segment, and AdditiveCCD's displacement bound (mean motion removed)
    ss = np.maximum(np.einsum("ij,ij->i", s0, s0), np.finfo(float).tiny)
    alpha = np.clip(np.einsum("ij,ij->i", r0, s0) / ss, 0.0, 1.0)
    d0 = np.hypot(*(r0 - alpha[:, None] * s0).T)
    mean = (dp + da + db) / 3.0
    spread = np.maximum(np.hypot(*(da - mean).T), np.hypot(*(db - mean).T))
    reach = np.hypot(*(dp - mean).T) + spread
    margin = np.maximum(eta * d0, floor)
    sign = np.where(c0 < 0, -1.0, 1.0)
    B, A = sign * c1, sign * c2  # |N(t)| = |c0| + B t + A t^2 while N keeps its sign
    gap = np.abs(c0) - (margin * ns + err)
    with np.errstate(divide="ignore", invalid="ignore"):
        # first root of gap + B t + A t^2 = 0 in (0, 1] (above the margin at t = 0)
        disc = B * B - 4.0 * A * gap
        root = np.sqrt(np.maximum(disc, 0.0))
        q = -0.5 * (B + np.where(B >= 0, root, -root))
        line = np.full(len(c0), np.inf)
        for r in (q / A, gap / q):
            ok = (disc >= 0) & np.isfinite(r) & (r > 0)
            line = np.where(ok & (r < line), r, line)
        # at or below the margin already: only separating motion (B t + A t^2 >= 0) is free
        turn = np.where(
            (B > 0) & (A < 0), -B / A, np.where((B < 0) | ((B == 0) & (A < 0)), 0.0, np.inf)
        )
        line = np.where(gap > 0, line, turn)
        slack = np.maximum(d0 - margin - 4.0 * eps * coord, 0.0)
        lipschitz = np.where(reach > 0, slack / reach, np.inf)
    bound = np.maximum(line, lipschitz)
    bound = np.where(bound > 1.0, np.inf, bound)
    floored = eta * d0 < floor
    drift = d0 * d0 < _DRIFT_ULPS * eps * coord * reach
    near = drift | (d0 < _NEAR_RATIO * reach) | floored
    return bound, near, floored, floor
