"""Discrete regularisers of the rest shape and of material fields (paper sec. 9.3, app. F).

Both are sums over small global structures (boundary edges, pairs of adjacent cells). Every
rank gathers the data it needs (boundary vertex positions, cell values) in the canonical
(input) order and evaluates the same sum in the same order, so values are identical on all
ranks and independent of the partition; each rank then fills the gradient entries it owns.
"""

from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol, override

import dolfinx.mesh
import numpy as np
from mpi4py import MPI

from diffsolids.errors import ParameterError
from diffsolids.mesh.ordering import CanonicalLayout
from diffsolids.objectives.functional import ObjectiveError, Regulariser
from diffsolids.parallel import collective_comm

if TYPE_CHECKING:
    from diffsolids.model import Model

__all__ = ["BoundarySmoothing", "MaterialSmoothing"]


def _allgather_concat(comm: MPI.Comm, local: np.ndarray) -> np.ndarray:
    """Rows of all ranks, in rank order (identical on all ranks)."""
    parts = collective_comm(comm).allgather(local)
    return np.concatenate(parts, axis=0)


class _BuiltForAModel(Protocol):
    """A regulariser or numeric leaf that keeps the model it was made for."""

    model: "Model"


def _check_model(reg: _BuiltForAModel, model: "Model") -> None:
    if model is not reg.model:
        raise ObjectiveError(f"{type(reg).__name__} was built for a different model")


