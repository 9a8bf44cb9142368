"""The `Domain`: a DOLFINx mesh with its body and boundary tags."""

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import dolfinx
import numpy as np
import numpy.typing as npt
from mpi4py import MPI

from diffsolids.errors import TagError
from diffsolids.parallel import collective_comm

__all__ = ["Domain", "create_box", "create_rectangle", "tag_facets"]


@dataclass
class Domain:
    """A mesh whose cells are tagged by body and whose facets are tagged by boundary part.

    Attributes:
        mesh: The DOLFINx mesh (triangles in 2D, tetrahedra in 3D).
        cell_tags: Body id of every cell (all cells carry a tag; default 1).
        facet_tags: Boundary-part ids of tagged facets (may be empty).
        names: Optional names of tags, e.g. ``{"clamp": 1}`` (bodies and facets share it).
    """

    mesh: dolfinx.mesh.Mesh
    cell_tags: dolfinx.mesh.MeshTags
    facet_tags: dolfinx.mesh.MeshTags
    names: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        tdim = self.mesh.topology.dim
        self.mesh.topology.create_connectivity(tdim - 1, tdim)
        self.mesh.topology.create_connectivity(tdim, tdim - 1)
        self._body_ids = _global_unique(self.mesh.comm, self.cell_tags.values)
        self._facet_ids = _global_unique(self.mesh.comm, self.facet_tags.values)

    @classmethod
    def from_mesh(
        cls,
        mesh: dolfinx.mesh.Mesh,
        cell_tags: dolfinx.mesh.MeshTags | None = None,
        facet_tags: dolfinx.mesh.MeshTags | None = None,
        names: Mapping[str, int] | None = None,
    ) -> "Domain":
        """Wrap a DOLFINx mesh; untagged cells become body 1, missing facet tags are empty."""
        tdim = mesh.topology.dim
        num_cells = (
            mesh.topology.index_map(tdim).size_local + mesh.topology.index_map(tdim).num_ghosts
        )
        if cell_tags is None:
            cells = np.arange(num_cells, dtype=np.int32)
            cell_tags = dolfinx.mesh.meshtags(mesh, tdim, cells, np.ones(num_cells, np.int32))
        if facet_tags is None:
            empty = np.zeros(0, np.int32)
            facet_tags = dolfinx.mesh.meshtags(mesh, tdim - 1, empty, empty)
        return cls(mesh, cell_tags, facet_tags, dict(names or {}))

    @property
    def dim(self) -> int:
        """Geometric (and topological) dimension."""
        return self.mesh.geometry.dim

    @property
    def comm(self) -> MPI.Comm:
        """The mesh communicator."""
        return self.mesh.comm

    @property
    def body_ids(self) -> list[int]:
        """Sorted body (cell tag) ids present on any rank."""
        return list(self._body_ids)

    @property
    def facet_ids(self) -> list[int]:
        """Sorted facet tag ids present on any rank."""
        return list(self._facet_ids)

    def body_id(self, body: int | str) -> int:
        """Resolve a body given by id or name; raise TagError if the mesh has no such body."""
        return self._resolve(body, self._body_ids, "body (cell tag)")

    def facet_id(self, tag: int | str) -> int:
        """Resolve a facet tag given by id or name; raise TagError if it does not exist."""
        return self._resolve(tag, self._facet_ids, "facet tag")

    def _resolve(self, key: int | str, present: list[int], what: str) -> int:
        if isinstance(key, str):
            if key not in self.names:
                raise TagError(f"unknown {what} name {key!r}; known names: {sorted(self.names)}")
            key = self.names[key]
        if int(key) not in present:
            raise TagError(f"unknown {what} {key}; the mesh has {what}s {present}")
        return int(key)

    def cells_of(self, body: int | str) -> np.ndarray:
        """Local cell indices (owned and ghost) of a body."""
        return self.cell_tags.find(self.body_id(body))

    def facets_of(self, tag: int | str) -> np.ndarray:
        """Local facet indices with a facet tag."""
        return self.facet_tags.find(self.facet_id(tag))

    def bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        """Global (min, max) corners of the rest configuration."""
        x = self.mesh.geometry.x[:, : self.dim]
        lo = np.array(x.min(axis=0) if len(x) else np.full(self.dim, np.inf), dtype=np.float64)
        hi = np.array(x.max(axis=0) if len(x) else np.full(self.dim, -np.inf), dtype=np.float64)
        # buffer (elementwise) reductions: the pickle-based allreduce applies min() to whole
        # arrays and raises on one rank while the other waits
        self.comm.Allreduce(MPI.IN_PLACE, lo, op=MPI.MIN)
        self.comm.Allreduce(MPI.IN_PLACE, hi, op=MPI.MAX)
        return lo, hi

    def characteristic_length(self) -> float:
        """Diagonal of the bounding box."""
        lo, hi = self.bounding_box()
        return float(np.linalg.norm(hi - lo))


