"""Shape control: rest positions of mesh vertices (paper: the geometric map q-bar)."""

import functools
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, override

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from mpi4py import MPI

from diffsolids.adjoint.sensitivities import Sensitivities, Targets
from diffsolids.contact.boundary_intersection import BoundaryIntersection
from diffsolids.controls.base import Control, ControlError
from diffsolids.errors import InvertedElementError
from diffsolids.mesh import Domain, inverted_cells
from diffsolids.model import undo_on_refusal
from diffsolids.parallel import collective_comm

if TYPE_CHECKING:
    from diffsolids.model import Model
    from diffsolids.simulation import Simulation

__all__ = ["ShapeControl", "boundary_vertices"]


def boundary_vertices(domain: Domain, exclude_facets: Sequence[int | str] = ()) -> np.ndarray:
    """Canonical (input) indices of boundary vertices, excluding vertices of tagged facets."""
    import dolfinx.mesh

    mesh = domain.mesh
    fdim = mesh.topology.dim - 1
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    nodes = np.unique(dolfinx.mesh.entities_to_geometry(mesh, fdim, facets))
    excluded = [domain.facets_of(t) for t in exclude_facets]
    if excluded:
        ex = np.unique(dolfinx.mesh.entities_to_geometry(mesh, fdim, np.concatenate(excluded)))
        nodes = np.setdiff1d(nodes, ex)
    ids = mesh.geometry.input_global_indices[nodes]
    return np.unique(np.concatenate(collective_comm(domain.comm).allgather(ids)))


