"""Configuration checks of the contact surface: intersections, touching pairs, their labels.

A configuration of the bodies (and obstacles) is refused when the collision surface intersects
itself or when two primitives are closer than a minimum gap (the barrier cannot start from
touching bodies). The error names the pairs of bodies, found on the sub-mesh of each pair.
"""

from collections.abc import Callable, Iterator, Mapping, Sequence

import ipctk
import numpy as np

from diffsolids.contact.detection.collision_set import CollisionBuilder
from diffsolids.contact.geometry.obstacle import Obstacle
from diffsolids.contact.geometry.surface import CollisionSurface
from diffsolids.errors import IntersectionError

__all__ = [
    "ConfigurationCheck",
    "body_label",
    "close_pairs",
    "edges_of",
    "intersecting_pairs",
    "pair_label",
]


def edges_of(faces: np.ndarray) -> np.ndarray:
    """The unique edges of triangles (sorted vertex pairs)."""
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(pairs, axis=0).astype(np.int32)


def body_label(
    surface: CollisionSurface,
    obstacles: Sequence[Obstacle],
    names: Mapping[str, int],
    body: int,
) -> str:
    """A body's name in messages: the obstacle's label, or "body i ('name')".

    Args:
        surface: The collision surface.
        obstacles: Its obstacles.
        names: The domain's names of body ids.
        body: A body id.
    """
    if body in surface.obstacle_ids:
        return obstacles[surface.obstacle_ids.index(body)].label
    named = [k for k, v in names.items() if v == body]
    return f"body {body}" + (f" ({named[0]!r})" if named else "")


def pair_label(label: Callable[[int], str], a: int, b: int) -> str:
    """The label of a pair of bodies, "A and B" or "A with itself", from the body labels."""
    if a == b:
        return f"{label(a)} with itself"
    return f"{label(a)} and {label(b)}"


def pair_meshes(
    surface: CollisionSurface, pairs: Sequence[tuple[int, int]], x: np.ndarray
) -> Iterator[tuple[int, int, ipctk.CollisionMesh, np.ndarray]]:
    """Per pair of bodies: (a, b, the collision mesh of the pair, its positions).

    Args:
        surface: The collision surface.
        pairs: Pairs (a, b) of body ids (a == b: self-contact).
        x: (num_vertices, dim) positions of the surface.
    """
    surf = surface
    dim = surf.dim
    prims = surf.edges if dim == 2 else surf.faces
    static = surf.static if surf.static is not None else np.zeros(surf.num_vertices, bool)
    for a, b in pairs:
        sel = np.isin(surf.primitive_body, (a, b))
        verts = np.unique(prims[sel])
        local = np.searchsorted(verts, prims[sel]).astype(np.int32)
        if dim == 2:
            sub = ipctk.CollisionMesh(np.asfortranarray(surf.rest_positions[verts]), local)
        else:
            sub = ipctk.CollisionMesh(
                np.asfortranarray(surf.rest_positions[verts]),
                np.asfortranarray(edges_of(local)),
                np.asfortranarray(local),
            )
        ids = np.arange(len(verts), dtype=np.int32)
        ids[static[verts]] = -1
        filt = ipctk.make_vertex_patches_filter(ids)
        if a != b:
            filt = filt & ipctk.make_vertex_patches_filter((surf.body[verts] == a).astype(np.int32))
        sub.can_collide = filt
        yield a, b, sub, np.asfortranarray(x[verts])


def intersecting_pairs(
    surface: CollisionSurface, pairs: Sequence[tuple[int, int]], x: np.ndarray
) -> list[tuple[int, int]]:
    """The pairs of bodies whose surfaces intersect at positions ``x``."""
    return [
        (a, b)
        for a, b, sub, xs in pair_meshes(surface, pairs, x)
        if ipctk.has_intersections(sub, xs, ipctk.LBVH())
    ]


def close_pairs(
    surface: CollisionSurface,
    pairs: Sequence[tuple[int, int]],
    x: np.ndarray,
    dhat: float,
    gap: float,
) -> list[tuple[int, int]]:
    """The pairs of bodies with primitives within ``gap`` of each other at ``x`` (gap <= dhat)."""
    close = []
    for a, b, sub, xs in pair_meshes(surface, pairs, x):
        Cs = ipctk.NormalCollisions()
        Cs.build(sub, xs, dhat, 0.0, ipctk.LBVH())
        if len(Cs) and np.sqrt(Cs.compute_minimum_distance(sub, xs)) <= gap:
            close.append((a, b))
    return close


class ConfigurationCheck:
    """Refuses configurations of a collision surface that intersect or touch, naming the pairs.

    Args:
        builder: Builds the collision set of a configuration (its surface, partition over the
            ranks, broad phase and dhat are the check's).
        obstacles: The surface's obstacles.
        names: The domain's names of body ids.
        pairs: The pairs of body ids (self-contact included).
        min_gap: Configurations closer than ``min_gap * dhat`` are refused.
    """

    def __init__(
        self,
        builder: CollisionBuilder,
        obstacles: Sequence[Obstacle],
        names: Mapping[str, int],
        pairs: Sequence[tuple[int, int]],
        min_gap: float,
    ) -> None:
        self.surface = builder.surface
        self.partition = builder.partition
        self.broad_phase = builder.broad_phase
        self.dhat = builder.dhat
        self.builder = builder
        self.obstacles = obstacles
        self.names = names
        self.pairs = pairs
        self.min_gap = min_gap

    def _body_label(self, body: int) -> str:
        return body_label(self.surface, self.obstacles, self.names, body)

    def _pair_label(self, a: int, b: int) -> str:
        return pair_label(self._body_label, a, b)

    def minimum_distance(self, x: np.ndarray, step: int) -> float:
        """The minimum distance of the configuration x of step ``step`` (collective).

        Raises:
            IntersectionError: Naming the bodies that intersect or are closer than
                ``min_gap * dhat``.
        """
        mesh = self.surface.mesh
        if ipctk.has_intersections(mesh, np.asfortranarray(x), self.broad_phase):
            pairs = [
                self._pair_label(a, b) for a, b in intersecting_pairs(self.surface, self.pairs, x)
            ]
            raise IntersectionError(
                f"the configuration at step {step} intersects: {'; '.join(pairs) or 'unknown'}"
                " (separate the bodies or fix the mesh)"
            )
        C = self.builder.build(x)
        dist = self.partition.minimum_distance(C, mesh, x)
        if dist <= self.min_gap * self.dhat:
            gap = self.min_gap * self.dhat
            pairs = [
                self._pair_label(a, b)
                for a, b in close_pairs(self.surface, self.pairs, x, self.dhat, gap)
            ]
            raise IntersectionError(
                f"at step {step} {'; '.join(pairs) or 'some bodies'} are {dist:.3e} apart, closer"
                f" than {self.min_gap:g} dhat = {self.min_gap * self.dhat:.3e}: the barrier"
                " cannot start from touching bodies (leave a gap)"
            )
        return dist
