"""Forward factorisations kept for the adjoint, within the memory the machine can spare."""

import gc
from pathlib import Path
from typing import ClassVar

from mpi4py import MPI
from petsc4py import PETSc

from diffsolids.errors import ParameterError
from diffsolids.parallel import collective_comm

__all__ = ["FactorStore", "factor_memory_mb", "lu_solver", "node_memory_mb"]


def lu_solver(comm: MPI.Comm, A: PETSc.Mat) -> PETSc.KSP:
    """A KSP that solves with ``A`` by a MUMPS LU factorisation, factorised now."""
    ksp = PETSc.KSP().create(comm)
    ksp.setOperators(A)
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType("lu")
    pc.setFactorSolverType("mumps")
    ksp.setUp()
    return ksp


def node_memory_mb(
    meminfo: Path = Path("/proc/meminfo"), cgroup: Path = Path("/sys/fs/cgroup")
) -> tuple[float, float] | None:
    """(available, total) memory in MB for this process: the node's, or its container's.

    The node's from ``/proc/meminfo`` (Linux), lowered to the memory limit of the process's
    cgroup (v2 ``memory.max``, v1 ``memory/memory.limit_in_bytes``) when one is set: inside a
    container ``/proc/meminfo`` shows the host. None where neither is known.
    """
    try:
        with open(meminfo) as f:
            info = dict(line.split(":", 1) for line in f if ":" in line)
        available, total = (float(info[k].split()[0]) / 1024 for k in ("MemAvailable", "MemTotal"))
    except (OSError, KeyError, ValueError):
        return None
    limit = _cgroup_memory_mb(cgroup)
    if limit is not None:
        available, total = min(available, limit[0]), min(total, limit[1])
    return available, total


def _cgroup_memory_mb(root: Path) -> tuple[float, float] | None:
    """(available, limit) in MB of a cgroup with a memory limit; None without one."""
    layouts = [  # (limit, usage, stat, reclaimable page cache key) of cgroup v2 and v1
        ("memory.max", "memory.current", "memory.stat", "inactive_file"),
        (
            "memory/memory.limit_in_bytes",
            "memory/memory.usage_in_bytes",
            "memory/memory.stat",
            "total_inactive_file",
        ),
    ]
    for limit_file, usage_file, stat_file, cache_key in layouts:
        try:
            text = (root / limit_file).read_text().strip()
            if text == "max" or float(text) >= 2.0**60:  # no limit
                return None
            limit, usage = float(text), float((root / usage_file).read_text())
            stat = dict(line.split() for line in (root / stat_file).read_text().splitlines())
        except (OSError, ValueError):
            continue
        available = limit - usage + float(stat.get(cache_key, 0.0))
        return available / 2**20, limit / 2**20
    return None


def factor_memory_mb(factor: PETSc.Mat) -> float:
    """Memory (MB) held by this rank's part of a MUMPS factorisation.

    MUMPS' own report, or the size of its factor entries when the report rounds to 0 MB.
    """

    def count(k: int) -> float:  # MUMPS reports counts above 2^31 negative, in millions
        n = factor.getMumpsInfo(k)
        return float(n) if n >= 0 else -1e6 * n

    entries_mb = (8.0 * count(9) + 4.0 * count(10)) / 2**20  # real and integer entries
    return max(float(factor.getMumpsInfo(22)), entries_mb)