class ShapeControl(Control):
    """Rest coordinates X = X0 + P q of (some) mesh vertices.

    Args:
        model: The Model (all geometry vertices are potential design variables).
        vertices: "all", "boundary", an array of canonical vertex indices (input order), or a
            marker ``x -> bool`` selecting vertices by rest position.
        exclude_facets: With "boundary": facet tags whose vertices stay fixed.
        linear_map: Optional matrix (num_vertices * dim x k) from k design variables to the
            displacement of all vertices in canonical order; overrides ``vertices``. A
            ``scipy.sparse.linalg.LinearOperator`` (e.g. a mesh-motion extension) is used as
            is; its products must be collective and identical on all ranks.
        refuse_intersections: Also refuse rest shapes whose boundary intersects itself, another
            body or an obstacle of the model's contact terms (a fold that inverts no cell).
            The refused shape is not applied; the optimiser treats the error as an invalid
            trial and backs off.
    """

    name = "shape"

    def __init__(
        self,
        model: "Model",
        vertices: str | npt.ArrayLike | Callable[[np.ndarray], np.ndarray] = "all",
        exclude_facets: Sequence[int | str] = (),
        linear_map: npt.ArrayLike | sp.spmatrix | sp.sparray | spla.LinearOperator | None = None,
        refuse_intersections: bool = False,
    ) -> None:
        self.model = model
        self.boundary = BoundaryIntersection(model) if refuse_intersections else None
        domain = model.domain
        mesh = domain.mesh
        self.dim = mesh.geometry.dim
        self.comm = mesh.comm
        gmap = mesh.geometry.index_map()
        self.num_vertices = gmap.size_global
        self.owned_nodes = gmap.size_local
        self.input_index = mesh.geometry.input_global_indices
        self.X0 = mesh.geometry.x[:, : self.dim].copy()
        n = self.num_vertices * self.dim
        if linear_map is not None:
            is_op = isinstance(linear_map, spla.LinearOperator)
            P = linear_map if is_op else sp.csr_matrix(linear_map)
            if P.shape[0] != n:
                raise ControlError(f"shape linear_map has {P.shape[0]} rows, expected {n}")
        else:
            sel = self._select(domain, vertices, exclude_facets)
            cols = (sel[:, None] * self.dim + np.arange(self.dim)).ravel()
            P = sp.csr_matrix(
                (np.ones(len(cols)), (cols, np.arange(len(cols)))), shape=(n, len(cols))
            )
        self.P = P
        self.q = np.zeros(P.shape[1])
        S = model.shape_space
        # S dof (P1, same per-cell ordering as the geometry) -> geometry node
        self._s_to_node = np.empty(
            S.dofmap.index_map.size_local + S.dofmap.index_map.num_ghosts, dtype=np.int64
        )
        self._s_to_node[S.dofmap.list.ravel()] = mesh.geometry.dofmaps[0].ravel()
        self._s_owned = S.dofmap.index_map.size_local

    def _select(
        self,
        domain: Domain,
        vertices: str | npt.ArrayLike | Callable[[np.ndarray], np.ndarray],
        exclude: Sequence[int | str],
    ) -> np.ndarray:
        if isinstance(vertices, str):
            if vertices == "all":
                return np.arange(self.num_vertices)
            if vertices == "boundary":
                return boundary_vertices(domain, exclude)
            raise ControlError(f"unknown vertex selection {vertices!r}")
        if callable(vertices):
            mask = np.asarray(vertices(self.X0.T), dtype=bool)
            ids = self.input_index[mask]
            return np.unique(np.concatenate(collective_comm(self.comm).allgather(ids)))
        ids = np.unique(np.asarray(vertices, dtype=np.int64))
        if ids.size and (ids.min() < 0 or ids.max() >= self.num_vertices):
            raise ControlError(f"vertex indices out of range 0..{self.num_vertices - 1}")
        return ids

    @override
    def check(self, simulation: "Simulation") -> None:
        if simulation.model is not self.model:
            raise ControlError("shape control belongs to a different model")

    @override
    @property
    def size(self) -> int:
        return self.P.shape[1]

    @override
    def value(self) -> np.ndarray:
        return self.q.copy()

    def displacement(self, q: np.ndarray) -> np.ndarray:
        """Vertex displacements (num_vertices x dim, canonical order) of parameters q."""
        return (self.P @ q).reshape(-1, self.dim)

    @override
    def assign(self, q: np.ndarray) -> None:
        mesh = self.model.domain.mesh
        dX = self.displacement(np.asarray(q, dtype=float))
        new = self.X0 + dX[self.input_index]
        bad = inverted_cells(mesh, self.model.reference_signs, _padded(new, mesh.geometry.x))
        total = collective_comm(self.comm).allreduce(len(bad), op=MPI.SUM)
        if total:
            orig = mesh.topology.original_cell_index[bad]
            shown = sorted(
                set().union(*collective_comm(self.comm).allgather(set(orig[:20].tolist())))
            )
            raise InvertedElementError(
                f"shape update inverts {total} cells (input cell indices {shown[:20]})", cells=bad
            )
        old = mesh.geometry.x[:, : self.dim].copy()
        self._move_rest(new)
        if self.boundary is not None and self.boundary.intersects():
            self._move_rest(old)
            raise InvertedElementError(
                "the shape update folds the boundary over itself (or into another body or an "
                "obstacle); the shape was not changed"
            )
        # a point refused as a whole (another control's field) moves the shape back
        undo_on_refusal(functools.partial(self._restore, old, self.q))
        self.q = np.asarray(q, dtype=float).copy()

    def _restore(self, X: np.ndarray, q: np.ndarray) -> None:
        self._move_rest(X)
        self.q = q

    def _move_rest(self, X: np.ndarray) -> None:
        self.model.domain.mesh.geometry.x[:, : self.dim] = X
        for term in self.model.numeric_terms:
            term.update_rest_positions()

    @override
    def targets(self) -> Targets:
        return Targets(shape=True)

    @override
    def transfer(self, old: Control, block: np.ndarray) -> np.ndarray:
        if not isinstance(old, ShapeControl):
            return super().transfer(old, block)
        return np.zeros(self.size)  # the new mesh is the rest shape at the old iterate

    def vertex_gradient(self, sens: Sensitivities) -> np.ndarray:
        """dJ/dX per vertex (num_vertices x dim, canonical order, identical on all ranks)."""
        g = sens.shape[: self._s_owned * self.dim].reshape(-1, self.dim)
        nodes = self._s_to_node[: self._s_owned]
        out = np.zeros((self.num_vertices, self.dim))
        out[self.input_index[nodes]] = g
        return collective_comm(self.comm).allreduce(out, op=MPI.SUM)

    @override
    def pullback(self, sens: Sensitivities) -> np.ndarray:
        return self.P.T @ self.vertex_gradient(sens).ravel()


def _padded(xd: np.ndarray, x: np.ndarray) -> np.ndarray:
    out = x.copy()
    out[:, : xd.shape[1]] = xd
    return out