def _global_unique(comm: MPI.Comm, values: np.ndarray) -> list[int]:
    local = np.unique(values).astype(int).tolist()
    return sorted(set().union(*collective_comm(comm).allgather(local)))


def tag_facets(
    mesh: dolfinx.mesh.Mesh, markers: Mapping[int, Callable[[np.ndarray], np.ndarray]]
) -> dolfinx.mesh.MeshTags:
    """Tag boundary facets with ids given by geometric markers ``{id: marker(x) -> bool}``.

    Later markers win where several match a facet.
    """
    fdim = mesh.topology.dim - 1
    mesh.topology.create_connectivity(fdim, fdim + 1)
    facet_values: dict[int, int] = {}
    for tag, marker in markers.items():
        for f in dolfinx.mesh.locate_entities_boundary(mesh, fdim, marker):
            facet_values[int(f)] = int(tag)
    facets = np.array(sorted(facet_values), dtype=np.int32)
    values = np.array([facet_values[f] for f in facets], dtype=np.int32)
    return dolfinx.mesh.meshtags(mesh, fdim, facets, values)


def _tag_cells(
    mesh: dolfinx.mesh.Mesh, bodies: Mapping[int, Callable[[np.ndarray], np.ndarray]] | None
) -> dolfinx.mesh.MeshTags | None:
    if not bodies:
        return None
    tdim = mesh.topology.dim
    imap = mesh.topology.index_map(tdim)
    num_cells = imap.size_local + imap.num_ghosts
    values = np.ones(num_cells, dtype=np.int32)
    midpoints = dolfinx.mesh.compute_midpoints(mesh, tdim, np.arange(num_cells, dtype=np.int32))
    for tag, marker in bodies.items():
        values[marker(midpoints.T)] = tag
    return dolfinx.mesh.meshtags(mesh, tdim, np.arange(num_cells, dtype=np.int32), values)


def create_rectangle(
    comm: MPI.Comm,
    corners: npt.ArrayLike,
    n: Sequence[int],
    facets: Mapping[int, Callable[[np.ndarray], np.ndarray]] | None = None,
    bodies: Mapping[int, Callable[[np.ndarray], np.ndarray]] | None = None,
    names: Mapping[str, int] | None = None,
    diagonal: str = "right",
) -> Domain:
    """A triangulated rectangle.

    Args:
        comm: MPI communicator.
        corners: ``[[x0, y0], [x1, y1]]``.
        n: Cells per direction ``[nx, ny]``.
        facets: Optional ``{tag: marker(x)}`` boundary markers.
        bodies: Optional ``{tag: marker(midpoints)}`` cell markers (default: all body 1).
        names: Optional tag names.
        diagonal: Diagonal direction ("right", "left", "crossed", ...).
    """
    mesh = dolfinx.mesh.create_rectangle(
        comm,
        [np.asarray(c, dtype=float) for c in corners],
        list(n),
        dolfinx.mesh.CellType.triangle,
        diagonal=dolfinx.mesh.DiagonalType[diagonal],
    )
    return _wrap(mesh, facets, bodies, names)


def create_box(
    comm: MPI.Comm,
    corners: npt.ArrayLike,
    n: Sequence[int],
    facets: Mapping[int, Callable[[np.ndarray], np.ndarray]] | None = None,
    bodies: Mapping[int, Callable[[np.ndarray], np.ndarray]] | None = None,
    names: Mapping[str, int] | None = None,
) -> Domain:
    """A tetrahedral box; arguments as in :func:`create_rectangle`."""
    mesh = dolfinx.mesh.create_box(
        comm,
        [np.asarray(c, dtype=float) for c in corners],
        list(n),
        dolfinx.mesh.CellType.tetrahedron,
    )
    return _wrap(mesh, facets, bodies, names)


def _wrap(
    mesh: dolfinx.mesh.Mesh,
    facets: Mapping[int, Callable[[np.ndarray], np.ndarray]] | None,
    bodies: Mapping[int, Callable[[np.ndarray], np.ndarray]] | None,
    names: Mapping[str, int] | None,
) -> Domain:
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim - 1, tdim)
    facet_tags = tag_facets(mesh, facets) if facets else None
    return Domain.from_mesh(mesh, _tag_cells(mesh, bodies), facet_tags, names)
