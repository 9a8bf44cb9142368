"""Helpers shared by the static shape-optimisation demos (bridges, 3D beam, interlocking parts).

Measurements of a state (volume, maximum von Mises stress, inverted cells, self-intersection
of the boundary), output of the initial and final states, and the before/after figures.
All functions are collective over the mesh communicator and return the same value on every
rank.
"""

from pathlib import Path

import dolfinx.mesh
import ipctk
import numpy as np
from dolfinx import fem
from mpi4py import MPI

from diffsolids.contact.surface import CollisionSurface
from diffsolids.controls import ShapeControl
from diffsolids.errors import InvertedElementError
from diffsolids.io import TrajectoryWriter
from diffsolids.io.output import von_mises_field
from diffsolids.mesh import inverted_cells, min_scaled_jacobian
from diffsolids.optimize import MeshMotionControl
from diffsolids.parallel import collective_comm

__all__ = [
    "BoundaryCheck",
    "GuardedMeshMotion",
    "GuardedShapeControl",
    "Invariants",
    "design_vertex_coordinates",
    "facet_polygons_2d",
    "max_von_mises",
    "min_quality",
    "num_inverted",
    "plot_shapes_2d",
    "plot_shapes_3d",
    "silhouettes_3d",
    "vertex_coordinates",
    "volume",
    "write_state",
]


def vertex_coordinates(domain) -> np.ndarray:
    """Vertex positions (num_vertices, dim) in canonical (input) order, on every rank."""
    mesh = domain.mesh
    dim = mesh.geometry.dim
    n = mesh.geometry.index_map().size_local
    out = np.zeros((mesh.geometry.index_map().size_global, dim))
    out[mesh.geometry.input_global_indices[:n]] = mesh.geometry.x[:n, :dim]
    return collective_comm(domain.comm).allreduce(out, op=MPI.SUM)


def design_vertex_coordinates(control) -> np.ndarray:
    """Reference positions of the design vertices of a MeshMotionControl (parameter order)."""
    motion = control.motion
    X = motion.reference[:, : motion.dim]
    mesh = motion.domain.mesh
    n = mesh.geometry.index_map().size_local
    out = np.zeros((motion.num_vertices, motion.dim))
    out[mesh.geometry.input_global_indices[:n]] = X[:n]
    return collective_comm(motion.comm).allreduce(out, op=MPI.SUM)[motion.design]


def volume(model) -> float:
    """Rest volume (area in 2D) of the model's mesh."""
    local = fem.assemble_scalar(fem.form(1.0 * model.fields.dx))
    return collective_comm(model.domain.comm).allreduce(local, op=MPI.SUM)


def max_von_mises(model, u: np.ndarray) -> float:
    """Largest cellwise (midpoint) von Mises stress of a displacement array."""
    field = von_mises_field(model, u)
    local = field.x.array.max() if field.x.array.size else -np.inf
    return collective_comm(model.domain.comm).allreduce(float(local), op=MPI.MAX)


def num_inverted(model) -> int:
    """Cells of the current rest mesh whose orientation flipped against the original mesh."""
    bad = inverted_cells(model.domain.mesh, model.reference_signs)
    return collective_comm(model.domain.comm).allreduce(len(bad), op=MPI.SUM)


def min_quality(model) -> float:
    """Minimum scaled Jacobian of the current rest mesh."""
    return float(min_scaled_jacobian(model.domain.mesh))


class BoundaryCheck:
    """Self-intersection test of a model's boundary (all bodies) with ipctk.

    ``check(u)`` tests the rest boundary (``u`` None) or the deformed one, ``X + u``.
    """

    def __init__(self, model):
        self.model = model
        self.surface = CollisionSurface(model.domain, model.V)

    def intersects(self, u: np.ndarray | None = None) -> bool:
        """Whether the boundary at rest (or deformed by ``u``) intersects itself."""
        s = self.surface
        s.update_rest_positions()
        x = s.rest_positions.copy()
        if u is not None:
            x += s.gather(u)
        return bool(ipctk.has_intersections(s.mesh, np.asfortranarray(x), ipctk.LBVH()))


