"""Derivative kernels of the contact term against central finite differences of add_residual.

Every kernel is checked in a random direction and along the vector it returns. The scenes avoid
symmetric placements (a vertex exactly above an edge switches IPC distance types, where the
lagged friction is only C^0); in 3D the upper box is turned by 1 degree so that its bottom edges
are near-parallel to the top edges of the lower box: mollified edge-edge pairs are active, where
ipctk 1.6.1's shape derivative needs our correction.
"""

import dolfinx.fem.petsc as fem_petsc
import numpy as np
import pytest
import ufl
from contact_checks import stacked_boxes
from dolfinx import fem
from mpi4py import MPI

import diffsolids as ds
from diffsolids.contact import ContactTerm
from diffsolids.contact.derivatives.barrier_shape import _mollified_pairs
from diffsolids.contact.geometry.surface import _vertex_blocks
from diffsolids.mesh.scene import combine_meshes
from diffsolids.simulation import Trajectory
from diffsolids.solvers.sparsity import matrix_with_pattern
from diffsolids.states import Phase, StepContext

H = 1e-7
TOL = 1e-6
GAP = 0.02


def _scene(
    dim: int,
    degree: int,
    order: int,
    eps_v: float = 100.0,
    comm=MPI.COMM_WORLD,
    formulation: str = "ipc",
):
    dom = combine_meshes(comm, stacked_boxes(dim, GAP, [2, 2]))
    model = ds.Model(dom, ds.NeoHookean(E=1e4, nu=0.3, density=10.0), degree=degree)
    model.add_dirichlet(lambda x: x[dim - 1] < 1e-9, 0.0)
    contact = ContactTerm(
        model, dhat=0.05, stiffness=1e3, friction=0.4, eps_v=eps_v, formulation=formulation
    )
    V = model.V
    X = V.tabulate_dof_coordinates()[:, :dim]
    upper_nodes = X[:, dim - 1] > 0.3 + 1e-9

    def field(amp: float, shift: float, sink: float = 0.0) -> np.ndarray:
        f = fem.Function(V)
        a = f.x.array.reshape(-1, dim)
        a[upper_nodes] = amp * np.sin(3 * X[upper_nodes] + shift)
        a[upper_nodes, 0] += 0.01 * shift
        a[upper_nodes, dim - 1] -= sink
        return f.x.array.copy()

    traj = Trajectory(
        times=[0.0] * order,
        u=[field(0.002, k) for k in range(order)],
        v=[np.zeros(len(X) * dim)] * order,
    )
    u = fem.Function(V)
    u.x.array[:] = field(0.003, 7.0, sink=0.01)
    integ = ds.BDF(order, 0.01, 10)
    coeffs = integ.coefficients(order)
    contact.begin_step(StepContext(order, coeffs, traj, integ, Phase.FORWARD))
    return model, contact, traj, u, coeffs


def _context(i, traj, coeffs):
    """Step i of the kernels' scene, set up as the forward does (u^i not known yet)."""
    return StepContext(i, coeffs, traj, ds.BDF(len(coeffs.alpha), coeffs.dt, 10), Phase.FORWARD)


class _Checker:
    def __init__(self, model, contact, u):
        self.model, self.contact, self.u = model, contact, u
        V = model.V
        self.comm = V.mesh.comm
        self.n_own = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        self.b = fem_petsc.create_vector(V)
        self.free = np.ones(len(u.x.array), dtype=bool)
        self.free[model.dirichlet_dofs()] = False
        self.rng = np.random.default_rng(3)

    def residual(self, values=None) -> np.ndarray:
        w = fem.Function(self.model.V)
        w.x.array[:] = self.u.x.array if values is None else values
        self.b.set(0.0)
        self.contact.add_residual(w, self.b)
        return self.b.array_r.copy()

    def dot(self, a, b) -> float:
        return self.comm.allreduce(float(a[: self.n_own] @ b[: self.n_own]), op=MPI.SUM)

    def ghosted(self, owned: np.ndarray) -> np.ndarray:
        """A ghosted V array from owned values, scaled to unit max-norm."""
        f = fem.Function(self.model.V)
        f.x.array[: self.n_own] = owned[: self.n_own]
        f.x.scatter_forward()
        a = f.x.array
        return a / self.comm.allreduce(np.abs(a).max(initial=0.0), op=MPI.MAX)

    def random(self) -> np.ndarray:
        p = self.rng.standard_normal(len(self.u.x.array)) * self.free
        return self.ghosted(p[: self.n_own])

    @staticmethod
    def central(f) -> float:
        return (f(H) - f(-H)) / (2 * H)

    def assert_close(self, fd, exact, what):
        err = abs(fd - exact) / abs(exact)
        assert abs(exact) > 0, f"{what}: zero derivative"
        assert err <= TOL, f"{what}: finite difference {fd:.12e} vs {exact:.12e} (rel {err:.2e})"


