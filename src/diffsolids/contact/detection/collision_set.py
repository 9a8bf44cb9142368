"""The collision set of the contact term: this rank's share, built at given positions.

:class:`CollisionBuilder` builds ipctk's NormalCollisions on the whole collision surface (the
same on every rank) and keeps this rank's share
(:meth:`~diffsolids.contact.partition.CollisionPartition.keep_share`). The sets with weight
gradients (shape derivatives) are kept for the last two positions; a set at a point of the
segment the last CCD swept reuses its candidates (only the narrow phase runs).
"""

import ipctk
import numpy as np

from diffsolids.contact.detection.step_bound import _CCD_REACH
from diffsolids.contact.geometry.surface import CollisionSurface
from diffsolids.contact.partition import CollisionPartition
from diffsolids.errors import ParameterError

__all__ = ["FORMULATIONS", "CollisionBuilder", "new_collision_set"]

#: The barrier formulations of :class:`~diffsolids.contact.ContactTerm` (``formulation``).
FORMULATIONS = ("convergent", "ipc")
# a line search point on the CCD's segment reuses the segment's candidates (no broad phase) while
# they are at most this many times the candidates of the last whole build: the segment's boxes
# cover the swept path inflated by dhat, ~2.5x a build's candidates in the median but up to
# ~100x where pairs rest far inside dhat (each candidate costs ~1 us in the narrow phase)
_SEGMENT_REUSE_RATIO = 8


def new_collision_set(
    formulation: str, area_weighting: bool, shape_derivatives: bool = False
) -> ipctk.NormalCollisions:
    """An empty ipctk collision set of a formulation, to be built.

    Args:
        formulation: "convergent": the improved max approximation of Li et al. 2023 (ipctk's
            ``IMPROVED_MAX_APPROX``; area weighting required), whose face, edge and vertex
            terms add up to one barrier of the distance to a flat or smooth surface whatever
            its triangulation; "ipc": one term per closest primitive pair (the IPC paper's).
        area_weighting: Weight each collision by its surface area.
        shape_derivatives: Keep the weights' gradients w.r.t. the rest positions.

    Raises:
        ParameterError: An unknown formulation, or "convergent" without area weighting.
    """
    if formulation not in FORMULATIONS:
        raise ParameterError(
            f"contact formulation {formulation!r}: expected one of {', '.join(FORMULATIONS)}"
        )
    if formulation == "convergent" and not area_weighting:
        raise ParameterError(
            "contact formulation 'convergent' needs area_weighting=True (its terms cancel by "
            "their area weights); use formulation='ipc' without area weights"
        )
    C = ipctk.NormalCollisions()
    C.use_area_weighting = area_weighting
    kinds = ipctk.NormalCollisions.CollisionSetType
    C.collision_set_type = kinds.IMPROVED_MAX_APPROX if formulation == "convergent" else kinds.IPC
    C.enable_shape_derivatives = shape_derivatives
    return C


