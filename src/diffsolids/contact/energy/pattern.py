"""The sparsity pattern of the contact term's Newton matrix: vertex blocks of the step.

The pattern of a step is its reach pattern (the pairs of primitives within 2 dhat of each other at
u^{i-1}, computed once per step, :func:`~diffsolids.contact.detection.reach.reach_blocks`), grown by
the blocks of any rank's Hessian share outside it. It is the same on every rank (the union over the
ranks) and stays the same object while unchanged, so the solver's check of the pattern is free.
"""

import numpy as np

from diffsolids.contact.detection.collision_arrays import collision_arrays, stencil_blocks
from diffsolids.contact.detection.reach import reach_blocks
from diffsolids.contact.energy.contact_potential import ContactPotential
from diffsolids.contact.energy.evaluation import Evaluation
from diffsolids.contact.geometry.free_dofs import FreeDofs
from diffsolids.contact.geometry.surface import _contains, block_pattern
from diffsolids.contact.step import ContactStep
from diffsolids.contact.timing import timed
from diffsolids.solvers.sparsity import sorted_unique

__all__ = ["ContactPattern"]

# the matrix pattern of a step covers the pairs within this many dhat at u^{i-1}
_PATTERN_REACH = 2.0


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

    def blocks(self, ev: Evaluation, step: ContactStep) -> np.ndarray:
        """Vertex-block pattern of the Newton matrix at ev (collision + friction stencils).

        The same on all ranks (collective): the reach pattern and the blocks of every rank's
        share outside it.

        The step's :meth:`reach` itself (the same array) while it holds them all, so that the
        matrix pattern stays the same object and the solver's check is free; in a backward
        sweep (a step begun on a whole trajectory) the union of the Hessians' blocks only.
        """
        if ev.blocks is None:
            surf = self.surface
            # the barrier's blocks are its collisions' stencils (no Hessian needed for them)
            arrays = collision_arrays(ev.collisions, surf.mesh)
            needed = stencil_blocks(arrays, surf.num_vertices)
            T = ev.friction
            if T is not None:
                if step.friction_pattern is None:
                    # at zero sliding velocity the friction Hessian covers every stencil
                    zero = np.asfortranarray(np.zeros_like(ev.U))
                    H0 = self.friction_potential.hessian(T, self.surface.mesh, zero)
                    step.friction_pattern = block_pattern(
                        H0, dim=self.dim, num_vertices=surf.num_vertices
                    )
                needed = sorted_unique(needed, step.friction_pattern)
            if surf.static is not None:  # blocks of static vertices have no matrix entries
                a, b = np.divmod(needed, surf.num_vertices)
                needed = needed[~(surf.static[a] | surf.static[b])]
            # a backward sweep assembles one matrix per step: the Hessians' blocks suffice
            # (the reach cost 0.14 s of the 0.22 s pattern check per step at 44 811 dofs)
            reach = self.reach(step) if step.forward else np.zeros(0, dtype=np.int64)
            # other ranks add their Hessians' entries to the rows this rank owns: the union
            outside = self.partition.union(needed[~_contains(reach, needed)])
            ev.blocks = reach if len(outside) == 0 else sorted_unique(reach, outside)
        return ev.blocks

    def reach(self, step: ContactStep) -> np.ndarray:
        """Vertex blocks of the pairs that are near at the start of the step.

        The stencils of the pairs of primitives whose boxes at u^{i-1}, each grown by
        ``_PATTERN_REACH / 2`` dhat, overlap
        (:func:`~diffsolids.contact.detection.reach.reach_blocks`): the pattern follows the pairs
        that are near, not the size of the primitives (a coarse obstacle). Pairs that come near
        during the step are added when their Hessian needs them (a matrix rebuild, and a restart of
        the Newton solve from its iterate). Growing the boxes by how far each vertex may move in the
        step as well (rebuilds then became rare) measured slower in every scene: the structural
        zeros of the larger pattern fill every factorisation. On the paper's sliding bunny (2 799
        dofs, a tumbling body whose motion relative to its translation is 35 dhat per step) the
        matrix held 1.66 M entries instead of 0.10 M, its LU factor 3.65 M instead of 0.62 M, and
        the 10-step forward took 40.4 s instead of 10.8 s (same Newton iterations and J); the
        paper's throw 11.3 s instead of 8.0 s over 8 steps. Left out: pairs of one body that are
        neighbours on the surface at rest (not contacts), and blocks of static vertices (no matrix
        entries; a pair with a static primitive adds none but the other primitive's own, which are
        always in).
        """
        if step.reach is None:
            with timed(self.timings, "reach_pattern"):
                surf = self.surface
                step.reach = reach_blocks(
                    surf.rest_positions + step.lagged,
                    surf.rest_positions,
                    surf.edges,
                    surf.faces,
                    surf.body,
                    0.5 * _PATTERN_REACH * self.dhat,
                    static=surf.static,
                )
        return step.reach

    def matrix_pattern(
        self, ev: Evaluation, step: ContactStep, free_dofs: FreeDofs, bc_dofs: np.ndarray
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