class FactorStore:
    """Keeps the last Newton factorisation of steps for the adjoint (within a memory budget).

    After a converged step the SNES's KSP (its PC holding the LU factors of the Jacobian at the
    last Newton iterate) is set to reuse its factors and stored; SNES continues with a fresh KSP
    of the same type. The adjoint then preconditions the exact Jacobian of step i with the
    factors of step i: a Krylov solve of one or two iterations.

    Memory: with a fixed ``budget_mb`` the factors of each rank stay within it. Without one
    (the default) factors are kept while the node keeps ``reserve`` of its total memory
    available (all ranks on the node counted); where the node's memory is unknown (no
    ``/proc/meminfo``) the budget is 2000 MB per rank.

    Every MUMPS instance holds several MPI communicators, and an MPI library has a few thousand
    (MPICH: 2048 per process; MUMPS does not check for failure and corrupts memory when they run
    out, after about 400 live instances). The number of stored factorisations is therefore
    capped, per store and for all stores of the process together. A store that reaches its cap
    keeps every other factorisation and from then on only steps that are multiples of a doubled
    stride, so a long trajectory keeps evenly spaced factors; the adjoint preconditions the steps
    in between with the nearest later factors (or refactorises when that needs many iterations).

    Args:
        budget_mb: Memory for stored factors per rank (estimated from MUMPS' report), or None
            for the node's spare memory.
        max_factors: Most factorisations this store keeps.
        reserve: Fraction of the node's total memory left available (``budget_mb=None``).

    Attributes:
        max_live: Most stored factorisations of all stores of the process together.
    """

    max_live: ClassVar[int] = 160
    _live: ClassVar[int] = 0

    def __init__(
        self, budget_mb: float | None = None, max_factors: int = 64, reserve: float = 0.25
    ) -> None:
        if max_factors < 1:
            raise ParameterError(f"max_factors must be at least 1, got {max_factors}")
        if budget_mb is not None and not budget_mb >= 0:
            raise ParameterError(f"budget_mb must be None or >= 0, got {budget_mb}")
        if not 0 <= reserve < 1:
            raise ParameterError(f"reserve must be a fraction in [0, 1), got {reserve}")
        if budget_mb is None and node_memory_mb() is None:
            budget_mb = 2000.0
        self.budget_mb = budget_mb
        self.max_factors = max_factors
        self.reserve = reserve
        self.factors: dict[int, PETSc.KSP] = {}
        self.sizes_mb: dict[int, float] = {}
        self.used_mb = 0.0
        self.stride = 1
        self._ranks_on_node: int | None = None

    def __del__(self) -> None:
        FactorStore._live -= len(getattr(self, "factors", ()))

    def clear(self) -> None:
        """Free all stored factorisations (a new trajectory starts with stride 1)."""
        for ksp in self.factors.values():
            ksp.destroy()
        FactorStore._live -= len(self.factors)
        self.factors.clear()
        self.sizes_mb.clear()
        self.used_mb = 0.0
        self.stride = 1

    def discard_after(self, step: int) -> None:
        """Free the factorisations of steps after ``step`` (collective: same steps on all ranks).

        A checkpointed backward sweep calls this once the adjoint of ``step`` is solved: later
        steps' factors are not needed again (a preconditioner still in use keeps its own
        reference to them).
        """
        for s in [s for s in self.factors if s > step]:
            self._drop(s)

    def _drop(self, step: int) -> None:
        self.factors.pop(step).destroy()
        self.used_mb -= self.sizes_mb.pop(step)
        FactorStore._live -= 1

    def _thin(self) -> None:
        """Keep every other stored factorisation and double the stride."""
        self.stride *= 2
        for step in [s for s in self.factors if s % self.stride]:
            self._drop(step)

    def _room(self, comm: MPI.Comm) -> bool:
        """Whether one more factorisation may be stored (collective: same answer on all ranks)."""
        if FactorStore._live >= FactorStore.max_live:
            gc.collect()  # stores of unreachable solvers free their factors
        full = len(self.factors) >= self.max_factors or FactorStore._live >= FactorStore.max_live
        if collective_comm(comm).allreduce(full, op=MPI.LOR):
            if not self.factors:
                return False
            self._thin()
        return True

    def _fits(self, size_mb: float, comm: MPI.Comm) -> bool:
        """Whether factors of ``size_mb`` per rank fit the budget (collective)."""
        if self.budget_mb is not None:
            return self.used_mb + size_mb <= self.budget_mb
        if self._ranks_on_node is None:
            node = comm.Split_type(MPI.COMM_TYPE_SHARED)
            self._ranks_on_node = node.size
            node.Free()
        available, total = node_memory_mb()
        fits = available - size_mb * self._ranks_on_node >= self.reserve * total
        return collective_comm(comm).allreduce(fits, op=MPI.LAND)

    def keep(self, step: int, snes: PETSc.SNES) -> None:
        """Store the current KSP of ``snes`` for ``step`` if it fits; give SNES a new KSP."""
        old = snes.getKSP()
        pc = old.getPC()
        if pc.getType() != "lu" or pc.getFactorSolverType() != "mumps":
            return
        if step % self.stride:
            return
        if step in self.factors:  # the step was solved again (a checkpointed recomputation)
            self._drop(step)
        comm = old.comm.tompi4py()
        if not self._room(comm) or step % self.stride:  # thinning may have doubled the stride
            return
        size_mb = collective_comm(comm).allreduce(
            factor_memory_mb(pc.getFactorMatrix()), op=MPI.MAX
        )
        if not self._fits(size_mb, comm):
            return
        pc.setReusePreconditioner(True)
        self.factors[step] = old
        self.sizes_mb[step] = size_mb
        self.used_mb += size_mb
        FactorStore._live += 1
        new = PETSc.KSP().create(old.comm)
        new.setOptionsPrefix(old.getOptionsPrefix())
        new.setType(old.getType())
        new.getPC().setType("lu")
        new.getPC().setFactorSolverType("mumps")
        snes.setKSP(new)
