"""Forward factorisations kept for the adjoint, within the memory the machine can spare."""

import gc
import os
import shutil
import tempfile
import weakref
from pathlib import Path
from typing import ClassVar

from mpi4py import MPI
from petsc4py import PETSc

from diffsolids.errors import ParameterError
from diffsolids.parallel import collective_comm
from diffsolids.solvers.linear_options import delete_options

__all__ = [
    "FactorStore",
    "detach_ksp",
    "factor_disk_mb",
    "factor_memory_mb",
    "lu_solver",
    "node_memory_mb",
]


def detach_ksp(snes: PETSc.SNES) -> PETSc.KSP:
    """Give ``snes`` a new LU KSP like its own (type, options prefix, factor package).

    Returns:
        The old KSP, with the factorisation it holds (the caller destroys it); later solves of
        the SNES factorise into the new one.
    """
    old = snes.getKSP()
    pc = old.getPC()
    new = PETSc.KSP().create(old.comm)
    new.setOptionsPrefix(old.getOptionsPrefix())
    new.setType(old.getType())
    new.getPC().setType("lu")
    new.getPC().setFactorSolverType(pc.getFactorSolverType() or "mumps")
    snes.setKSP(new)
    return old


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


def factor_disk_mb(factor: PETSc.Mat) -> float:
    """Size (MB) of this rank's part of a MUMPS factorisation's entries (its out-of-core files)."""

    def count(k: int) -> float:  # MUMPS reports counts above 2^31 negative, in millions
        n = factor.getMumpsInfo(k)
        return float(n) if n >= 0 else -1e6 * n

    return (8.0 * count(9) + 4.0 * count(10)) / 2**20  # real and integer entries


def factor_memory_mb(factor: PETSc.Mat) -> float:
    """Memory (MB) held by this rank's part of a MUMPS factorisation.

    MUMPS' own report, or the size of its factor entries when the report rounds to 0 MB.
    """
    return max(float(factor.getMumpsInfo(22)), factor_disk_mb(factor))


