"""Checkpoints of an optimisation: a killed run resumes where the last checkpoint left it.

Layout of the checkpoint directory:

- ``state.npz`` (written by rank 0): parameters, gradient, L-BFGS pairs and a JSON record
  (iteration counter, objective, history, counters, remesh count, name of the trajectory files).
- ``trajectory_<tag>_rank<r>.npz`` (one per rank): the accepted trajectory (rank-local arrays)
  that warm-starts the next forward solves, with a fingerprint of the rank's dof layout.
- ``mesh_<k>/``: directory handed to the remesher's ``save_checkpoint``/``load_checkpoint``
  after the k-th remesh.

Every file is written to a temporary name and moved into place with ``os.replace``; the
trajectory files of a checkpoint are complete before ``state.npz`` refers to them, so the
directory always holds one consistent checkpoint.
"""

import json
import os
from pathlib import Path

import numpy as np
from mpi4py import MPI

from diffsolids.optimize.options import OptimizationError
from diffsolids.parallel import collective_comm
from diffsolids.simulation import Trajectory

__all__ = ["Checkpoint", "atomic_write_bytes", "atomic_write_npz", "make_directory"]


def make_directory(path: str | os.PathLike, comm: MPI.Comm, what: str) -> Path:
    """Create a directory on rank 0 (collective); its failure is an error on every rank.

    Args:
        path: The directory (parents are created too).
        comm: The communicator.
        what: What the directory is for, for the message ("checkpoint directory").

    Raises:
        OptimizationError: The path is a file, or the directory cannot be created.
    """
    path = Path(path)
    problem = None
    if comm.rank == 0:
        if path.exists() and not path.is_dir():
            problem = f"{what} {path} is a file, not a directory"
        else:
            try:
                path.mkdir(parents=True, exist_ok=True)
            except OSError as e:
                problem = f"{what} {path} cannot be created: {e.strerror or e}"
    problem = collective_comm(comm).bcast(problem, root=0)
    if problem is not None:
        raise OptimizationError(problem)
    return path


def atomic_write_npz(path: Path, arrays: dict) -> None:
    """Write ``arrays`` to ``path`` (npz) through a temporary file and ``os.replace``."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and ``os.replace``."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class Checkpoint:
    """Reads and writes the checkpoint of one optimisation run.

    Args:
        directory: Checkpoint directory (created if missing).
        comm: Communicator of the run (all ranks call every method).

    Raises:
        OptimizationError: ``directory`` is a file or cannot be created.
    """

    STATE = "state.npz"

    def __init__(self, directory: str | os.PathLike, comm: MPI.Comm) -> None:
        self.directory = make_directory(directory, comm, "checkpoint directory")
        self.comm = comm

    def exists(self) -> bool:
        """Whether a checkpoint is present (same answer on all ranks)."""
        found = (self.directory / self.STATE).is_file() if self.comm.rank == 0 else None
        return bool(collective_comm(self.comm).bcast(found, root=0))

    def mesh_directory(self, remesh_count: int) -> Path:
        """Directory for the remesher's data after remesh number ``remesh_count``."""
        return make_directory(
            self.directory / f"mesh_{remesh_count:03d}", self.comm, "remesher's checkpoint"
        )

    def _trajectory_path(self, tag: str, rank: int) -> Path:
        return self.directory / f"trajectory_{tag}_rank{rank:04d}.npz"

    def save(
        self,
        meta: dict,
        arrays: dict[str, np.ndarray],
        trajectory: Trajectory | None,
        layout: np.ndarray,
    ) -> None:
        """Write a checkpoint.

        Args:
            meta: JSON-serialisable record (identical on all ranks; rank 0 writes it).
            arrays: Shared arrays (identical on all ranks; rank 0 writes them).
            trajectory: The accepted trajectory (rank-local arrays) or None.
            layout: Fingerprint of this rank's dof layout (checked when loading).
        """
        tag = f"it{meta['iteration']:06d}_m{meta['remesh_count']:03d}"
        rank = self.comm.rank
        if trajectory is not None:
            atomic_write_npz(
                self._trajectory_path(tag, rank),
                {
                    "times": np.asarray(trajectory.times, dtype=float),
                    "u": np.array(trajectory.u),
                    "v": np.array(trajectory.v),
                    "layout": np.asarray(layout),
                },
            )
        self.comm.barrier()
        meta = {**meta, "trajectory": tag if trajectory is not None else None}
        meta["num_ranks"] = self.comm.size
        if rank == 0:
            atomic_write_npz(
                self.directory / self.STATE,
                {**arrays, "meta": np.array(json.dumps(meta))},
            )
        self.comm.barrier()
        keep = self._trajectory_path(tag, rank).name
        for old in self.directory.glob(f"trajectory_*_rank{rank:04d}.npz"):
            if old.name != keep:
                old.unlink(missing_ok=True)

    def load_state(self) -> tuple[dict, dict]:
        """The shared part of the checkpoint: (JSON record, arrays), identical on all ranks."""
        data = None
        if self.comm.rank == 0:
            with np.load(self.directory / self.STATE, allow_pickle=False) as f:
                data = {k: f[k] for k in f.files}
        data = collective_comm(self.comm).bcast(data, root=0)
        meta = json.loads(str(data.pop("meta")))
        return meta, data

    def load_trajectory(
        self, meta: dict, layout: np.ndarray
    ) -> tuple[Trajectory | None, str | None]:
        """The checkpointed trajectory of this rank.

        Args:
            meta: The record from :meth:`load_state`.
            layout: This rank's dof-layout fingerprint (must equal the checkpointed one).

        Returns:
            (trajectory, None), or (None, why it cannot be used) on all ranks.
        """
        tag = meta.get("trajectory")
        trajectory, problem = None, None
        if tag is None:
            problem = "the checkpoint holds no trajectory"
        elif meta.get("num_ranks") != self.comm.size:
            problem = f"the checkpoint was written by {meta.get('num_ranks')} ranks"
        else:
            path = self._trajectory_path(tag, self.comm.rank)
            if not path.is_file():
                problem = f"{path.name} is missing"
            else:
                with np.load(path, allow_pickle=False) as f:
                    if np.array_equal(f["layout"], layout):
                        trajectory = Trajectory(
                            times=[float(t) for t in f["times"]],
                            u=[row.copy() for row in f["u"]],
                            v=[row.copy() for row in f["v"]],
                        )
                    else:
                        problem = "the dof layout differs from the checkpointed run"
        problems = collective_comm(self.comm).allgather(problem)
        problem = next((p for p in problems if p is not None), None)
        return (None, problem) if problem is not None else (trajectory, None)
