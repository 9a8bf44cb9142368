"""Kinematic obstacles: collision-only geometry moved by a prescribed function of time.

An :class:`Obstacle` is a 2D polyline (segments) or a 3D triangle surface, or the boundary of
a volume mesh, that takes part in IPC contact and friction (``ContactTerm(...,
obstacles=[...])``) without any degree of freedom in the finite-element system: its vertices
are extra vertices of the collision mesh whose displacements are prescribed at every step.

Motion: ``motion(t)`` returns the obstacle's placement at time (or load parameter) ``t``:

- an array of shape ``(num_vertices, dim)``: the displacement of every vertex from
  ``vertices``;
- an array of shape ``(dim,)``: a translation of the whole obstacle;
- a pair ``(R, b)`` with ``R`` of shape ``(dim, dim)`` and ``b`` of shape ``(dim,)``: the rigid
  (or affine) placement ``x = R X + b`` of the rest vertices ``X``.

``motion=None`` is a fixed obstacle. The function is evaluated on every rank and rank 0's
values are broadcast, so all ranks hold the same obstacle (obstacles are global data).

Area weights (``ContactTerm(area_weighting=True)``): ipctk weights a 2D vertex-edge pair by half
the vertex's area (half the lengths of its edges), a 3D vertex-face pair by a quarter of the
vertex's area and an edge-edge pair by a quarter of the two edges' areas, with the areas of
the collision mesh's own primitives: an obstacle vertex gets its area from the obstacle's
segments/triangles, exactly as the boundary vertex of a meshed volume does from its boundary
facets. So an obstacle whose geometry is a clamped volume's boundary
(:meth:`Obstacle.from_domain`) gives the same contact as that volume (the same collision set,
weights and trajectory; tests/test_obstacles.py checks it). A coarser obstacle for the same
surface (a plane as two triangles) has no vertices under a body: its pairs are the body's
vertices against the obstacle's faces only, the pairs of obstacle vertices against the body's
faces are missing, and in flat contact the barrier carries about half the weight of a finely
meshed obstacle (the contact force is the same at equilibrium, its gap is smaller). PolyFEM's
``is_obstacle`` surfaces behave the same way (the same ipctk collision sets).
"""

import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import dolfinx
import numpy as np
import numpy.typing as npt
from mpi4py import MPI

from diffsolids.errors import MeshError, ParameterError
from diffsolids.mesh import Domain
from diffsolids.mesh.readers import _rotation_matrix
from diffsolids.parallel import collective_comm

__all__ = ["Obstacle", "checked_obstacles"]

Motion = Callable[[float], Any]


def _edges_of(faces: np.ndarray) -> np.ndarray:
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(pairs, axis=0).astype(np.int32)


