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
:meth:`StepBound._near_pairs_2d`); in 3D the face-vertex and edge-edge pairs as near get the
plane bound of :func:`_plane_bounds` (see :meth:`StepBound._near_pairs_3d`), vectorised over
the pairs.
"""

from collections.abc import Callable

import ipctk
import numpy as np
from mpi4py import MPI

from diffsolids.contact.geometry.candidate_ids import candidate_ids
from diffsolids.contact.geometry.distances import pair_distances
from diffsolids.contact.geometry.surface import CollisionSurface
from diffsolids.contact.partition import CollisionPartition
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
        floor_held: After a query, the smallest gap floor that held a near pair, or None.
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
        if self.surface.dim == 3 or not len(candidates.vv_candidates):
            near, far = self._near_pairs(candidates, x0, x1, cached)
        toi = far.compute_collision_free_stepsize(self.surface.mesh, x0, x1, 0.0, self.ccd)
        toi = collective_comm(self.comm).allreduce(min(float(toi), near), op=MPI.MIN)
        return (toi, candidates) if with_candidates else toi

    def _any_near(
        self,
        candidates: ipctk.Candidates,
        x0: np.ndarray,
        x1: np.ndarray,
        cached: Callable[[], ipctk.NormalCollisions | None],
        eta: float,
    ) -> bool:
        """Whether a pair can be near (collective: the same answer on all ranks).

        No pair is near if the closest pair at x0 is farther than a near pair can be (the
        collision set at x0 is usually cached): skips the per-candidate work in most queries.
        """
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
                return False
        return True

    def _near_pairs(
        self,
        candidates: ipctk.Candidates,
        x0: np.ndarray,
        x1: np.ndarray,
        cached: Callable[[], ipctk.NormalCollisions | None],
    ) -> tuple[float, ipctk.Candidates]:
        """The collision-free fraction of x0 -> x1 for the near pairs, and the other candidates.

        A vertex resting a tiny gap d above an edge (2D) or a triangle (3D) while it slides
        along it, or two edges as close sliding across each other (soft barriers: ~1e-11 m
        apart, sliding ~1e-2 m per step), is beyond ipctk's narrow phases. AdditiveCCD advances
        by ~0.9 d / |motion| per iteration: at its 1e7-iteration cap (~1 s) it returns the
        fraction reached, orders of magnitude below the time of impact, and the Newton solve
        stalls with every step cut to it; before the cap the round-off of its ~|motion| / d
        position updates can exceed the gap, and it reports no impact where there is one
        (measured: 7e-12 m above an edge, sliding 4e-6 m, crossing at 0.49 of the step: no
        impact). Tight Inclusion refines its interval just as slowly. Such pairs (see
        ``_DRIFT_ULPS``, ``_NEAR_RATIO``) get a closed-form bound vectorised over the pairs: in
        2D the exact one of :func:`_edge_vertex_bounds` (a vertex meets an edge only on the
        edge's line), in 3D the plane bound of :func:`_plane_bounds` (a point meets a triangle
        only on its plane, two edges meet only where their lines do; conservative where the
        plane is: a vertex sliding off a triangle over a convex crease is stopped where it
        would cross that triangle's plane). A 3D near pair whose plane test gives nothing at x0
        (the vertex beside the triangle, close to its plane; nearly parallel edges) keeps
        ipctk's narrow phase unless it is floored. The others keep ipctk's narrow phase
        (without near pairs, exactly as before). No near pair gets closer than
        ``_GAP_FLOOR_ULPS`` ulps of its coordinates, where round-off would decide which side
        of an edge a vertex is on.
        """
        eta = 1.0 - float(self.ccd.conservative_rescaling)
        kinds = _near_pair_kinds(candidates, self.surface.mesh)
        if not any(len(cands) for _, cands, _ in kinds):
            return np.inf, candidates
        if not self._any_near(candidates, x0, x1, cached, eta):
            return np.inf, candidates
        radius = _near_radius(x0, x1, eta)
        bound, held = np.inf, np.inf
        far = ipctk.Candidates()
        bounded = [name for name, _, _ in kinds]
        for name in ("ev_candidates", "vv_candidates", "fv_candidates", "ee_candidates"):
            if name not in bounded:
                setattr(far, name, getattr(candidates, name))
        for name, cands, pair_bounds in kinds:
            if not len(cands):
                continue
            b, near, floored, floor = pair_bounds(x0, x1, eta, radius)
            if near.any():
                bound = min(bound, float(b[near].min()))
            h = floored & near & (b < 1.0)
            if h.any():
                held = min(held, float(floor[h].min()))
            setattr(far, name, _without(cands, np.flatnonzero(near)))
        if np.isfinite(held):  # for failure_report: the floor, not the barrier, holds pairs
            self.floor_held = held
        return bound, far


def _without(items: list, dropped: np.ndarray) -> list:
    """``items`` less the entries at the sorted indices ``dropped``."""
    if len(dropped) > 64:
        keep = np.ones(len(items), dtype=bool)
        keep[dropped] = False
        return [items[int(k)] for k in np.flatnonzero(keep)]
    out = list(items)
    for k in dropped[::-1]:
        del out[int(k)]
    return out


def _near_radius(x0: np.ndarray, x1: np.ndarray, eta: float) -> float:
    """A distance at x0 beyond which no pair of the path x0 -> x1 is near.

    The near tests of :func:`_with_displacement_bound` with the largest coordinate of the
    path and 4 x its largest vertex displacement, which bounds every pair's reach.
    """
    eps = np.finfo(float).eps
    coord = max(float(np.abs(x0).max()), float(np.abs(x1).max()))
    reach = 4.0 * float(np.sqrt(np.einsum("ij,ij->i", x1 - x0, x1 - x0).max()))
    radius = max(
        np.sqrt(_DRIFT_ULPS * eps * coord * reach),
        _NEAR_RATIO * reach,
        _GAP_FLOOR_ULPS * eps * coord / eta,
    )
    return 1.01 * radius


def _boxes_within(x: np.ndarray, first: list, second: list, radius: float) -> np.ndarray:
    """Pairs whose bounding boxes at x are within ``radius`` of each other.

    A pair's primitives have the vertex id arrays ``first`` and ``second``; the distance of
    their boxes bounds the primitives' distance from below.
    """
    a, b = np.stack([x[k] for k in first], axis=1), np.stack([x[k] for k in second], axis=1)
    gap = np.maximum(np.maximum(a.min(axis=1) - b.max(axis=1), b.min(axis=1) - a.max(axis=1)), 0)
    return np.einsum("ij,ij->i", gap, gap) <= radius * radius


def _bounds_within(bounds: Callable, corners: list, n: int, mask: np.ndarray) -> tuple:
    """``bounds(corners)`` on the pairs of ``mask``; the others not near (bound inf)."""
    out = (np.full(n, np.inf), np.zeros(n, bool), np.zeros(n, bool), np.zeros(n))
    if mask.any():
        for full, part in zip(out, bounds([k[mask] for k in corners]), strict=True):
            full[mask] = part
    return out


def _near_pair_kinds(candidates: ipctk.Candidates, mesh: ipctk.CollisionMesh) -> list[tuple]:
    """(candidate list name, the candidates, their bounds ``f(x0, x1, eta, radius)``) per kind.

    2D: vertex-edge pairs (:func:`_edge_vertex_bounds`); 3D: face-vertex and edge-edge pairs
    (:func:`_plane_bounds`). Pairs farther apart at x0 than ``radius`` (:func:`_near_radius`)
    are not near and are not bounded.
    """
    if mesh.dim == 2:
        ev = candidates.ev_candidates

        def ev_bounds(x0: np.ndarray, x1: np.ndarray, eta: float, radius: float) -> tuple:
            pairs = candidate_ids(ev, "edge_id", "vertex_id")
            edge = mesh.edges[pairs[:, 0]]
            mask = _boxes_within(x0, [pairs[:, 1]], [edge[:, 0], edge[:, 1]], radius)

            def bounds(cols: list) -> tuple:
                return _edge_vertex_bounds(x0, x1, mesh.edges, np.column_stack(cols), eta)

            return _bounds_within(bounds, [pairs[:, 0], pairs[:, 1]], len(pairs), mask)

        return [("ev_candidates", ev, ev_bounds)]
    fv, ee = candidates.fv_candidates, candidates.ee_candidates

    def fv_bounds(x0: np.ndarray, x1: np.ndarray, eta: float, radius: float) -> tuple:
        ids = candidate_ids(fv, "face_id", "vertex_id")
        tri = mesh.faces[ids[:, 0]]
        corners = [ids[:, 1], tri[:, 0], tri[:, 1], tri[:, 2]]
        mask = _boxes_within(x0, corners[:1], corners[1:], radius)

        def bounds(cols: list) -> tuple:
            return _plane_bounds(x0, x1, cols, "fv", eta)

        return _bounds_within(bounds, corners, len(ids), mask)

    def ee_bounds(x0: np.ndarray, x1: np.ndarray, eta: float, radius: float) -> tuple:
        ids = candidate_ids(ee, "edge0_id", "edge1_id")
        e0, e1 = mesh.edges[ids[:, 0]], mesh.edges[ids[:, 1]]
        corners = [e0[:, 0], e0[:, 1], e1[:, 0], e1[:, 1]]
        mask = _boxes_within(x0, corners[:2], corners[2:], radius)

        def bounds(cols: list) -> tuple:
            return _plane_bounds(x0, x1, cols, "ee", eta)

        return _bounds_within(bounds, corners, len(ids), mask)

    return [("fv_candidates", fv, fv_bounds), ("ee_candidates", ee, ee_bounds)]


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
    bound, near, floored = _with_displacement_bound(line, d0, margin, coord, reach, eta, floor)
    return bound, near, floored, floor


def _with_displacement_bound(
    crossing: np.ndarray,
    gap: np.ndarray,
    margin: np.ndarray,
    coord: np.ndarray,
    reach: np.ndarray,
    eta: float,
    floor: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The larger of a crossing bound and AdditiveCCD's displacement bound; the near pairs.

    The displacement bound is (gap - margin) / reach, reach the largest relative displacement
    of the pair's points. A pair is near where its gap is below sqrt(``_DRIFT_ULPS`` ulp
    reach) or ``_NEAR_RATIO`` reach, or floored (eta gap below the floor).

    Returns:
        (bound, near, floored): the bound (inf: not within the step) and the two masks.
    """
    eps = np.finfo(float).eps
    with np.errstate(divide="ignore", invalid="ignore"):
        slack = np.maximum(gap - margin - 4.0 * eps * coord, 0.0)
        lipschitz = np.where(reach > 0, slack / reach, np.inf)
    bound = np.maximum(crossing, lipschitz)
    bound = np.where(bound > 1.0, np.inf, bound)
    floored = eta * gap < floor
    drift = gap * gap < _DRIFT_ULPS * eps * coord * reach
    near = drift | (gap < _NEAR_RATIO * reach) | floored
    return bound, near, floored


def _cubic(a0: np.ndarray, a1: np.ndarray, a2: np.ndarray, a3: np.ndarray, t: float) -> np.ndarray:
    """a0 + a1 t + a2 t^2 + a3 t^3, row-wise."""
    return a0 + t * (a1 + t * (a2 + t * a3))


def _first_zero(a0: np.ndarray, a1: np.ndarray, a2: np.ndarray, a3: np.ndarray) -> np.ndarray:
    """A lower bound of the first zero in [0, 1] of L(t) = a0 + a1 t + a2 t^2 + a3 t^3.

    0 where L(0) <= 0, inf where L has no zero in [0, 1]. On 32 sub-intervals L is bounded from
    below by L(t_i) + L'(t_i) tau - max|L''| tau^2 / 2.
    """
    curv = np.maximum(np.abs(2.0 * a2), np.abs(2.0 * a2 + 6.0 * a3))  # max |L''| on [0, 1]
    zero = np.where(a0 > 0, np.inf, 0.0)
    pieces = 32
    h = 1.0 / pieces
    open_ = a0 > 0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for i in range(pieces):
            if not open_.any():
                break
            t = i * h
            value = _cubic(a0, a1, a2, a3, t)
            slope = a1 + t * (2.0 * a2 + 3.0 * t * a3)
            # first tau > 0 with value + slope tau - curv tau^2 / 2 = 0 (value > 0), in the
            # form without cancellation for either sign of the slope
            root = np.sqrt(slope * slope + 2.0 * curv * np.maximum(value, 0.0))
            tau = np.where(slope < 0, 2.0 * value / (root - slope), (slope + root) / curv)
            tau = np.where(value > 0, np.where(np.isnan(tau), np.inf, tau), 0.0)
            hit = open_ & (tau < h)
            zero = np.where(hit, t + np.maximum(tau, 0.0), zero)
            open_ &= ~hit
    return zero


def _plane_bounds(
    x0: np.ndarray, x1: np.ndarray, corners: list[np.ndarray], kind: str, eta: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per 3D pair: a lower bound of the fraction of x0 -> x1 it stays apart (vectorised).

    ``kind`` "fv": corners (p, a, b, c), a vertex and a triangle; "ee": (a0, a1, b0, b1), two
    edges. With r, s, w = p - a, b - a, c - a (fv) or b0 - a0, a1 - a0, b1 - b0 (ee), all
    linear in t, N(t) = r . (s x w) = c0 + c1 t + c2 t^2 + c3 t^3 and |N(t)| / |s x w| is the
    distance to the triangle's plane (between the edges' lines), a lower bound of the pair's
    distance. With sigma the sign of c0, |N| >= sigma N: the pair stays farther than the margin
    m = max(eta d0, floor) (d0 the plane distance at x0, floor ``_GAP_FLOOR_ULPS`` ulps of its
    largest coordinate) while L(t) = sigma N(t) - (m n_max + err) > 0, n_max bounding |s x w|
    over the step and err the round-off of N. The first zero of L is bounded from below on 32
    sub-intervals by L(t_i) + L'(t_i) tau - max|L''| tau^2 / 2 (:func:`_first_zero`); where L
    is positive again at t = 1 and the plane distance stays above the floor over the whole
    step, the pair does not bound it (a dip inside the step only). The displacement bound
    (d0 - m) / (largest relative displacement of the pair's points) holds too; the larger of
    the two is returned (inf: not within the step). Pairs with L(0) <= 0 (the plane test
    says nothing) are near only when floored, with the displacement bound alone.

    Returns:
        (bound, near, floored, floor) as :func:`_edge_vertex_bounds`.
    """
    eps = np.finfo(float).eps
    P0 = [x0[k] for k in corners]
    D = [x1[k] - q for k, q in zip(corners, P0, strict=True)]
    if kind == "fv":
        r0, s0, w0 = P0[0] - P0[1], P0[2] - P0[1], P0[3] - P0[1]
        dr, ds, dw = D[0] - D[1], D[2] - D[1], D[3] - D[1]
    else:
        r0, s0, w0 = P0[2] - P0[0], P0[1] - P0[0], P0[3] - P0[2]
        dr, ds, dw = D[2] - D[0], D[1] - D[0], D[3] - D[2]

    def dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", u, v)

    def norm(u: np.ndarray) -> np.ndarray:
        return np.sqrt(dot(u, u))

    X0, X1, X2 = np.cross(s0, w0), np.cross(s0, dw) + np.cross(ds, w0), np.cross(ds, dw)
    c0, c1 = dot(r0, X0), dot(r0, X1) + dot(dr, X0)
    c2, c3 = dot(r0, X2) + dot(dr, X1), dot(dr, X2)
    nr, ns, nw = norm(r0) + norm(dr), norm(s0) + norm(ds), norm(w0) + norm(dw)
    n0 = norm(X0)
    n_max = np.minimum(ns * nw, n0 + norm(X1) + norm(X2))
    ends = np.concatenate(P0 + [q + d for q, d in zip(P0, D, strict=True)], axis=1)
    coord = np.abs(ends).max(axis=1)
    err = 32.0 * eps * (nr * ns * nw + coord * (ns * nw + nr * nw + nr * ns))
    floor = _GAP_FLOOR_ULPS * eps * coord
    with np.errstate(divide="ignore", invalid="ignore"):
        d0 = np.where(n0 > 0, np.abs(c0) / n0, 0.0)  # to the plane (between the lines)
    # the pair's distance at x0 decides whether it is near (a vertex beside a triangle, close
    # to its plane, is not: the plane test would stop it for nothing)
    dist = pair_distances(P0, kind)
    mean = sum(D) / 4.0
    if kind == "fv":
        reach = norm(D[0] - mean) + np.max([norm(d - mean) for d in D[1:]], axis=0)
    else:
        reach = np.maximum(norm(D[0] - mean), norm(D[1] - mean)) + np.maximum(
            norm(D[2] - mean), norm(D[3] - mean)
        )
    margin = np.maximum(eta * np.minimum(d0, dist), floor)
    sign = np.where(c0 < 0, -1.0, 1.0)
    a1, a2, a3 = sign * c1, sign * c2, sign * c3
    a0 = np.abs(c0) - (margin * n_max + err)
    plane = _first_zero(a0, a1, a2, a3)
    # A pair whose plane distance dips below the margin inside the step only (a rotating
    # triangle: linear paths of its corners bend the vertex's path relative to it) and is back
    # above the margin at the end does not collide if the distance stays above the floor: the
    # whole step is free (the margin keeps the end points, where the barrier is evaluated, off
    # the floor).
    dip = (plane <= 1.0) & (_cubic(a0, a1, a2, a3, 1.0) > 0)
    if dip.any():
        through = _first_zero(np.abs(c0) - (floor * n_max + err), a1, a2, a3)
        plane = np.where(dip & (through > 1.0), np.inf, plane)
    bound, near, floored = _with_displacement_bound(plane, dist, margin, coord, reach, eta, floor)
    return bound, near & ((a0 > 0) | floored), floored, floor
