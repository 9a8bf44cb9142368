"""Mesh motion: interior vertices follow the design boundary (paper sec. 5, interior smoothing).

The design parameters q are displacements of selected vertices (usually the boundary minus
clamped parts). Every other vertex moves by a linear extension built once on the reference mesh:
with K the stiffness of a P1 vector field (linear elasticity or a component-wise Laplacian, its
coefficient scaled by (mean cell volume / cell volume)^stiffening so small cells stay stiff),
C the constrained vertices (designed D and fixed F) and I the free ones,

    d_D = q,   d_F = 0,   K_II d_I = -K_IC d_C,

so X = X0 + P q with P = [I; 0; -K_II^{-1} K_ID]. The adjoint P^T g = g_D - K_DI K_II^{-T} g_I
is one solve with the transposed (factorised) operator, so shape gradients include the
dependence of every interior vertex exactly.

:class:`MeshMotion` is that P as a ``scipy.sparse.linalg.LinearOperator`` over the canonical
vertex order of :class:`~diffsolids.controls.ShapeControl`; :class:`MeshMotionControl` is the
shape control using it. :meth:`MeshMotion.riesz_map` gives an H1-type inner product of the
design space (the Schur complement of K + alpha M onto the design vertices) usable as the
initial inverse Hessian of L-BFGS.
"""

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, override

import dolfinx.fem.petsc
import numpy as np
import numpy.typing as npt
import scipy.sparse.linalg as spla
import ufl
from dolfinx import fem
from mpi4py import MPI
from petsc4py import PETSc

from diffsolids.controls.base import ControlError
from diffsolids.controls.shape import ShapeControl, boundary_vertices
from diffsolids.mesh import Domain, signed_cell_volumes
from diffsolids.mesh.ordering import CanonicalLayout
from diffsolids.parallel import collective_comm
from diffsolids.solvers.factor_store import lu_solver
from diffsolids.solvers.forms import compile_form

if TYPE_CHECKING:
    from diffsolids.model import Model
    from diffsolids.reduced_functional import ReducedFunctional

__all__ = ["MeshMotion", "MeshMotionControl", "RieszMap", "ShapeInnerProduct"]

_EXTENSIONS = ("elasticity", "harmonic")


