"""Communicators for mpi4py's object (pickle-based) collectives.

mpi4py 4.1 guards its lower-case collectives (``allreduce``, ``allgather``, ``bcast``,
``gather``, ...) with a lock that it stores as an attribute of the communicator. When a
DOLFINx mesh (or a PETSc object) frees its communicator while a Python exception is
propagating, that attribute's delete callback runs with the exception still set: the user sees
``SystemError`` from ``commlock_free_cb`` instead of their error, and the process may hang or
segfault. Object collectives therefore never run on a communicator that DOLFINx or PETSc owns:
they run on :func:`collective_comm`, a congruent communicator that lives as long as MPI.
"""

from mpi4py import MPI

__all__ = ["collective_comm", "peak_rss_mb"]

# Communicators made for process groups that are neither COMM_WORLD nor one rank, keyed by the
# group's COMM_WORLD ranks in order. Kept until MPI finalises: never freed mid-exception.
_SUBGROUP_COMMS: dict[tuple[int, ...], MPI.Intracomm] = {}


def collective_comm(comm: MPI.Comm) -> MPI.Intracomm:
    """A communicator of the same ranks, in the same order, that is safe for object collectives.

    Args:
        comm: Any intra-communicator, typically ``mesh.comm`` or a PETSc object's communicator.

    Returns:
        ``MPI.COMM_SELF`` for one rank, ``MPI.COMM_WORLD`` when ``comm`` is congruent to it,
        otherwise a duplicate made once per process group (collective over ``comm`` the first
        time) and kept until MPI finalises.
    """
    if comm.size == 1:
        return MPI.COMM_SELF
    if MPI.Comm.Compare(comm, MPI.COMM_WORLD) in (MPI.IDENT, MPI.CONGRUENT):
        return MPI.COMM_WORLD
    group, world = comm.Get_group(), MPI.COMM_WORLD.Get_group()
    key = tuple(MPI.Group.Translate_ranks(group, list(range(comm.size)), world))
    group.Free()
    world.Free()
    if key not in _SUBGROUP_COMMS:
        _SUBGROUP_COMMS[key] = comm.Dup()
    return _SUBGROUP_COMMS[key]


def peak_rss_mb() -> float:
    """This process's peak resident memory so far, in MB (the kernel's high-water mark)."""
    import resource
    import sys

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0