# sliding speeds are about 9: eps_v = 100 tests the smoothed (sticking) branch of the friction,
# eps_v = 0.5 the sliding branch (3D only: in 2D its velocity Hessian vanishes identically)
CASES = [
    (2, 1, 1, 100.0, "ipc"),
    (2, 2, 3, 100.0, "ipc"),
    (2, 3, 2, 100.0, "ipc"),
    (3, 1, 2, 100.0, "ipc"),
    (3, 2, 1, 0.5, "ipc"),
    (3, 1, 3, 0.5, "ipc"),
    # merged and negative weights (read), the others' weight gradients in bulk
    (2, 1, 2, 100.0, "convergent"),
    (3, 1, 2, 0.5, "convergent"),
]


def _contact_pattern(model, contact, u):
    """(a V x V mass-like matrix, the Dirichlet dofs, the keys row*N+col of the contact pattern)."""
    V = model.V
    like = fem_petsc.create_matrix(
        fem.form(ufl.inner(ufl.TrialFunction(V), ufl.TestFunction(V)) * ufl.dx)
    )
    bc = model.dirichlet_dofs()
    rows, cols = contact.matrix_pattern(u, bc)
    N = like.getSize()[1]
    return like, bc, np.unique(np.asarray(rows, np.int64) * N + cols)


@pytest.mark.parametrize(("dim", "degree", "order", "eps_v", "formulation"), CASES)
def test_contact_derivative_kernels(dim, degree, order, eps_v, formulation):
    model, contact, traj, u, coeffs = _scene(dim, degree, order, eps_v, formulation=formulation)
    chk = _Checker(model, contact, u)
    comm = chk.comm
    ev = contact._evaluate(u)
    assert len(ev.collisions) > 0 and len(ev.friction) > 0
    if dim == 3:  # mollified edge-edge pairs present: the ipctk shape-derivative bug is in play
        rest = contact.surface.rest_positions
        assert any(True for _ in _mollified_pairs(ev.collisions, contact.surface.mesh, rest, ev.x))

    # exact Hessian (adjoint Jacobian) against the residual
    like, bc, keys = _contact_pattern(model, contact, u)
    A = matrix_with_pattern(like, keys)
    A.zeroEntries()
    contact.add_adjoint_jacobian(u, A, bc)
    A.assemble()
    r0 = chk.residual()
    lam = chk.random()
    for p in (chk.random(), chk.ghosted(r0 * chk.free[: chk.n_own])):
        pv = A.createVecRight()
        pv.array_w[:] = p[: chk.n_own]
        Ap = A.createVecLeft()
        A.mult(pv, Ap)
        fd = chk.central(lambda t, p=p: chk.dot(lam, chk.residual(u.x.array + t * p)))
        chk.assert_close(fd, chk.dot(lam, Ap.array_r), "Hessian")

    # history: friction through the lagged state (j = 1) and the BDF velocity (all j)
    hist = contact.adjoint_history(u, lam)
    assert sorted(hist) == list(range(1, order + 1))
    for j, g in hist.items():
        for p in (chk.random(), chk.ghosted(g)):

            def f(t, j=j, p=p):
                moved = [a.copy() for a in traj.u]
                moved[order - j] = moved[order - j] + t * p
                contact.begin_step(_context(order, Trajectory(traj.times, moved, traj.v), coeffs))
                return chk.dot(lam, chk.residual())

            chk.assert_close(chk.central(f), chk.dot(g, p), f"history j={j}")
    contact.begin_step(_context(order, traj, coeffs))

    # friction coefficient per pair of bodies (force linear in mu)
    gmu = contact.adjoint_friction(u, lam)
    mu0 = contact.friction_coefficients
    for k, pair in enumerate(contact.friction_pairs):

        def f(t, k=k):
            mu = mu0.copy()
            mu[k] += t * 1e3  # linear in mu: a large step is exact
            contact.friction_coefficients = mu
            return chk.dot(lam, chk.residual()) / 1e3

        if pair == (1, 2):
            chk.assert_close(chk.central(f), gmu[k], f"friction {pair}")
        else:
            assert gmu[k] == 0.0 and abs(chk.central(f)) < 1e-12
    contact.friction_coefficients = mu0

    # shape: rest positions of the mesh vertices (P1 space)
    gX = contact.adjoint_shape(u, lam)
    S = model.shape_space
    node_blocks = _vertex_blocks(model.domain.mesh, S)
    nS = S.dofmap.index_map.size_local * dim
    x0 = model.domain.mesh.geometry.x.copy()
    rng = np.random.default_rng(5)
    for theta_owned in (rng.standard_normal(nS), gX[:nS]):
        th = fem.Function(S)
        th.x.array[:nS] = theta_owned
        th.x.scatter_forward()
        th.x.array[:] /= comm.allreduce(np.abs(th.x.array).max(), op=MPI.MAX)

        def f(t, th=th):
            model.domain.mesh.geometry.x[:, :dim] = (
                x0[:, :dim] + t * th.x.array.reshape(-1, dim)[node_blocks]
            )
            contact.begin_step(_context(order, traj, coeffs))
            return chk.dot(lam, chk.residual())

        exact = comm.allreduce(float(gX[:nS] @ th.x.array[:nS]), op=MPI.SUM)
        chk.assert_close(chk.central(f), exact, "shape")
        model.domain.mesh.geometry.x[:] = x0