class Obstacle:
    """Collision-only geometry (no dofs), fixed or moved by a prescribed function of time.

    Args:
        vertices: (n, dim) rest coordinates, dim 2 or 3.
        edges: 2D only: (m, 2) vertex indices of the segments (default: the open polyline
            through the vertices in order).
        faces: 3D only: (m, 3) vertex indices of the triangles (required in 3D).
        motion: ``motion(t)`` -> displacement (n, dim), translation (dim,) or ``(R, b)``; None:
            fixed. See the module docstring.
        name: Name used in friction tables (``{("block", "ground"): 0.3}``), errors and records.

    Raises:
        MeshError: Bad coordinates or connectivity (wrong shape, index out of range, degenerate
            segment or triangle, faces in 2D, no faces in 3D).
        ParameterError: A motion that is not callable.
    """

    def __init__(
        self,
        vertices: npt.ArrayLike,
        edges: npt.ArrayLike | None = None,
        faces: npt.ArrayLike | None = None,
        motion: Motion | None = None,
        name: str | None = None,
    ) -> None:
        X = np.asarray(vertices, dtype=float)
        label = f"obstacle {name!r}" if name else "obstacle"
        if X.ndim != 2 or X.shape[1] not in (2, 3) or len(X) == 0:
            raise MeshError(f"{label}: vertices of shape {X.shape}, expected (n, 2) or (n, 3)")
        if not np.all(np.isfinite(X)):
            raise MeshError(f"{label}: non-finite vertex coordinates")
        self.dim = X.shape[1]
        self.name = name
        self.label = label
        n = len(X)
        if self.dim == 2:
            if faces is not None and len(np.asarray(faces)):
                raise MeshError(f"{label}: a 2D obstacle has segments (edges), not faces")
            E = (
                np.column_stack([np.arange(n - 1), np.arange(1, n)])
                if edges is None
                else np.asarray(edges)
            )
            F = np.zeros((0, 3), dtype=np.int32)
            prims = self._indices(E, 2, n, "edges")
            length = np.linalg.norm(X[prims[:, 1]] - X[prims[:, 0]], axis=1)
            degenerate = length <= 1e-14 * max(1.0, float(np.abs(X).max()))
            E = prims
        else:
            if faces is None:
                raise MeshError(f"{label}: a 3D obstacle needs triangles (faces)")
            F = self._indices(np.asarray(faces), 3, n, "faces")
            area = np.linalg.norm(
                np.cross(X[F[:, 1]] - X[F[:, 0]], X[F[:, 2]] - X[F[:, 0]]), axis=1
            )
            degenerate = area <= 1e-28 * max(1.0, float(np.abs(X).max())) ** 2
            E = _edges_of(F)
        if np.any(degenerate):
            k = int(np.flatnonzero(degenerate)[0])
            kind = "segment" if self.dim == 2 else "triangle"
            raise MeshError(f"{label}: {kind} {k} is degenerate (zero length or area)")
        if motion is not None and not callable(motion):
            raise ParameterError(f"{label}: motion must be a function of time, got {motion!r}")
        self.rest_positions = np.ascontiguousarray(X)
        self.edges = np.ascontiguousarray(E, dtype=np.int32)
        self.faces = np.ascontiguousarray(F, dtype=np.int32)
        self.motion = motion

    def _indices(self, prims: np.ndarray, width: int, n: int, what: str) -> np.ndarray:
        P = np.asarray(prims)
        if P.ndim != 2 or P.shape[1] != width or len(P) == 0:
            raise MeshError(f"{self.label}: {what} of shape {P.shape}, expected (m, {width})")
        if not np.issubdtype(P.dtype, np.integer) and not np.all(np.round(P) == P):
            raise MeshError(f"{self.label}: {what} must hold integer vertex indices")
        P = P.astype(np.int64)
        if P.min() < 0 or P.max() >= n:
            raise MeshError(
                f"{self.label}: {what} refer to vertex {int(P.max() if P.max() >= n else P.min())}"
                f" of {n}"
            )
        if np.any(np.diff(np.sort(P, axis=1), axis=1) == 0):
            raise MeshError(f"{self.label}: {what} with a repeated vertex")
        return P.astype(np.int32)

    @property
    def num_vertices(self) -> int:
        """Number of vertices."""
        return len(self.rest_positions)

    @property
    def moving(self) -> bool:
        """Whether the obstacle has a motion."""
        return self.motion is not None

    def displacement(self, t: float) -> np.ndarray:
        """(n, dim) displacement of the vertices from their rest positions at time ``t``.

        Raises:
            ParameterError: ``motion(t)`` of a wrong shape or not finite.
        """
        X = self.rest_positions
        if self.motion is None:
            return np.zeros_like(X)
        value = self.motion(t)
        n, d = X.shape
        expected = (
            f"({n}, {d}) displacements, a ({d},) translation or a pair (R ({d}, {d}), b ({d},))"
        )
        if isinstance(value, tuple | list) and len(value) == 2 and np.ndim(value[0]) == 2:
            R, b = (np.asarray(v, dtype=float) for v in value)
            if R.shape != (d, d) or b.shape != (d,):
                raise ParameterError(
                    f"{self.label}: motion({t:g}) returned R {R.shape}, b {b.shape}; expected "
                    f"{expected}"
                )
            U = X @ R.T + b - X
        else:
            U = np.asarray(value, dtype=float)
            if U.shape == (d,):
                U = np.broadcast_to(U, X.shape).copy()
            elif U.shape != (n, d):
                raise ParameterError(
                    f"{self.label}: motion({t:g}) returned shape {U.shape}; expected {expected}"
                )
        if not np.all(np.isfinite(U)):
            raise ParameterError(f"{self.label}: motion({t:g}) is not finite")
        return U

    def positions(self, t: float) -> np.ndarray:
        """(n, dim) vertex positions at time ``t``."""
        return self.rest_positions + self.displacement(t)

    @classmethod
    def from_domain(
        cls,
        domain: Domain | dolfinx.mesh.Mesh,
        motion: Motion | None = None,
        name: str | None = None,
    ) -> "Obstacle":
        """The boundary of a volume mesh (e.g. from :func:`diffsolids.mesh.read_mesh`).

        Collective over the domain's communicator: the boundary facets of all ranks are
        gathered, vertices numbered by their input index (the same obstacle on every rank).

        Args:
            domain: A :class:`~diffsolids.mesh.Domain` (or its DOLFINx mesh) of cells of the
                top dimension (triangles/quadrilaterals in 2D, tetrahedra in 3D).
            motion: As for :class:`Obstacle`.
            name: As for :class:`Obstacle`.
        """
        mesh = domain.mesh if isinstance(domain, Domain) else domain
        tdim, gdim = mesh.topology.dim, mesh.geometry.dim
        if tdim != gdim:
            raise MeshError(f"obstacle from a mesh of tdim {tdim} in {gdim}D: expected a volume")
        if mesh.geometry.cmaps[0].degree != 1:
            raise MeshError("obstacle from a mesh of non-affine geometry (degree > 1)")
        mesh.topology.create_connectivity(tdim - 1, tdim)
        facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
        nodes = dolfinx.mesh.entities_to_geometry(mesh, tdim - 1, facets)
        if gdim == 3 and nodes.shape[1] != 3:
            raise MeshError("obstacle from a 3D mesh whose boundary facets are not triangles")
        ids = np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)
        local = (ids[nodes], mesh.geometry.x[nodes.ravel(), :gdim])
        parts = collective_comm(mesh.comm).allgather(local)
        facet_ids = np.concatenate([p[0] for p in parts]).reshape(-1, nodes.shape[1])
        node_x = np.concatenate([p[1] for p in parts])
        uids, first = np.unique(facet_ids.ravel(), return_index=True)
        X = node_x[first]
        prims = np.searchsorted(uids, facet_ids)
        prims = prims[np.lexsort(np.sort(prims, axis=1).T[::-1])]
        if gdim == 2:
            return cls(X, edges=prims, motion=motion, name=name)
        return cls(X, faces=prims, motion=motion, name=name)

    @classmethod
    def from_file(
        cls,
        path: str | os.PathLike,
        *,
        dim: int | None = None,
        scale: float | Sequence[float] = 1.0,
        rotation: float | Sequence[float] | None = None,
        translation: Sequence[float] | None = None,
        motion: Motion | None = None,
        name: str | None = None,
    ) -> "Obstacle":
        """An obstacle from a mesh file (every rank reads it; x' = R (scale x) + translation).

        A surface mesh (3D triangles, e.g. ``.obj``/``.stl``; 2D line segments) is the
        obstacle itself; a volume mesh (2D triangles/quadrilaterals, 3D tetrahedra) gives its
        boundary (:func:`diffsolids.mesh.read_mesh` and :meth:`from_domain`).

        Args:
            path: Any file meshio reads (``.msh`` volumes also through read_mesh).
            dim: Geometric dimension (default: 3 unless the z coordinates are all zero).
            scale: Scale factor, or one per axis (> 0).
            rotation: Degrees, as :func:`diffsolids.mesh.read_mesh` (PolyFEM's
                ``transformation``): an angle in 2D, Euler angles about x, y, z in 3D.
            translation: Translation vector.
            motion: As for :class:`Obstacle`.
            name: As for :class:`Obstacle` (default: the file's stem).

        Raises:
            MeshError: A missing or unreadable file, or one with neither surface nor volume
                cells of the dimension.
        """
        import meshio

        from diffsolids.mesh import read_mesh
        from diffsolids.mesh.readers import check_points_and_cells

        path = Path(path)
        name = path.stem if name is None else name
        if not path.exists():
            raise MeshError(f"obstacle file {path} does not exist")
        try:
            data = meshio.read(path)
        except Exception as e:  # meshio raises many types
            raise MeshError(f"obstacle file {path}: unreadable ({e})") from e
        points = np.asarray(data.points, dtype=float)
        if points.ndim != 2 or len(points) == 0 or not data.cells:
            raise MeshError(f"obstacle file {path}: no points or cells")
        check_points_and_cells(
            f"obstacle file {path}", points, [(c.type, c.data) for c in data.cells]
        )
        if dim is None:
            dim = 3 if points.shape[1] == 3 and np.ptp(points[:, 2]) > 0 else 2
        kinds = {c.type for c in data.cells}
        volume = {"tetra"} if dim == 3 else {"triangle", "quad"}
        if kinds & volume:
            domain = read_mesh(
                path, MPI.COMM_SELF, dim, scale=scale, rotation=rotation, translation=translation
            )
            return cls.from_domain(domain, motion=motion, name=name)
        kind = "triangle" if dim == 3 else "line"
        cells = [c.data for c in data.cells if c.type == kind]
        if not cells:
            raise MeshError(f"obstacle file {path}: no {kind} or volume cells ({sorted(kinds)})")
        prims = np.concatenate(cells)
        used, prims = np.unique(prims, return_inverse=True)
        prims = prims.reshape(-1, 3 if dim == 3 else 2)
        factor = np.broadcast_to(np.asarray(scale, dtype=float), (dim,))
        if not (np.all(np.isfinite(factor)) and np.all(factor > 0)):
            raise MeshError(f"obstacle file {path}: scale {scale} must be finite and positive")
        X = (factor * points[used, :dim]) @ _rotation_matrix(dim, rotation).T
        if translation is not None:
            X = X + np.asarray(translation, dtype=float)
        if dim == 3:
            return cls(X, faces=prims, motion=motion, name=name)
        return cls(X, edges=prims, motion=motion, name=name)

    def broadcast(self, comm: MPI.Comm) -> None:
        """Make the rest geometry rank 0's on every rank (collective)."""
        if comm.size == 1:
            return
        shapes = collective_comm(comm).bcast(
            (self.rest_positions.shape, self.edges.shape, self.faces.shape), root=0
        )
        mine = (self.rest_positions.shape, self.edges.shape, self.faces.shape)
        if collective_comm(comm).allreduce(shapes != mine, op=MPI.LOR):
            raise MeshError(f"{self.label} differs between ranks: {shapes} on rank 0")
        for arr in (self.rest_positions, self.edges, self.faces):
            comm.Bcast(arr, root=0)


def checked_obstacles(obstacles: Sequence[Obstacle], names: Sequence[str]) -> tuple[Obstacle, ...]:
    """The obstacles as a tuple, checked: Obstacle objects whose names are not taken.

    Args:
        obstacles: The obstacles of a contact term.
        names: The names already taken (the domain's names of bodies and tags).

    Raises:
        ParameterError: An obstacle that is not an Obstacle or whose name is taken.
    """
    obstacles = tuple(obstacles)
    names = set(names)
    for o in obstacles:
        if not isinstance(o, Obstacle):
            raise ParameterError(f"obstacles must be Obstacle objects, got {type(o).__name__}")
        if o.name is not None and o.name in names:
            raise ParameterError(
                f"obstacle name {o.name!r} is taken (by a body, tag or another obstacle)"
            )
        if o.name is not None:
            names.add(o.name)
    return obstacles
