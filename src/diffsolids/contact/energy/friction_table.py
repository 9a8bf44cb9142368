"""Friction coefficients of the contact term: one per pair of bodies (self-contact included).

Each collision gets the coefficient of the pair of bodies of its two sides: ipctk blends
per-vertex values, here the body index of each vertex, and the blend looks the pair up in the
table (static and kinetic coefficients equal).
"""

from collections.abc import Callable, Mapping, Sequence

import ipctk
import numpy as np

from diffsolids.contact.geometry.surface import CollisionSurface
from diffsolids.errors import ParameterError

__all__ = ["body_pairs", "checked_coefficients", "coefficients_of", "tangential_collisions"]


def body_pairs(body_ids: Sequence[int]) -> tuple[list[tuple[int, int]], np.ndarray]:
    """The pairs (a, b), a <= b in the order of ``body_ids``, and their index per body index.

    Returns:
        (pairs, index): ``index[ia, ib]`` (symmetric) is the position of the pair of the bodies
        ``body_ids[ia]`` and ``body_ids[ib]`` in ``pairs``.
    """
    ids = list(body_ids)
    pairs = [(a, b) for k, a in enumerate(ids) for b in ids[k:]]
    index = np.zeros((len(ids), len(ids)), dtype=np.int64)
    for p, (a, b) in enumerate(pairs):
        ia, ib = ids.index(a), ids.index(b)
        index[ia, ib] = index[ib, ia] = p
    return pairs, index


def coefficients_of(
    friction: float | Mapping, num_pairs: int, pair_index: Callable[[int | str, int | str], int]
) -> np.ndarray:
    """Coefficient per pair from one value for all pairs or ``{(body_a, body_b): mu}``.

    Args:
        friction: A float, or a mapping from pairs of bodies (ids or names) to mu (others 0).
        num_pairs: Number of pairs.
        pair_index: Position of a pair of bodies (ids or names) among the pairs.
    """
    if isinstance(friction, Mapping):
        mu = np.zeros(num_pairs)
        for (a, b), value in friction.items():
            mu[pair_index(a, b)] = value
        return mu
    return np.full(num_pairs, float(friction))


def checked_coefficients(values: np.ndarray | Sequence[float], num_pairs: int) -> np.ndarray:
    """The coefficients as a float array, refused unless one finite value >= 0 per pair.

    Raises:
        ParameterError: A wrong number of values, or a negative or non-finite one.
    """
    mu = np.asarray(values, dtype=float).reshape(-1)
    if mu.shape != (num_pairs,):
        raise ParameterError(f"{len(mu)} friction coefficients given for {num_pairs} pairs")
    if not np.all(np.isfinite(mu)) or np.any(mu < 0):
        raise ParameterError(f"friction coefficients {mu} must be finite and >= 0")
    return mu


def tangential_collisions(
    surface: CollisionSurface,
    x: np.ndarray,
    collisions: ipctk.NormalCollisions,
    barrier: ipctk.BarrierPotential,
    mu_table: np.ndarray,
) -> ipctk.TangentialCollisions:
    """Lagged friction collisions at x with the coefficient of each pair of bodies.

    Args:
        surface: The collision surface.
        x: (num_vertices, dim) positions of the lagged state.
        collisions: The collision set at x.
        barrier: The barrier potential (normal forces).
        mu_table: (num_bodies, num_bodies) coefficient of each pair of body indices.
    """
    T = ipctk.TangentialCollisions()
    vertices = np.asfortranarray(x)
    table = np.asarray(mu_table, dtype=float)
    if table.size and np.all(table == table.flat[0]):
        # one coefficient for every pair: ipctk's scalar build, ~5x faster than the callback
        # below (one Python call per collision side) and the same coefficients bit for bit
        T.build(surface.mesh, vertices, collisions, barrier, float(table.flat[0]))
        return T
    labels = surface.body_index.astype(float)
    rows = table.tolist()  # nested lists: a Python index is ~10x cheaper than a numpy one

    def blend(a: float, b: float) -> float:
        return rows[round(a)][round(b)]

    T.build(surface.mesh, vertices, collisions, barrier, labels, labels, blend)
    return T