class CollisionBuilder:
    """This rank's share of the collision set at given positions of a collision surface.

    Args:
        surface: The collision surface (its mesh and static mask at build time).
        broad_phase: ipctk broad phase of the builds.
        partition: Which collisions this rank keeps.
        dhat: Barrier activation distance.
        area_weighting: Weight each collision by its surface area.
        formulation: One of ``FORMULATIONS`` (:func:`new_collision_set`).

    Attributes:
        segment: (U0, dU, candidates, token) of the last CCD step (``ContactTerm.max_step``),
            or None: the candidates of the segment U0 + t dU, t in [0, ``_CCD_REACH``], valid
            while the term's evaluation token is ``token``.
    """

    def __init__(
        self,
        surface: CollisionSurface,
        broad_phase: ipctk.BroadPhase,
        partition: CollisionPartition,
        dhat: float,
        area_weighting: bool,
        formulation: str = "ipc",
    ) -> None:
        new_collision_set(formulation, area_weighting)  # refuses a bad pair here
        self.formulation = formulation
        self.surface = surface
        self.broad_phase = broad_phase
        self.partition = partition
        self.dhat = dhat
        self.area_weighting = area_weighting
        self.segment: tuple | None = None
        self._whole_candidates = 0  # candidates of the last whole build
        self._shape_builds: list[tuple] = []

    def build(self, x: np.ndarray, shape_derivatives: bool = False) -> ipctk.NormalCollisions:
        """This rank's share of the collision set at positions x (weight gradients when asked).

        The whole set is built on every rank (the same on all), then only this rank's
        collisions are kept (:meth:`CollisionPartition.keep_share`).

        The sets with weight gradients are kept for the last two positions (same collision mesh
        and static mask): the adjoint of step i builds them at x^i and, for the lagged
        friction, at x^{i-1}, where the adjoint of step i - 1 needs its own again.
        """
        surf = self.surface
        if shape_derivatives:
            kept = self.kept_shape_set(x)
            if kept is not None:
                return kept
        C = self.whole_set(x, shape_derivatives)
        self.partition.keep_share(C)
        if shape_derivatives:
            self._shape_builds = [(surf.mesh, surf.static, np.array(x), C), *self._shape_builds[:1]]
        return C

    def kept_shape_set(self, x: np.ndarray) -> ipctk.NormalCollisions | None:
        """The kept set with weight gradients at positions x on the current surface, or None."""
        surf = self.surface
        for mesh, static, xc, C in self._shape_builds:
            if mesh is surf.mesh and static is surf.static and np.array_equal(xc, x):
                return C
        return None

    def whole_set(self, x: np.ndarray, shape_derivatives: bool = False) -> ipctk.NormalCollisions:
        """The whole collision set at positions x (the same on every rank)."""
        C = new_collision_set(self.formulation, self.area_weighting, shape_derivatives)
        candidates = ipctk.Candidates()
        x = np.asfortranarray(x)
        candidates.build(self.surface.mesh, x, 0.5 * self.dhat, self.broad_phase)
        self._whole_candidates = len(candidates)
        self._build(C, candidates, x)
        return C

    def _build(
        self, C: ipctk.NormalCollisions, candidates: ipctk.Candidates, x: np.ndarray
    ) -> None:
        """Build C from the candidates, flat obstacle regions treated as planes."""
        flat = self.surface.flat
        if flat:
            candidates = flat.filter(candidates)
            if self.formulation == "ipc":
                candidates = flat.nearest(candidates, x, self.surface.mesh)
        C.build(candidates, self.surface.mesh, x, self.dhat, 0.0)
        if flat and self.formulation == "convergent":
            flat.correct(C, self.surface.mesh)

    def build_on_segment(self, U: np.ndarray, x: np.ndarray, token: int) -> ipctk.NormalCollisions:
        """Collision set at x, reusing the CCD candidates when x lies on the last checked step.

        The line search only visits points x0 + t dx, t in [0, 1], of the segment the CCD swept
        (to 2 dx) with boxes inflated by dhat: its candidates contain every pair within dhat
        there, so only the narrow phase runs, unless they are more than
        ``_SEGMENT_REUSE_RATIO`` times the last whole build's. ``token``: the term's current
        evaluation token (the segment is reused only if it was swept under the same one).
        """
        seg = self.segment
        if seg is not None:
            U0, dU, candidates, seg_token = seg
            if seg_token == token and len(candidates) <= _SEGMENT_REUSE_RATIO * max(
                self._whole_candidates, 1
            ):
                diff = U - U0
                t = float(np.vdot(diff, dU) / np.vdot(dU, dU))
                tol = 1e-10 * (np.abs(U0).max() + np.abs(dU).max())
                if -1e-12 <= t <= _CCD_REACH and np.abs(diff - t * dU).max() <= tol:
                    C = new_collision_set(self.formulation, self.area_weighting)
                    self._build(C, candidates, np.asfortranarray(x))
                    return self.partition.keep_share(C)
        return self.build(x)
