"""The sparsity pattern of the contact term's Newton matrix: vertex blocks of the step.

The pattern of a step is its reach pattern (the pairs of primitives that can meet in the step,
computed once per step from u^{i-1} and how far each vertex may move,
:func:`~diffsolids.contact.reach.reach_blocks`), grown by the blocks of any rank's Hessian
share outside it. It is the same on every rank (the union over the ranks) and stays the same
object while unchanged, so the solver's check of the pattern is free.
"""

import numpy as np

from diffsolids.contact.evaluation import Evaluation
from diffsolids.contact.free_dofs import FreeDofs
from diffsolids.contact.potential import ContactPotential
from diffsolids.contact.reach import reach_blocks
from diffsolids.contact.surface import _contains, block_pattern
from diffsolids.contact.timing import timed
from diffsolids.solvers.sparsity import sorted_unique

__all__ = ["ContactPattern"]

# the matrix pattern of a step covers the pairs within this many dhat at u^{i-1} (plus motion)
_PATTERN_REACH = 2.0
# ... when no vertex moves farther than this times the step's estimate (reach.step_motion)
_MOTION_FACTOR = 1.0


class ContactPattern:
    """Vertex-block and matrix pattern of the contact Hessian (exact + friction stencils).

    Args:
        potential: The Hessian at an evaluation; its collision surface, partition over the
            ranks (the union of their blocks), friction potential (its stencils), dhat and
            timers are those of the pattern.
    """

    def __init__(self, potential: ContactPotential) -> None:
        self.surface = potential.surface
        self.partition = potential.partition
        self.potential = potential
        self.friction_potential = potential.friction_potential
        self.dhat = potential.dhat
        self.dim = potential.surface.dim
        self.timings = potential.timings
        self._memo: tuple | None = None

    def blocks(self, ev: Evaluation, step: dict) -> np.ndarray:
        """Vertex-block pattern of the Newton matrix at ev (exact Hessian + friction stencils).

        The same on all ranks (collective): the reach pattern and the blocks of every rank's
        share outside it.

        The step's :meth:`reach` itself (the same array) while it holds them all, so that the
        matrix pattern stays the same object and the solver's check is free.
        """
        if ev.blocks is None:
            parts = [self.potential.hessian(ev)]
            T = ev.extras["friction"]
            if T is not None:
                if "friction_pattern" not in step:
                    # at zero sliding velocity the friction Hessian covers every stencil
                    zero = np.asfortranarray(np.zeros_like(ev.U))
                    step["friction_pattern"] = self.friction_potential.hessian(
                        T, self.surface.mesh, zero
                    )
                parts.append(step["friction_pattern"])
            surf = self.surface
            needed = block_pattern(*parts, dim=self.dim, num_vertices=surf.num_vertices)
            if surf.static is not None:  # blocks of static vertices have no matrix entries
                a, b = np.divmod(needed, surf.num_vertices)
                needed = needed[~(surf.static[a] | surf.static[b])]
            reach = self.reach(step)
            # other ranks add their Hessians' entries to the rows this rank owns: the union
            outside = self.partition.union(needed[~_contains(reach, needed)])
            ev.blocks = reach if len(outside) == 0 else sorted_unique(reach, outside)
        return ev.blocks

    def reach(self, step: dict) -> np.ndarray:
        """Vertex blocks of the pairs that can meet in the step: a superset for the whole step.

        The stencils of the pairs of primitives whose boxes at u^{i-1}, each grown by
        ``_PATTERN_REACH / 2`` dhat plus how far its vertices may move in the step (the step's
        ``motion`` and ``deformation``, :func:`~diffsolids.contact.reach.step_motion`; relative
        to their body for pairs of one body), overlap
        (:func:`~diffsolids.contact.reach.reach_blocks`). So a new contact rarely needs a
        larger matrix (a rebuild and a new symbolic factorisation), and the pattern follows
        the pairs that are near, not the size of the primitives (a coarse obstacle). Left out:
        pairs of one body that are neighbours on the surface at rest (not contacts), and blocks
        of static vertices (no matrix entries; a pair with a static primitive adds none but the
        other primitive's own, which are always in).
        """
        if "reach" not in step:
            with timed(self.timings, "reach_pattern"):
                surf = self.surface
                step["reach"] = reach_blocks(
                    surf.rest_positions + step["lagged"],
                    surf.rest_positions,
                    surf.edges,
                    surf.faces,
                    surf.body,
                    0.5 * _PATTERN_REACH * self.dhat,
                    _MOTION_FACTOR * step["motion"],
                    _MOTION_FACTOR * step["deformation"],
                    surf.static,
                )
        return step["reach"]

    def matrix_pattern(
        self, ev: Evaluation, step: dict, free_dofs: FreeDofs, bc_dofs: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Global (rows, cols) of the matrix entries at ev (owned rows, free dofs; collective).

        The same arrays while the blocks and the Dirichlet dofs are unchanged: the solver then
        skips its checks.
        """
        blocks = self.blocks(ev, step)
        free = free_dofs.mask(bc_dofs)
        memo = self._memo
        same = memo is not None and (memo[0] is blocks or np.array_equal(memo[0], blocks))
        if same and memo[1] == free_dofs.key:
            return memo[2]
        with timed(self.timings, "pattern"):
            entries = self.surface.matrix_entries(blocks, free)
        self._memo = (blocks, free_dofs.key, entries)
        return entries