class _BoundaryGuard:
    """Refuses rest shapes whose boundary intersects itself (mixin of a shape control).

    Inverted cells are refused by ShapeControl; a fold of the boundary over another part of
    the body (or over another body) can happen without them. The optimiser treats the error
    as an invalid trial and returns to the last accepted shape.
    """

    def assign(self, q: np.ndarray) -> None:
        """Apply q, then refuse a self-intersecting boundary (InvertedElementError)."""
        super().assign(q)
        if self.boundary.intersects():
            raise InvertedElementError("the shape update folds the boundary over itself")


class GuardedMeshMotion(_BoundaryGuard, MeshMotionControl):
    """MeshMotionControl that also refuses rest shapes with a self-intersecting boundary."""

    def __init__(self, model, **kwargs):
        super().__init__(model, **kwargs)
        self.boundary = BoundaryCheck(model)


class GuardedShapeControl(_BoundaryGuard, ShapeControl):
    """ShapeControl that also refuses rest shapes with a self-intersecting boundary."""

    def __init__(self, model, **kwargs):
        super().__init__(model, **kwargs)
        self.boundary = BoundaryCheck(model)


class Invariants:
    """Stop condition that never stops: checks every accepted iterate (collective).

    Counts iterates with inverted cells, with a self-intersecting rest boundary and (with
    ``deformed``) with a self-intersecting deformed boundary at the last state.
    """

    def __init__(self, deformed: bool = False):
        self.deformed = deformed
        self.inverted = 0
        self.intersecting = 0
        self.intersecting_deformed = 0
        self.checked = 0
        self._checks: dict[int, BoundaryCheck] = {}

    def __call__(self, record, optimizer) -> bool:
        """Check the accepted iterate of ``optimizer``; returns False (never stops the run)."""
        rf = optimizer.rf
        model = rf.model
        if id(model) not in self._checks:
            self._checks[id(model)] = BoundaryCheck(model)
        check = self._checks[id(model)]
        self.inverted += int(num_inverted(model) > 0)
        self.intersecting += int(check.intersects())
        if self.deformed:
            self.intersecting_deformed += int(check.intersects(rf.trajectory.u[-1]))
        self.checked += 1
        return False


def write_state(model, path: Path, u: np.ndarray) -> list[Path]:
    """Write one state (displacement and von Mises stress) as VTX ``.bp`` or XDMF; returns files."""
    writer = TrajectoryWriter(model, path)
    writer.write(0.0, u, np.zeros_like(u))
    writer.close()
    if path.suffix == ".xdmf":
        return [path, path.with_suffix(".h5")]
    return [path, path.with_name(path.stem + "_cells.bp")]


def facet_polygons_2d(model, u: np.ndarray | None = None) -> np.ndarray:
    """Boundary edges (n, 2, 2) of a 2D model at rest or deformed, gathered on every rank."""
    mesh = model.domain.mesh
    mesh.topology.create_connectivity(1, 2)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    nodes = dolfinx.mesh.entities_to_geometry(mesh, 1, facets)
    x = mesh.geometry.x[:, :2].copy()
    if u is not None:
        x += _nodal_displacement(model, u)
    return np.concatenate(collective_comm(mesh.comm).allgather(x[nodes]))


def silhouettes_3d(model, axes=(1, 2)) -> list[np.ndarray]:
    """Silhouette edges of a 3D model's rest boundary seen along each of the given axes.

    An edge of the boundary belongs to the silhouette seen along axis k when the outward
    normals of its two boundary triangles point to opposite sides of k (one faces the viewer,
    the other away). Returns one (n, 2, 3) array of edge end points per axis, on every rank.
    """
    mesh = model.domain.mesh
    mesh.topology.create_connectivity(2, 3)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    nodes = dolfinx.mesh.entities_to_geometry(mesh, 2, facets)
    f2c = mesh.topology.connectivity(2, 3)
    cells = f2c.array[f2c.offsets[facets]]
    corner = mesh.geometry.dofmaps[0][cells]
    x = mesh.geometry.x
    tri = x[nodes]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    centroid = x[corner].mean(axis=1)  # inside the cell: the normal points away from it
    normal *= -np.sign(np.sum(normal * (centroid - tri[:, 0]), axis=1))[:, None]
    ids = mesh.geometry.input_global_indices[nodes]
    parts = collective_comm(mesh.comm).allgather((ids, tri, normal))
    ids, tri, normal = (np.concatenate([p[k] for p in parts]) for k in range(3))
    _, first = np.unique(np.sort(ids, axis=1), axis=0, return_index=True)  # once per facet
    tri_ids, tri, normal = ids[first], tri[first], normal[first]
    # edges (sorted global vertex ids) of every triangle with the triangle they belong to
    edges, owner, ends = [], [], []
    for i, j in ((0, 1), (1, 2), (2, 0)):
        e = np.sort(tri_ids[:, [i, j]], axis=1)
        edges.append(e)
        owner.append(np.arange(len(tri_ids)))
        ends.append(tri[:, [i, j]])
    edges, owner, ends = np.concatenate(edges), np.concatenate(owner), np.concatenate(ends)
    key = np.lexsort(edges.T[::-1])
    edges, owner, ends = edges[key], owner[key], ends[key]
    pair = np.flatnonzero(np.all(edges[1:] == edges[:-1], axis=1))
    out = []
    unit = normal / np.linalg.norm(normal, axis=1)[:, None]
    for k in axes:
        side = np.where(np.abs(unit[:, k]) < 1e-6, 0.0, np.sign(unit[:, k]))
        flip = side[owner[pair]] != side[owner[pair + 1]]
        out.append(ends[pair[flip]])
    return out