class MeshMotion(spla.LinearOperator):
    """Linear map from design-vertex displacements to displacements of all vertices.

    Built on the mesh geometry at construction (the reference shape; rebuild after a remesh).
    ``P @ q`` and ``P.T @ g`` are collective over the mesh communicator; both take and return
    vectors identical on every rank in the canonical order of ShapeControl (vertex input order,
    components within a vertex).

    Args:
        domain: The Domain (its current geometry is the reference).
        vertices: Design vertices: "boundary" (all boundary vertices except those of
            ``exclude_facets``), an array of canonical vertex indices, or a marker
            ``x -> bool`` on reference positions (evaluated on every rank's local vertices).
        exclude_facets: With "boundary": facet tags whose vertices stay fixed.
        extension: "elasticity" (linear elasticity with Poisson ratio ``poisson_ratio``) or
            "harmonic" (Laplacian per component).
        stiffening: Exponent chi of the cell weight (mean volume / volume)^chi (0: uniform).
        poisson_ratio: Poisson ratio of the elasticity extension.

    Boundary vertices that are not design vertices stay fixed; all other vertices are extended.

    Raises:
        ControlError: Unknown extension, no design vertices, or out-of-range indices.
    """

    def __init__(
        self,
        domain: Domain,
        vertices: str | npt.ArrayLike | Callable[[np.ndarray], np.ndarray] = "boundary",
        exclude_facets: Sequence[int | str] = (),
        extension: str = "elasticity",
        stiffening: float = 1.0,
        poisson_ratio: float = 0.3,
    ) -> None:
        if extension not in _EXTENSIONS:
            raise ControlError(f"unknown mesh extension {extension!r}; choose from {_EXTENSIONS}")
        if not -1.0 < poisson_ratio < 0.5:
            raise ControlError(f"extension Poisson ratio {poisson_ratio} outside (-1, 0.5)")
        self.domain = domain
        self.extension = extension
        self.poisson_ratio = float(poisson_ratio)
        mesh = domain.mesh
        self.comm = mesh.comm
        self.dim = mesh.geometry.dim
        self.W = fem.functionspace(mesh, ("Lagrange", 1, (self.dim,)))
        self.layout = CanonicalLayout(self.W)
        self.num_vertices = self.layout.num_global
        self.design = self._design_vertices(vertices, exclude_facets)
        if self.design.size == 0:
            raise ControlError("mesh motion without design vertices")
        fixed = np.setdiff1d(boundary_vertices(domain), self.design)
        super().__init__(float, (self.num_vertices * self.dim, self.design.size * self.dim))

        # local (owned + ghost) nodes of W and their canonical indices
        imap = self.W.dofmap.index_map
        self._owned = imap.size_local
        canon = np.empty(imap.size_local + imap.num_ghosts, dtype=np.int64)
        canon[self.W.dofmap.list.ravel()] = mesh.geometry.input_global_indices[
            mesh.geometry.dofmaps[0].ravel()
        ]
        k = np.minimum(np.searchsorted(self.design, canon), self.design.size - 1)
        is_design = self.design[k] == canon
        self._design_nodes = np.flatnonzero(is_design).astype(np.int32)  # local, with ghosts
        self._design_slot = k[is_design]  # position in self.design
        fixed_nodes = np.flatnonzero(np.isin(canon, fixed)).astype(np.int32)
        owned_design = self._design_nodes < self._owned
        self._owned_design_nodes = self._design_nodes[owned_design]
        self._owned_design_slot = self._design_slot[owned_design]

        self.cell_weight = self._cell_weight(stiffening)
        self._a = compile_form(self.stiffness_form(self.cell_weight))
        self.K = dolfinx.fem.petsc.assemble_matrix(self._a)
        self.K.assemble()
        constrained = np.union1d(self._design_nodes, fixed_nodes).astype(np.int32)
        bc = fem.dirichletbc(fem.Function(self.W), constrained)
        self.A = dolfinx.fem.petsc.assemble_matrix(self._a, bcs=[bc])
        self.A.assemble()
        self._ksp = lu_solver(self.comm, self.A)
        bs = self.dim
        owned_c = constrained[constrained < self._owned]
        self._owned_constrained_dofs = (owned_c[:, None] * bs + np.arange(bs)).ravel()
        self.fixed_nodes = fixed_nodes
        self.reference = mesh.geometry.x.copy()
        self._b, self._x, self._r, self._w = (
            dolfinx.fem.petsc.create_vector(self.W) for _ in range(4)
        )

    # -- construction helpers ------------------------------------------------------------------
    def _design_vertices(
        self,
        vertices: str | npt.ArrayLike | Callable[[np.ndarray], np.ndarray],
        exclude: Sequence[int | str],
    ) -> np.ndarray:
        mesh = self.domain.mesh
        if isinstance(vertices, str):
            if vertices != "boundary":
                raise ControlError(f"unknown design vertex selection {vertices!r}")
            return boundary_vertices(self.domain, exclude)
        if callable(vertices):
            x = mesh.geometry.x[:, : self.dim]
            ids = mesh.geometry.input_global_indices[np.asarray(vertices(x.T), dtype=bool)]
            return np.unique(np.concatenate(collective_comm(self.comm).allgather(ids))).astype(
                np.int64
            )
        ids = np.unique(np.asarray(vertices, dtype=np.int64))
        if ids.size and (ids.min() < 0 or ids.max() >= self.num_vertices):
            raise ControlError(f"vertex indices out of range 0..{self.num_vertices - 1}")
        return ids

    def _cell_weight(self, chi: float) -> fem.Function:
        mesh = self.domain.mesh
        Q = fem.functionspace(mesh, ("DG", 0))
        weight = fem.Function(Q, name="extension_weight")
        vol = np.abs(signed_cell_volumes(mesh))
        num_owned = mesh.topology.index_map(mesh.topology.dim).size_local
        total = collective_comm(self.comm).allreduce(
            np.array([vol[:num_owned].sum(), num_owned]), op=MPI.SUM
        )
        mean = total[0] / total[1]
        weight.x.array[Q.dofmap.list[:, 0]] = (mean / vol) ** float(chi)
        return weight

    def stiffness_form(self, weight: fem.Function | fem.Constant, mass: float = 0.0) -> ufl.Form:
        """The extension's bilinear form on ``W`` with a cell weight (plus a mass term)."""
        u, v = ufl.TrialFunction(self.W), ufl.TestFunction(self.W)
        if self.extension == "harmonic":
            a = weight * ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx
        else:
            nu = self.poisson_ratio
            mu = 1.0 / (2.0 * (1.0 + nu))
            lmbda = nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
            eps = lambda w: ufl.sym(ufl.grad(w))  # noqa: E731
            sigma = 2.0 * mu * eps(u) + lmbda * ufl.tr(eps(u)) * ufl.Identity(self.dim)
            a = weight * ufl.inner(sigma, eps(v)) * ufl.dx
        if mass:
            a = a + mass * ufl.inner(u, v) * ufl.dx
        return a

    # -- the linear map ------------------------------------------------------------------------
    @property
    def num_design_vertices(self) -> int:
        """Number of design vertices (parameters = this times dim)."""
        return int(self.design.size)

    def _owned_array(self, vec: PETSc.Vec) -> np.ndarray:
        return vec.getArray(readonly=True)[: self._owned * self.dim]

    @override
    def _matvec(self, q: np.ndarray) -> np.ndarray:
        # b = E_C w_C - R_I K E_C w_C with the reference K (never the moved mesh)
        q = np.asarray(q, dtype=float).reshape(-1, self.dim)
        w, b = self._w, self._b
        w_owned = w.getArray()
        w_owned[:] = 0.0
        self.scatter_design(q, w_owned)
        self.K.mult(w, b)
        b_owned = b.getArray()
        b_owned *= -1.0
        b_owned[self._owned_constrained_dofs] = w_owned[self._owned_constrained_dofs]
        self._ksp.solve(b, self._x)
        return self.layout.gather(self._owned_array(self._x))

    @override
    def _rmatvec(self, g: np.ndarray) -> np.ndarray:
        # P^T g = E_C^T (y - K^T R_I y), y = A^{-T} g (A: K with constrained rows/columns
        # replaced by the identity, R_I: zero the constrained entries)
        g = np.asarray(g, dtype=float).reshape(-1, self.dim)
        b, y = self._b, self._x
        b.getArray()[: self._owned * self.dim] = g[self.layout.positions].ravel()
        self._ksp.solveTranspose(b, y)
        y_owned = self._owned_array(y).copy()
        y.getArray()[self._owned_constrained_dofs] = 0.0
        self.K.multTranspose(y, self._r)
        dq_local = (y_owned - self._owned_array(self._r)).reshape(-1, self.dim)
        return self.gather_design(dq_local)

    def scatter_design(self, q: np.ndarray, owned: np.ndarray) -> None:
        """Write design values q (num_design_vertices, dim) into their owned nodes of ``owned``.

        ``owned``: an array over the owned nodes of ``W`` (flat or (nodes, dim)).
        """
        owned.reshape(-1, self.dim)[self._owned_design_nodes] = q[self._owned_design_slot]

    def gather_design(self, owned: np.ndarray) -> np.ndarray:
        """The design nodes' values of an owned-node array of ``W``, flat (collective)."""
        out = np.zeros((self.design.size, self.dim))
        out[self._owned_design_slot] = owned.reshape(-1, self.dim)[self._owned_design_nodes]
        return collective_comm(self.comm).allreduce(out, op=MPI.SUM).ravel()

    def riesz_map(self, mass_weight: float | None = None, scale: float = 1.0) -> "RieszMap":
        """An SPD inner product of the design space (see :class:`RieszMap`)."""
        return RieszMap(self, mass_weight, scale)