@pytest.mark.parametrize("dim", [2, 3])
def test_friction_coefficient_kernel_without_friction(dim):
    """The coefficients' gradient where every coefficient is 0 (no friction in the forward)
    against a one-sided difference (the residual is linear in mu, so exact to round-off)."""
    model, contact, _, u, _ = _scene(dim, 1, 1, 0.5, comm=MPI.COMM_SELF)
    chk = _Checker(model, contact, u)
    lam = chk.random()
    mu0 = contact.friction_coefficients
    contact.friction_coefficients = np.zeros_like(mu0)
    r0 = chk.dot(lam, chk.residual())
    gmu = contact.adjoint_friction(u, lam)
    for k, pair in enumerate(contact.friction_pairs):
        mu = np.zeros_like(mu0)
        mu[k] = 1.0
        contact.friction_coefficients = mu
        fd = chk.dot(lam, chk.residual()) - r0
        if pair == (1, 2):
            chk.assert_close(fd, gmu[k], f"friction {pair} at mu = 0")
        else:
            assert gmu[k] == 0.0 and abs(fd) < 1e-12


def test_shape_derivative_differs_from_ipctks():
    """ipctk's own 3D shape derivative (1.6.0, 1.6.1) misses by percents at mollified pairs (the
    check can fail)."""
    import scipy.sparse as sp

    import diffsolids.contact.derivatives.step_adjoint as step_adjoint

    model, contact, _, u, _ = _scene(3, 1, 1, comm=MPI.COMM_SELF)
    lam = _Checker(model, contact, u).random()
    with_fix = contact.adjoint_shape(u, lam)
    original = step_adjoint.barrier_shape_adjoint
    step_adjoint.barrier_shape_adjoint = lambda C, mesh, x, b, k, lam, *a: (
        sp.csc_matrix(b.shape_derivative(C, mesh, x)).T @ lam
    )
    try:
        without = contact.adjoint_shape(u, lam)
    finally:
        step_adjoint.barrier_shape_adjoint = original
    rel = np.linalg.norm(with_fix - without) / np.linalg.norm(with_fix)
    assert rel > 1e-3


def test_projected_newton_matrix_is_psd_and_exact_is_not():
    """The Newton fallback adds the PSD-projected contact Hessian on the exact one's pattern."""
    model, contact, _, u, _ = _scene(3, 1, 1, comm=MPI.COMM_SELF)
    like, bc, keys = _contact_pattern(model, contact, u)
    N = like.getSize()[1]
    free = np.setdiff1d(np.arange(N), bc)
    eigenvalues = {}
    for project in (False, True):
        A = matrix_with_pattern(like, keys)  # inserting outside the pattern would raise
        A.zeroEntries()
        contact.add_jacobian(u, A, bc, project=project)
        A.assemble()
        dense = A.convert("dense").getDenseArray()[np.ix_(free, free)]
        assert np.allclose(dense, dense.T, atol=1e-9 * np.abs(dense).max())
        eigenvalues[project] = np.linalg.eigvalsh(dense)
    scale = np.abs(eigenvalues[False]).max()
    assert eigenvalues[False].min() < -1e-6 * scale
    assert eigenvalues[True].min() >= -1e-10 * scale
