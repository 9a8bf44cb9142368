"""Jacobian matrices whose sparsity grows beyond the finite-element pattern (contact).

The FE sparsity from DOLFINx couples dofs of the same cell only; a numeric term such as contact
couples dofs of different bodies, and which ones changes with the configuration. Numeric terms
with a ``matrix_pattern(u, bc_dofs) -> (rows, cols)`` method (global indices, owned rows) declare
the entries they will add; :class:`GrowingPattern` keeps a matrix whose exact (preallocated,
no-malloc) pattern contains the FE pattern and those entries, rebuilding it with the union pattern
only when new entries appear. While the pattern is unchanged the same matrix object is reused, so
the direct solver keeps its symbolic factorisation.
"""

import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol

import dolfinx.fem.petsc as fem_petsc
import numpy as np
from dolfinx import fem
from mpi4py import MPI
from petsc4py import PETSc

from diffsolids.parallel import collective_comm

if TYPE_CHECKING:
    from diffsolids.model import Model
    from diffsolids.model.numeric import NumericTerm

__all__ = ["GrowingPattern", "JacobianOwner", "matrix_with_pattern", "sorted_unique"]


class JacobianOwner(Protocol):
    """What :class:`GrowingPattern` reads of its solver (met by :class:`NewtonSolver`)."""

    A: PETSc.Mat
    jacobian_form: fem.Form
    model: "Model"
    u: fem.Function
    numeric_terms: "Sequence[NumericTerm]"


def sorted_unique(*arrays: np.ndarray) -> np.ndarray:
    """Sorted unique values of the concatenated integer arrays (``np.unique`` by sorting).

    NumPy 2.3+ finds unique integers with a hash table; for the 10^5-10^7 scattered int64
    matrix keys here that measured 30-40x slower than a sort (numpy 2.5, 1.5e6 keys: 2.7 s
    against 0.07 s), and it was most of a contact Newton iteration's pattern work.

    Args:
        arrays: One or more integer arrays (any shape).
    """
    s = np.sort(np.concatenate([np.ravel(a) for a in arrays]))
    keep = np.ones(len(s), dtype=bool)
    np.not_equal(s[1:], s[:-1], out=keep[1:])
    return s[keep]


def _keys_of(A: PETSc.Mat) -> np.ndarray:
    """Sorted global keys row * N + col of the stored entries of the owned rows of A."""
    indptr, cols, _ = A.getValuesCSR()
    rstart, rend = A.getOwnershipRange()
    rows = np.repeat(np.arange(rstart, rend, dtype=np.int64), np.diff(indptr))
    return np.sort(rows * A.getSize()[1] + cols.astype(np.int64))