class RieszMap:
    """``riesz(g) = A^{-1} g``: shape gradients represented in an H1-type inner product.

    A is the Schur complement, onto the design vertices, of R = K0 + alpha M (K0 the
    extension operator of the motion without cell stiffening, M the P1 mass matrix, fixed
    vertices clamped): for design displacements q,

        q^T A q = min over extensions d with d_D = q, d_F = 0 of d^T R d,

    i.e. the elastic (or Dirichlet) energy plus alpha times the L2 norm of the smoothest
    extension into the body: a discrete H^(1/2) trace norm of the boundary displacement. A is
    symmetric positive definite (a Schur complement of an SPD matrix; alpha > 0 also without
    fixed vertices), a discretisation of one continuous operator (mesh independent), and
    A^{-1} g costs one solve with R (Neumann data g on the design vertices):
    [R^{-1} E_D g]_D = A^{-1} g.

    Use ``-riesz(g)`` as a smoothed descent direction, or the map as the initial inverse
    Hessian of L-BFGS.

    Args:
        motion: The MeshMotion whose design vertices and extension type define the space.
        mass_weight: alpha (default 1 / L^2, L the bounding-box diagonal).
        scale: Factor multiplying A^{-1}.
    """

    def __init__(
        self, motion: MeshMotion, mass_weight: float | None = None, scale: float = 1.0
    ) -> None:
        self.motion = motion
        domain = motion.domain
        geometry = domain.mesh.geometry.x
        current = geometry.copy()
        geometry[:] = motion.reference  # build on the reference shape of the motion
        try:
            if mass_weight is None:
                mass_weight = 1.0 / domain.characteristic_length() ** 2
            if mass_weight < 0 or scale <= 0:
                raise ControlError("the Riesz map needs mass_weight >= 0 and scale > 0")
            self.mass_weight, self.scale = float(mass_weight), float(scale)
            one = fem.Constant(domain.mesh, PETSc.ScalarType(1.0))
            self._a = compile_form(motion.stiffness_form(one, self.mass_weight))
            bc = fem.dirichletbc(fem.Function(motion.W), motion.fixed_nodes.astype(np.int32))
            self.R = dolfinx.fem.petsc.assemble_matrix(self._a, bcs=[bc])
        finally:
            geometry[:] = current
        self.R.assemble()
        self._ksp = lu_solver(motion.comm, self.R)
        self._b = dolfinx.fem.petsc.create_vector(motion.W)
        self._x = dolfinx.fem.petsc.create_vector(motion.W)

    @property
    def size(self) -> int:
        """Number of design parameters."""
        return self.motion.shape[1]

    def __call__(self, g: np.ndarray) -> np.ndarray:
        """A^{-1} g for a gradient g over the design parameters (collective)."""
        m = self.motion
        g = np.asarray(g, dtype=float)
        if g.shape != (self.size,):
            raise ControlError(f"Riesz map expects a vector of length {self.size}")
        arr = self._b.getArray()
        arr[:] = 0.0
        m.scatter_design(g.reshape(-1, m.dim), arr)
        self._ksp.solve(self._b, self._x)
        return self.scale * m.gather_design(self._x.getArray(readonly=True))