class FactorStore:
    """Keeps the last Newton factorisation of steps for the adjoint (within a memory budget).

    After a converged step the SNES's KSP (its PC holding the LU factors of the Jacobian at the
    last Newton iterate) is set to reuse its factors and stored; SNES continues with a fresh KSP
    of the same type. The adjoint then preconditions the exact Jacobian of step i with the
    factors of step i: a Krylov solve of one or two iterations.

    Storage: ``out_of_core=True`` (the default without a ``budget_mb``) keeps the factors on
    disk (MUMPS out-of-core, files in ``directory``, removed with the factorisation): the
    Newton solves write them as they factorise, the adjoint's solves read them back, and the
    memory stays that of the forward. The stored factors of all ranks on the node then take
    at most half of the free disk space of ``directory`` when the run starts. (Where the
    temporary directory is a memory file system, tmpfs, the files take memory: give a
    ``directory`` on disk.)

    Memory (``out_of_core=False``): with a fixed ``budget_mb`` the factors of each rank stay
    within it. Without one the factors of all ranks on the node together take at most
    ``node_share`` of the memory the node has available when the run starts (each rank its
    share), and never leave less than ``reserve`` of the node's total memory available. Where
    the node's memory is unknown (no ``/proc/meminfo``) the budget is 2000 MB per rank.

    A store whose next factorisation would exceed its budget thins to evenly spaced steps
    (below) instead of keeping only the first steps, and the adjoint preconditions each step
    with the nearest stored factors.

    Every MUMPS instance holds several MPI communicators, and an MPI library has a few thousand
    (MPICH: 2048 per process; MUMPS does not check for failure and corrupts memory when they run
    out, after about 400 live instances). The number of stored factorisations is therefore
    capped, per store and for all stores of the process together. A store that reaches its cap
    keeps every other factorisation and from then on only steps that are multiples of a doubled
    stride, so a long trajectory keeps evenly spaced factors; the adjoint preconditions the steps
    in between with the nearest later factors (or refactorises when that needs many iterations).

    Args:
        budget_mb: Memory for stored factors per rank (estimated from MUMPS' report), or None
            for ``node_share`` of the node's available memory.
        max_factors: Most factorisations this store keeps.
        reserve: Fraction of the node's total memory left available (``budget_mb=None``).
        node_share: Fraction of the node's available memory at the start of a run that the
            factors of all its ranks may take together (``budget_mb=None``, in memory).
        out_of_core: Keep the factors on disk; None: on disk unless ``budget_mb`` is given.
        directory: Directory of the out-of-core files (default: the system's temporary one).

    Attributes:
        max_live: Most stored factorisations of all stores of the process together.
    """

    max_live: ClassVar[int] = 160
    _live: ClassVar[int] = 0

    def __init__(
        self,
        budget_mb: float | None = None,
        max_factors: int = 64,
        reserve: float = 0.25,
        node_share: float = 0.1,
        out_of_core: bool | None = None,
        directory: str | os.PathLike | None = None,
    ) -> None:
        if max_factors < 1:
            raise ParameterError(f"max_factors must be at least 1, got {max_factors}")
        if budget_mb is not None and not budget_mb >= 0:
            raise ParameterError(f"budget_mb must be None or >= 0, got {budget_mb}")
        if not 0 <= reserve < 1:
            raise ParameterError(f"reserve must be a fraction in [0, 1), got {reserve}")
        if not 0 < node_share <= 1:
            raise ParameterError(f"node_share must be a fraction in (0, 1], got {node_share}")
        self.out_of_core = budget_mb is None if out_of_core is None else bool(out_of_core)
        self.directory = str(directory) if directory is not None else tempfile.gettempdir()
        if self.out_of_core and not os.access(self.directory, os.W_OK | os.X_OK):
            raise ParameterError(f"out-of-core factors: directory {self.directory} is not writable")
        if budget_mb is None and not self.out_of_core and node_memory_mb() is None:
            budget_mb = 2000.0
        self.budget_mb = budget_mb
        self.max_factors = max_factors
        self.reserve = reserve
        self.node_share = node_share
        self.run_budget_mb: float | None = budget_mb  # per rank, fixed at a run's first keep
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
        self.run_budget_mb = self.budget_mb

    def node_claim_mb(self, available: float, total: float, ranks_on_node: int) -> float:
        """Memory (MB) the stores of all ranks on a node may claim together.

        Args:
            available: The node's available memory (MB).
            total: The node's total memory (MB).
            ranks_on_node: Ranks of the job on the node.
        """
        if self.out_of_core:
            return 0.0
        if self.budget_mb is not None:
            return self.budget_mb * ranks_on_node
        return min(self.node_share * available, self._headroom_mb(available, total))

    def spare_mb(self, available: float, total: float, ranks_on_node: int) -> float:
        """Memory (MB) of the node the job may use besides the stores (checkpointed states).

        With a fixed budget: what it leaves available. Without one: what the stores leave of
        the memory above the node's reserve (none on a node that is already below it).
        """
        claim = self.node_claim_mb(available, total, ranks_on_node)
        if self.budget_mb is not None and not self.out_of_core:
            return available - claim
        return self._headroom_mb(available, total) - claim

    def _headroom_mb(self, available: float, total: float) -> float:
        return max(available - self.reserve * total, 0.0)

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

    def _make_room(self, size_mb: float, comm: MPI.Comm) -> bool:
        """Thin until factors of ``size_mb`` per rank fit; False if they do not fit alone."""
        while not self._fits(size_mb, comm):
            if not self.factors:
                return False
            self._thin()
        return True

    def _fits(self, size_mb: float, comm: MPI.Comm) -> bool:
        """Whether factors of ``size_mb`` per rank fit the budget (collective)."""
        if self.run_budget_mb is None:
            self.run_budget_mb = self._node_budget_mb(comm)
        fits = self.used_mb + size_mb <= self.run_budget_mb
        if self.budget_mb is None and not self.out_of_core:  # others may have taken memory
            available, total = node_memory_mb()
            fits = fits and available - size_mb * self._ranks(comm) >= self.reserve * total
        return collective_comm(comm).allreduce(fits, op=MPI.LAND)

    def _ranks(self, comm: MPI.Comm) -> int:
        if self._ranks_on_node is None:
            node = comm.Split_type(MPI.COMM_TYPE_SHARED)
            self._ranks_on_node = node.size
            node.Free()
        return self._ranks_on_node

    def _node_budget_mb(self, comm: MPI.Comm) -> float:
        """This rank's share of :meth:`node_claim_mb` now (the same on all ranks)."""
        ranks = self._ranks(comm)
        if self.out_of_core:
            claim = 0.5 * shutil.disk_usage(self.directory).free / 2**20 / ranks
            return float(collective_comm(comm).allreduce(claim, op=MPI.MIN))
        available, total = node_memory_mb()
        claim = self.node_claim_mb(available, total, ranks) / ranks
        return float(collective_comm(comm).allreduce(claim, op=MPI.MIN))

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
        factor = pc.getFactorMatrix()
        local_mb = factor_disk_mb(factor) if self.out_of_core else factor_memory_mb(factor)
        size_mb = collective_comm(comm).allreduce(local_mb, op=MPI.MAX)
        if not self._make_room(size_mb, comm) or step % self.stride:
            return
        pc.setReusePreconditioner(True)
        self.factors[step] = old
        self.sizes_mb[step] = size_mb
        self.used_mb += size_mb
        FactorStore._live += 1
        detach_ksp(snes)

    def begin_run(self, snes: PETSc.SNES) -> None:
        """Free the last run's factorisations and set ``snes`` up to factorise as stored.

        Out of core: MUMPS writes the factors of ``snes``'s next factorisations to
        :attr:`directory` (options under the SNES's own prefix; a KSP that has factorised
        already is replaced by a fresh one, which reads them).
        """
        self.clear()
        prefix = snes.getOptionsPrefix() or ""
        opts = PETSc.Options(prefix)
        factorises = opts.getString("pc_type", "") in ("lu", "cholesky") and (
            opts.getString("pc_factor_mat_solver_type", "") == "mumps"
        )
        if not self.out_of_core or not factorises or opts.hasName("mat_mumps_icntl_22"):
            return
        opts["mat_mumps_icntl_22"] = 1
        opts["mat_mumps_ooc_tmpdir"] = self.directory
        names = ["mat_mumps_icntl_22", "mat_mumps_ooc_tmpdir"]
        weakref.finalize(snes, delete_options, prefix, names)  # with the solver's own options
        pc = snes.getKSP().getPC()
        if pc.getType() == "lu" and pc.getFactorSolverType() == "mumps":
            detach_ksp(snes)