def matrix_with_pattern(like: PETSc.Mat, keys: np.ndarray) -> PETSc.Mat:
    """A new matrix shaped like ``like`` whose pattern contains exactly ``keys`` (sorted row*N+col).

    For block (BAIJ) matrices the pattern is the set of blocks holding a key. The entries are
    preallocated and inserted as zeros; inserting outside them is an error.
    """
    N = like.getSize()[1]
    rstart, rend = like.getOwnershipRange()
    rows, cols = np.divmod(keys, N)
    bs = like.getBlockSize() if "baij" in like.getType() else 1
    if bs > 1:  # block CSR over the blocks that hold a key
        blocks = sorted_unique((rows // bs) * (N // bs) + cols // bs)
        rows, cols = np.divmod(blocks, N // bs)
        rstart, rend = rstart // bs, rend // bs
    indptr = np.searchsorted(rows, np.arange(rstart, rend + 1))
    B = PETSc.Mat().create(like.getComm())
    B.setSizes(like.getSizes())
    B.setBlockSizes(*like.getBlockSizes())
    B.setType(like.getType())
    B.setPreallocationCSR((indptr.astype(PETSc.IntType), cols.astype(PETSc.IntType)))
    B.setLGMap(*like.getLGMap())
    B.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
    near_null_space = like.getNearNullSpace()
    if near_null_space.handle:
        B.setNearNullSpace(near_null_space)
    return B


class GrowingPattern:
    """Keeps Jacobian matrices large enough for the numeric terms of a NewtonSolver.

    Args:
        solver: The NewtonSolver (its Jacobian form, Dirichlet conditions and numeric terms).

    Attributes:
        rebuilds: Number of matrices rebuilt with a larger pattern.
        misses: Checks by :meth:`missing` that found entries lacking (the Newton solver then
            restarts with a larger matrix; the numeric terms' patterns should make this rare).
        seconds: Time spent checking and rebuilding patterns (excluding the terms' own work,
            e.g. the contact Hessian, which the next Jacobian reuses).
        rebuild_seconds: Part of ``seconds`` spent creating matrices.
    """

    def __init__(self, solver: JacobianOwner) -> None:
        self.solver = solver
        self.terms = [t for t in solver.numeric_terms if t.grows_pattern]
        self._keys: dict[int, np.ndarray] = {}
        self._fe_keys: np.ndarray | None = None
        self.rebuilds = 0
        self.misses = 0
        self.seconds = 0.0
        self.rebuild_seconds = 0.0
        self._term_seconds = 0.0
        # per term: the (rows, cols) arrays it returned last and their keys; terms return the
        # same array objects while their pattern is unchanged, which skips all the work
        self._last: dict[int, tuple] = {}
        self._verified: tuple | None = None

    @property
    def active(self) -> bool:
        """Whether any numeric term declares matrix entries."""
        return bool(self.terms)

    def _present(self, A: PETSc.Mat) -> np.ndarray:
        handle = A.handle
        if handle not in self._keys:
            if not A.assembled:
                s = self.solver
                fem_petsc.assemble_matrix(A, s.jacobian_form, s.model.bcs, diag=1.0)
                A.assemble()
            A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
            self._keys[handle] = _keys_of(A)
            if self._fe_keys is None:
                self._fe_keys = self._keys[handle]
        return self._keys[handle]

    def _term_keys(self) -> tuple[list[np.ndarray], bool]:
        """Sorted keys each term needs at u, and whether all are the ones returned last time."""
        s = self.solver
        bc = s.model.dirichlet_dofs()
        N = s.A.getSize()[1]
        keys, same = [], True
        for term in self.terms:
            t0 = time.perf_counter()
            rows, cols = term.matrix_pattern(s.u, bc)
            self._term_seconds += time.perf_counter() - t0
            last = self._last.get(id(term))
            if last is not None and last[0] is rows and last[1] is cols:
                keys.append(last[2])
                continue
            same = False
            k = sorted_unique(
                np.asarray(rows, dtype=np.int64) * N + np.asarray(cols, dtype=np.int64)
            )
            self._last[id(term)] = (rows, cols, k)
            keys.append(k)
        return keys, same

    def _needed(self) -> np.ndarray:
        keys, _ = self._term_keys()
        if len(keys) == 1:
            return keys[0]
        return sorted_unique(np.zeros(0, dtype=np.int64), *keys)

    def missing(self, A: PETSc.Mat) -> bool:
        """Whether A lacks entries the terms need at the solver's current u (collective)."""
        lacking = self._lacking(A)
        self.misses += lacking
        return lacking

    def _lacking(self, A: PETSc.Mat) -> bool:
        if not self.terms:
            return False
        t0, inner = time.perf_counter(), self._term_seconds
        present = self._present(A)
        keys, same = self._term_keys()
        if same and self._verified == (A.handle, len(present)):
            lacking = False  # the same entries were found in this very matrix before
        else:
            lacking = False
            for needed in keys:
                pos = np.minimum(np.searchsorted(present, needed), max(len(present) - 1, 0))
                lacking |= bool(len(needed)) and not np.all(present[pos] == needed)
        self.seconds += time.perf_counter() - t0 - (self._term_seconds - inner)
        lacking = collective_comm(A.getComm().tompi4py()).allreduce(lacking, op=MPI.LOR)
        self._verified = None if lacking else (A.handle, len(present))
        return lacking

    def ensure(self, A: PETSc.Mat) -> PETSc.Mat:
        """A itself if it holds all needed entries, else a new matrix with the union pattern.

        The union keeps earlier extra entries unless they outnumber the needed ones 4:1 (then
        the pattern restarts from FE + needed), so a sliding contact does not grow it forever.
        """
        if not self._lacking(A):
            return A
        t0, inner = time.perf_counter(), self._term_seconds
        present, needed = self._present(A), self._needed()
        extra = len(present) - len(self._fe_keys)
        base = present if extra <= 4 * len(needed) + 1000 else self._fe_keys
        B = matrix_with_pattern(A, sorted_unique(base, needed))
        self._keys[B.handle] = _keys_of(B)
        B.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
        self.rebuilds += 1
        elapsed = time.perf_counter() - t0 - (self._term_seconds - inner)
        self.seconds += elapsed
        self.rebuild_seconds += elapsed
        return B

    def restart(self, A: PETSc.Mat) -> PETSc.Mat:
        """A matrix with the FE pattern only (A itself if it has no other entries).

        A run that starts from the FE pattern grows the same patterns whatever ran before,
        so its factorisations, and its states, are the same to the last bit.
        """
        if self._fe_keys is None:
            return A
        grown = len(self._present(A)) != len(self._fe_keys)  # this rank's rows
        grown = collective_comm(A.getComm().tompi4py()).allreduce(grown, op=MPI.LOR)
        if not grown:
            return A
        B = matrix_with_pattern(A, self._fe_keys)
        self._keys[B.handle] = self._fe_keys
        self.rebuilds += 1
        return B

    def forget(self, A: PETSc.Mat) -> None:
        """Drop cached keys of a matrix that is about to be destroyed."""
        self._keys.pop(A.handle, None)