class MeshMotionControl(ShapeControl):
    """Shape control whose parameters move design vertices and extend into the body.

    ``MeshMotionControl(model, "boundary", exclude_facets=[clamp], extension="elasticity")``
    has one displacement per design vertex and component (canonical order: vertex input index,
    then component); all other vertices follow the extension of :class:`MeshMotion` (built on
    the model's current geometry, which becomes the reference X0).

    Args:
        model: The Model.
        vertices: Design vertices (see MeshMotion).
        exclude_facets: Facet tags whose vertices stay fixed.
        extension: "elasticity" or "harmonic".
        stiffening: Cell-volume stiffening exponent.
        poisson_ratio: Poisson ratio of the elasticity extension.
        refuse_intersections: Refuse rest shapes with a self-intersecting boundary (see
            :class:`~diffsolids.controls.ShapeControl`).
    """

    name = "shape[mesh motion]"

    def __init__(
        self,
        model: "Model",
        vertices: str | npt.ArrayLike | Callable[[np.ndarray], np.ndarray] = "boundary",
        exclude_facets: Sequence[int | str] = (),
        extension: str = "elasticity",
        stiffening: float = 1.0,
        poisson_ratio: float = 0.3,
        refuse_intersections: bool = False,
    ) -> None:
        self.motion = MeshMotion(
            model.domain, vertices, exclude_facets, extension, stiffening, poisson_ratio
        )
        super().__init__(model, linear_map=self.motion, refuse_intersections=refuse_intersections)

    def riesz_map(self, mass_weight: float | None = None, scale: float = 1.0) -> RieszMap:
        """The design space's H1-type inner product (see :class:`RieszMap`)."""
        return self.motion.riesz_map(mass_weight, scale)


class ShapeInnerProduct:
    """Initial inverse Hessian of L-BFGS for a ReducedFunctional with mesh-motion controls.

    Calling it, ``inner_product(g)``, applies the :class:`RieszMap` of every MeshMotionControl
    to its block of the gradient and ``other_scale`` times the identity to all other blocks;
    :meth:`rebuild` makes the same inner product for the functional built after a remesh (the
    optimiser calls it).

    Args:
        rf: The ReducedFunctional.
        mass_weight: alpha of the Riesz maps (default 1 / L^2).
        scale: Factor of the shape blocks.
        other_scale: Factor of the identity on the other blocks.

    Raises:
        ControlError: The functional has no MeshMotionControl.
    """

    def __init__(
        self,
        rf: "ReducedFunctional",
        mass_weight: float | None = None,
        scale: float = 1.0,
        other_scale: float = 1.0,
    ) -> None:
        self.options = {"mass_weight": mass_weight, "scale": scale, "other_scale": other_scale}
        controls = rf.controls
        self.offsets = controls.offsets
        self.maps = {
            k: c.riesz_map(mass_weight, scale)
            for k, c in enumerate(controls.controls)
            if isinstance(c, MeshMotionControl)
        }
        if not self.maps:
            raise ControlError("ShapeInnerProduct needs a MeshMotionControl among the controls")
        self.other_scale = float(other_scale)

    def __call__(self, g: np.ndarray) -> np.ndarray:
        """M^{-1} g block by block (collective)."""
        g = np.asarray(g, dtype=float)
        if g.shape != (self.offsets[-1],):
            raise ControlError(f"inner product expects a vector of length {self.offsets[-1]}")
        out = self.other_scale * g
        for k, riesz in self.maps.items():
            a, b = self.offsets[k], self.offsets[k + 1]
            out[a:b] = riesz(g[a:b])
        return out

    def rebuild(self, rf: "ReducedFunctional") -> "ShapeInnerProduct":
        """The same inner product for another functional (e.g. after a remesh)."""
        return ShapeInnerProduct(rf, **self.options)