def _nodal_displacement(model, u: np.ndarray) -> np.ndarray:
    """Displacement (num nodes, dim) at the geometry nodes (P1 interpolation of u)."""
    mesh = model.domain.mesh
    dim = model.dim
    P1 = fem.functionspace(mesh, ("Lagrange", 1, (dim,)))
    src = fem.Function(model.V)
    src.x.array[:] = u
    dst = fem.Function(P1)
    dst.interpolate(src)
    dof_of_node = np.empty(len(mesh.geometry.x), dtype=np.int64)
    dof_of_node[mesh.geometry.dofmaps[0].ravel()] = P1.dofmap.list.ravel()
    return dst.x.array.reshape(-1, dim)[dof_of_node]


def plot_shapes_2d(
    path: Path, before, after, result, title: str, comm, target=None, labels=None
) -> None:
    """Boundary before (grey), after (blue) and optionally a target (dashed); J per iteration."""
    if comm.rank != 0:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from common import plot_history, save_figure
    from matplotlib.collections import LineCollection

    labels = labels or ("initial", "optimised", "target")
    fig, (ax, ax_j) = plt.subplots(1, 2, figsize=(13, 3.6), gridspec_kw={"width_ratios": [2.6, 1]})
    ax.add_collection(LineCollection(before, colors="0.6", lw=0.8, label=labels[0]))
    ax.add_collection(LineCollection(after, colors="C0", lw=1.4, label=labels[1]))
    if target is not None:
        ax.add_collection(
            LineCollection(target, colors="k", lw=0.8, linestyles="--", label=labels[2])
        )
    ax.autoscale()
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize="small")
    ax.set_title(title, fontsize="medium")
    plot_history(ax_j, result)
    fig.tight_layout()
    save_figure(fig, path, comm)
    plt.close(fig)


def plot_shapes_3d(path: Path, before, after, result, title: str, comm) -> None:
    """Side (x-z) and top (x-y) silhouettes before and after (see silhouettes_3d); J history."""
    if comm.rank != 0:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from common import plot_history, save_figure
    from matplotlib.collections import LineCollection

    fig = plt.figure(figsize=(12, 4.6))
    grid = fig.add_gridspec(2, 2, width_ratios=[2.4, 1])
    axes = [fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[1, 0]), fig.add_subplot(grid[:, 1])]
    views = (((0, 2), "side (x-z)"), ((0, 1), "top (x-y)"))
    for ax, ((a, b), name), edges0, edges1 in zip(axes[:2], views, before, after, strict=True):
        ax.add_collection(
            LineCollection(edges0[:, :, [a, b]], colors="0.6", lw=0.8, label="initial")
        )
        ax.add_collection(
            LineCollection(edges1[:, :, [a, b]], colors="C0", lw=1.3, label="optimised")
        )
        ax.autoscale()
        ax.set_aspect("equal")
        ax.set_title(name, fontsize="medium")
    axes[0].legend(loc="upper right", fontsize="small")
    plot_history(axes[2], result)
    fig.suptitle(title, fontsize="medium")
    fig.tight_layout()
    save_figure(fig, path, comm)
    plt.close(fig)