class BoundarySmoothing(Regulariser):
    """Smoothing of the boundary: scale-invariant (paper eq. 37) or the graph Laplacian's.

    Scale-invariant (default): J = sum_{i in B} ||s_i||^p, s_i = sum_j (v_i - v_j) /
    sum_j ||v_i - v_j|| over the neighbours j of i along boundary edges (edges of exterior
    facets). s_i vanishes where the boundary is straight and evenly sampled; J does not
    change when the shape is scaled.

    ``scale_invariant=False``: J = sum_{i in B} ||v_i - mean_j v_j||^2, PolyFEM's
    ``BoundarySmoothingForm`` with ``scale_invariant: false`` (the squared norm of the
    uniform graph Laplacian of the boundary vertices; ``p`` is not used, as there). J has
    units of length squared and grows with the shape's size.

    Args:
        model: The Model (rest positions are its mesh's current vertex positions).
        p: Exponent p > 1 of the scale-invariant form (paper: 2; larger p gives smoother
            surfaces).
        exclude_facets: Facet tags whose vertices are left out of B (e.g. fixed parts).
        scale_invariant: The paper's form (True) or the Laplacian's (False).
    """

    def __init__(
        self,
        model: "Model",
        p: float = 2.0,
        exclude_facets: Sequence[int | str] = (),
        scale_invariant: bool = True,
    ) -> None:
        p = float(p)
        if not (np.isfinite(p) and p > 1.0):
            raise ParameterError(f"boundary smoothing needs p > 1, got {p}")
        self.model, self.p = model, p
        self.scale_invariant = bool(scale_invariant)
        self.name = (
            f"boundary smoothing (p={p:g})"
            if self.scale_invariant
            else "boundary smoothing (Laplacian)"
        )
        mesh = model.domain.mesh
        self.comm = mesh.comm
        self.dim = mesh.geometry.dim
        fdim = mesh.topology.dim - 1
        mesh.topology.create_connectivity(fdim, fdim + 1)
        facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
        nodes = dolfinx.mesh.entities_to_geometry(mesh, fdim, facets)[:, : fdim + 1]
        ids = mesh.geometry.input_global_indices
        corners = ids[nodes]  # (num facets, fdim + 1) input vertex indices
        pairs = [corners[:, [a, b]] for a in range(fdim + 1) for b in range(a + 1, fdim + 1)]
        local_edges = np.sort(np.concatenate(pairs, axis=0), axis=1).astype(np.int64)
        edges = np.unique(_allgather_concat(self.comm, local_edges.reshape(-1, 2)), axis=0)
        excluded = [model.domain.facets_of(t) for t in exclude_facets]
        if excluded:
            ex_nodes = dolfinx.mesh.entities_to_geometry(mesh, fdim, np.concatenate(excluded))
            ex = np.unique(_allgather_concat(self.comm, ids[ex_nodes.ravel()].astype(np.int64)))
            edges = edges[~np.isin(edges, ex).any(axis=1)]
        self.vertices = np.unique(edges)  # B, sorted input indices
        compact = np.searchsorted(self.vertices, edges)
        # directed edges (i, j) and (j, i): s_i sums over both directions
        self._src = np.concatenate([compact[:, 0], compact[:, 1]])
        self._dst = np.concatenate([compact[:, 1], compact[:, 0]])
        # owned geometry nodes of B and their rows in the gathered position array
        owned = mesh.geometry.index_map().size_local
        node_ids = ids[:owned].astype(np.int64)
        in_b = np.isin(node_ids, self.vertices)
        self._owned_nodes = np.flatnonzero(in_b)
        self._owned_rows = np.searchsorted(self.vertices, node_ids[in_b])
        # owned dofs of the shape space -> rows of B (or -1)
        S = model.shape_space
        s_owned = S.dofmap.index_map.size_local
        s_to_node = np.empty(s_owned + S.dofmap.index_map.num_ghosts, dtype=np.int64)
        s_to_node[S.dofmap.list.ravel()] = mesh.geometry.dofmaps[0].ravel()
        dof_ids = ids[s_to_node[:s_owned]].astype(np.int64)
        rows = np.searchsorted(self.vertices, dof_ids)
        rows = np.minimum(rows, len(self.vertices) - 1)
        self._dof_rows = np.where(self.vertices[rows] == dof_ids, rows, -1)

    def positions(self) -> np.ndarray:
        """Current rest positions of B (rows in the order of ``self.vertices``, all ranks)."""
        x = self.model.domain.mesh.geometry.x[self._owned_nodes, : self.dim]
        rows = _allgather_concat(self.comm, self._owned_rows)
        values = _allgather_concat(self.comm, x)
        out = np.empty((len(self.vertices), self.dim))
        out[rows] = values
        return out

    def _sums(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        d = X[self._src] - X[self._dst]
        length = np.linalg.norm(d, axis=1)
        n = len(X)
        S = np.column_stack(
            [np.bincount(self._src, weights=d[:, k], minlength=n) for k in range(self.dim)]
        )
        L = np.bincount(self._src, weights=length, minlength=n)
        return d, length, S, L

    def _laplacian(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """r_i = v_i - mean_j v_j over the boundary neighbours, and the degrees."""
        n = len(X)
        degree = np.bincount(self._src, minlength=n).astype(float)
        neighbours = np.column_stack(
            [np.bincount(self._src, weights=X[self._dst, k], minlength=n) for k in range(self.dim)]
        )
        return X - neighbours / degree[:, None], degree

    @override
    def evaluate(self, model: "Model") -> float:
        _check_model(self, model)
        if not self.scale_invariant:
            r, _ = self._laplacian(self.positions())
            return float(np.sum(r * r))
        _, _, S, L = self._sums(self.positions())
        s = S / L[:, None]
        return float(np.sum(np.linalg.norm(s, axis=1) ** self.p))

    def vertex_gradient(self) -> np.ndarray:
        """dJ/dv for the vertices of B (rows as ``self.vertices``; appendix F)."""
        X = self.positions()
        if not self.scale_invariant:
            r, degree = self._laplacian(X)
            w = 2.0 * r / degree[:, None]  # dJ/dv_k = 2 r_k - sum_{i ~ k} 2 r_i / deg_i
            return 2.0 * r - np.column_stack(
                [
                    np.bincount(self._dst, weights=w[self._src, k], minlength=len(X))
                    for k in range(self.dim)
                ]
            )
        d, length, S, L = self._sums(X)
        s = S / L[:, None]
        norm = np.linalg.norm(s, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            factor = np.where(norm > 0, self.p * norm ** (self.p - 2.0), 0.0)
        g = factor[:, None] * s  # dJ/ds_i
        dS = g / L[:, None]  # dJ/dS_i
        dL = -np.sum(g * s, axis=1) / L  # dJ/dL_i
        src = self._src
        dd = dS[src] + dL[src, None] * d / length[:, None]  # dJ/d(v_i - v_j) per directed edge
        n = len(X)
        return np.column_stack(
            [
                np.bincount(src, weights=dd[:, k], minlength=n)
                - np.bincount(self._dst, weights=dd[:, k], minlength=n)
                for k in range(self.dim)
            ]
        )

    @override
    def gradient(self, model: "Model") -> dict[str, np.ndarray]:
        _check_model(self, model)
        G = self.vertex_gradient()
        rows = self._dof_rows
        out = np.zeros((len(rows), self.dim))
        out[rows >= 0] = G[rows[rows >= 0]]
        return {"shape": out.ravel()}


class MaterialSmoothing(Regulariser):
    """Smoothing of cellwise (DG0) parameter fields over adjacent cells (paper eq. 38).

    J = sum_c sum_t sum_{t' in Adj(t)} (1 - c_t' / c_t)^2 over the named coefficients c, with
    Adj(t) the cells sharing a facet with t (every adjacent pair counts in both orders).

    Args:
        model: The Model.
        coefficients: Names of scalar DG0 coefficients (default: the elastic parameters of the
            model, ("E", "nu") or ("lmbda", "mu")).
    """

    def __init__(self, model: "Model", coefficients: Sequence[str] | None = None) -> None:
        self.model = model
        names = tuple(model.parametrisation if coefficients is None else coefficients)
        if not names:
            raise ParameterError("material smoothing needs at least one coefficient")
        for name in names:
            if name not in model.coefficients:
                raise ParameterError(
                    f"the model has no coefficient {name!r}; it has {sorted(model.coefficients)}"
                )
            V = model.coefficients[name].function_space
            if V.element.basix_element.degree != 0 or V.dofmap.index_map_bs != 1:
                raise ParameterError(f"material smoothing of {name!r} needs a scalar DG0 field")
        self.names = names
        self.name = f"material smoothing ({', '.join(names)})"
        mesh = model.domain.mesh
        self.comm = mesh.comm
        self.layouts = {n: CanonicalLayout(model.coefficients[n].function_space) for n in names}
        self.pairs = self._adjacent_pairs(mesh)

    def _adjacent_pairs(self, mesh: dolfinx.mesh.Mesh) -> np.ndarray:
        """Pairs (t, t') of input cell indices sharing a facet (each pair once, sorted)."""
        tdim = mesh.topology.dim
        owned = mesh.topology.index_map(tdim).size_local
        cells = np.arange(owned, dtype=np.int32)
        verts = mesh.geometry.input_global_indices[mesh.geometry.dofmaps[0][cells, : tdim + 1]]
        orig = mesh.topology.original_cell_index[:owned].astype(np.int64)
        verts = _allgather_concat(self.comm, verts.astype(np.int64))
        orig = _allgather_concat(self.comm, orig)
        nv = tdim + 1
        keys = np.concatenate(
            [np.sort(np.delete(verts, k, axis=1), axis=1) for k in range(nv)], axis=0
        )
        cell_of = np.tile(orig, nv)
        order = np.lexsort(keys.T[::-1])
        keys, cell_of = keys[order], cell_of[order]
        same = np.all(keys[1:] == keys[:-1], axis=1)
        first = np.flatnonzero(same)
        pairs = np.sort(np.column_stack([cell_of[first], cell_of[first + 1]]), axis=1)
        return pairs[np.lexsort(pairs.T[::-1])]

    def _values(self, name: str) -> np.ndarray:
        c = self.layouts[name].gather(self.model.coefficients[name].x.array)
        if np.any(c == 0) or not np.all(np.isfinite(c)):
            raise ObjectiveError(f"material smoothing of {name!r} needs finite nonzero values")
        return c

    @override
    def evaluate(self, model: "Model") -> float:
        _check_model(self, model)
        a, b = self.pairs[:, 0], self.pairs[:, 1]
        total = 0.0
        for name in self.names:
            c = self._values(name)
            total += float(np.sum((1 - c[b] / c[a]) ** 2 + (1 - c[a] / c[b]) ** 2))
        return total

    @override
    def gradient(self, model: "Model") -> dict[str, np.ndarray]:
        _check_model(self, model)
        a, b = self.pairs[:, 0], self.pairs[:, 1]
        out = {}
        for name in self.names:
            c = self._values(name)
            ca, cb = c[a], c[b]
            # d/dc_a and d/dc_b of (1 - c_b/c_a)^2 + (1 - c_a/c_b)^2 (appendix F)
            da = 2 * (1 - cb / ca) * cb / ca**2 - 2 * (1 - ca / cb) / cb
            db = -2 * (1 - cb / ca) / ca + 2 * (1 - ca / cb) * ca / cb**2
            n = len(c)
            G = np.bincount(a, weights=da, minlength=n) + np.bincount(b, weights=db, minlength=n)
            out[name] = G[self.layouts[name].positions]
        return out
