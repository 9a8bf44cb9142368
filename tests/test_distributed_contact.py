"""The collision partition of distributed contact, checked in one process.

:class:`~diffsolids.contact.partition.CollisionPartition` reads only ``size`` and ``rank`` of
its communicator to split a collision set, so the split of every rank of a 2-, 3- or 7-rank
run can be checked here on the serial set: the shares are disjoint, cover the set, keep each
collision's weight, are balanced, and do not depend on the order of the lists. The MPI side
(sums, the matrix, gradients equal to serial) is tests/mpi/test_distributed_contact_parallel.py.
"""

import ipctk
import numpy as np
import pytest
from mpi4py import MPI

from diffsolids.contact.partition import CollisionPartition, collision_keys
from diffsolids.mesh.scene import combine_meshes, simplex_box


class _Ranks:
    """Stands for a communicator of ``size`` ranks seen from ``rank`` (no collectives used)."""

    def __init__(self, size: int, rank: int) -> None:
        self.size, self.rank = size, rank


def _collisions(shuffle: int | None = None) -> tuple[ipctk.CollisionMesh, np.ndarray, object]:
    """A 3D flat-on-flat collision set (vertex-vertex, edge-vertex, edge-edge, face-vertex)."""
    import diffsolids as ds
    from diffsolids.contact import ContactTerm

    dhat = 1e-3
    lower = simplex_box([[0, 0, 0], [1, 1, 0.25]], [8, 8, 1])
    upper = simplex_box([[0.25, 0.25, 0.25 + 0.5 * dhat], [0.75, 0.75, 0.5]], [5, 5, 1])
    # grids of spacing 1/8 and 1/10: vertices above vertices, edges and faces
    model = ds.Model(combine_meshes(MPI.COMM_SELF, [lower, upper]), ds.NeoHookean(E=1e6, nu=0.3))
    surf = ContactTerm(model, dhat=dhat, stiffness=1.0).surface
    x = np.asfortranarray(surf.rest_positions)
    C = ipctk.NormalCollisions()
    C.use_area_weighting = True
    C.build(surf.mesh, x, dhat, 0.0, ipctk.LBVH())
    if shuffle is not None:  # the order ipctk's threads may report them in
        rng = np.random.default_rng(shuffle)
        for name in ("vv_collisions", "ev_collisions", "ee_collisions", "fv_collisions"):
            listed = getattr(C, name)
            setattr(C, name, [listed[k] for k in rng.permutation(len(listed))])
    return surf.mesh, x, C


def _copy(C):
    out = ipctk.NormalCollisions()
    out.use_area_weighting = C.use_area_weighting
    for name in ("vv_collisions", "ev_collisions", "ee_collisions", "fv_collisions"):
        setattr(out, name, getattr(C, name))
    return out


def _weights(C) -> np.ndarray:
    groups = (C.vv_collisions, C.ev_collisions, C.ee_collisions, C.fv_collisions)
    return np.array([c.weight for g in groups for c in g])


def test_one_rank_keeps_everything():
    _, _, C = _collisions()
    n = len(C)
    part = CollisionPartition(MPI.COMM_SELF)
    assert part.keep_share(C) is C and len(C) == n
    assert not part.distributed and part.counts == {"evaluations": 1, "collisions": n}
    g = np.arange(5.0)
    assert part.sum(g) is g and part.total(2.5) == 2.5 and part.minimum(3.0) == 3.0


@pytest.mark.parametrize("size", [2, 3, 7])
def test_shares_partition_the_collision_set(size):
    mesh, x, C = _collisions()
    kinds = [len(C.vv_collisions), len(C.ev_collisions), len(C.ee_collisions)]
    assert min(kinds) > 0 and len(C.fv_collisions) > 0  # every type is split
    keys, weights = collision_keys(C), _weights(C)
    barrier = ipctk.BarrierPotential(1e-3, 1.0)
    energy = barrier(C, mesh, x)
    grad = barrier.gradient(C, mesh, x)
    shares = []
    for rank in range(size):
        share = CollisionPartition(_Ranks(size, rank)).keep_share(_copy(C))
        shares.append((collision_keys(share), _weights(share), share))
    got = np.concatenate([s[0] for s in shares])
    assert len(got) == len(keys) == len(np.unique(got))  # each collision on one rank
    order, ref = np.argsort(got), np.argsort(keys)
    assert np.array_equal(got[order], keys[ref])
    assert np.array_equal(np.concatenate([s[1] for s in shares])[order], weights[ref])
    # the shares' barrier energies and gradients add up to the whole set's
    e = sum(barrier(s[2], mesh, x) for s in shares)
    g = sum(barrier.gradient(s[2], mesh, x) for s in shares)
    assert abs(e - energy) <= 1e-13 * abs(energy)
    assert np.abs(g - grad).max() <= 1e-13 * np.abs(grad).max()
    # balanced: binomial spread around len / size
    counts = np.array([len(s[0]) for s in shares])
    mean = len(keys) / size
    assert np.abs(counts - mean).max() <= 4.0 * np.sqrt(mean) + 1


def test_share_does_not_depend_on_the_order():
    _, _, C = _collisions()
    _, _, D = _collisions(shuffle=1)
    for rank in range(3):
        a = collision_keys(CollisionPartition(_Ranks(3, rank)).keep_share(_copy(C)))
        b = collision_keys(CollisionPartition(_Ranks(3, rank)).keep_share(_copy(D)))
        assert np.array_equal(np.sort(a), np.sort(b))


def test_owner_is_balanced_on_structured_keys():
    # consecutive ids in the high bits of the key (a row of edges against one vertex) spread
    # over the ranks (a hash of the low bits alone would send them all to one rank)
    keys = (np.int64(3) << 60) | (np.arange(20000, dtype=np.int64) << 30) | 7
    for size in (2, 3, 64):
        owner = CollisionPartition(_Ranks(size, 0)).owner(keys)
        counts = np.bincount(owner, minlength=size)
        assert owner.min() >= 0 and owner.max() < size
        mean = len(keys) / size  # a random split: binomial spread around the mean
        assert np.abs(counts - mean).max() <= 4.0 * np.sqrt(mean)
