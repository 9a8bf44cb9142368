"""The batched contact adjoint kernels equal the per-collision loops they replaced (1e-12).

References kept here (test-only): the per-collision loops of
``contact/derivatives/barrier_shape.py`` (``_ee_correction`` over mollified edge-edge pairs, ipctk's
per-pair mollifier helpers) and of ``ContactAdjoint.friction_rest`` (ipctk's per-collision friction
force times the weight gradient), as they were before the vectorisation. The scenes of
test_contact_kernels: 2D and 3D, friction 0.4 on the sliding (eps_v 0.5) and the smoothed (eps_v
100) branch, mollified edge-edge pairs in 3D. The finite-difference checks of the kernels stay in
test_contact_kernels and test_gradients_contact.
"""

import ipctk
import numpy as np
import pytest
import scipy.sparse as sp
from mpi4py import MPI
from test_contact_kernels import _Checker, _scene

import diffsolids.contact.derivatives.barrier_shape as contact_shape
import diffsolids.contact.derivatives.step_adjoint as step_adjoint
from diffsolids.contact.derivatives.area_weights import (
    area_gradient_adjoint,
    merged_weight_collisions,
    weight_gradient_rows,
)
from diffsolids.contact.derivatives.step_adjoint import ContactAdjoint
from diffsolids.contact.detection.collision_arrays import (
    collision_arrays,
    read_weights,
    weights_from_gradients,
)
from diffsolids.contact.energy.lagged_arrays import (
    barrier_derivatives,
    friction_collision_arrays,
)

TOL = 1e-12


# -- references: the loops as they were ------------------------------------------------------
def _reference_mollified_pairs(collisions, mesh, rest: np.ndarray, x: np.ndarray):
    E, F = mesh.edges, mesh.faces
    for c in collisions.ee_collisions:
        ids = np.asarray(c.vertex_ids(E, F))
        xr = rest[ids].ravel()
        xp = x[ids].ravel()
        eps = c.mollifier_threshold(xr)
        s = ipctk.edge_edge_cross_squarednorm(*xp.reshape(4, 3))
        if s < eps:
            yield c, ids, xr, xp, eps, s


def _reference_ee_correction(collisions, mesh, x: np.ndarray, barrier, stiffness: float):
    rest = mesh.rest_positions
    n = x.size
    rows, cols, vals = [], [], []
    kappa_b = barrier.barrier
    dhat2 = barrier.dhat**2
    for c, ids, xr, xp, eps, s in _reference_mollified_pairs(collisions, mesh, rest, x):
        d = c.compute_distance(xp)
        w = c.weight
        f = w * stiffness * kappa_b(d, dhat2)
        gf = w * stiffness * kappa_b.first_derivative(d, dhat2) * c.compute_distance_gradient(xp)
        gs = ipctk.edge_edge_cross_squarednorm_gradient(*xp.reshape(4, 3))
        geps = ipctk.edge_edge_mollifier_threshold_gradient(*xr.reshape(4, 3))
        m2 = ipctk.edge_edge_mollifier_hessian(s, eps)
        dm1 = ipctk.edge_edge_mollifier_gradient_derivative_wrt_eps_x(s, eps)
        gxm = c.mollifier_gradient_wrt_x(xr, xp)
        delta = f * (m2 * np.outer(gs, gs) + dm1 * (np.outer(gs, geps) - np.outer(geps, gs)))
        delta += np.outer(gf, gxm) - np.outer(gxm, gf)
        dofs = (ids[:, None] * 3 + np.arange(3)).ravel()
        rows.append(np.repeat(dofs, 12))
        cols.append(np.tile(dofs, 12))
        vals.append(delta.ravel())
    if not rows:
        return sp.csc_matrix((n, n))
    return sp.csc_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    )


def _reference_barrier_shape_adjoint(C, mesh, x, barrier, stiffness: float, lam: np.ndarray):
    """ipctk's barrier shape derivative, with the mollifier correction in 3D, applied to lam."""
    g = sp.csc_matrix(barrier.shape_derivative(C, mesh, x)).T @ lam
    if x.shape[1] == 3:
        g += _reference_ee_correction(C, mesh, x, barrier, stiffness).T @ lam
    return g


def _reference_friction_rest_adjoint(self: ContactAdjoint, ev, lam_c: np.ndarray) -> np.ndarray:
    lagging = self.lagging
    T = lagging.tangential_collisions(lagging.mu_table(lagging.mu), self.potential.barrier, True)
    Jl = self.friction_jacobian(ev, T, ipctk.FrictionPotential.DiffWRT.LAGGED_DISPLACEMENTS)
    out = Jl.T @ lam_c
    if not self.area_weighting:
        return out
    mesh, d = self.surface.mesh, self.dim
    E, F = mesh.edges, mesh.faces
    X = self.surface.rest_positions
    U = lagging.step.lagged
    V = lagging.velocity(ev.U)
    lam = lam_c.reshape(-1, d)
    potential, barrier = self.friction_potential, self.potential.barrier
    for group in (T.vv_collisions, T.ev_collisions, T.ee_collisions, T.fv_collisions):
        for c in group:
            ids = np.asarray(c.vertex_ids(E, F))
            ids = ids[ids >= 0]
            force = potential.force(c, X[ids].ravel(), U[ids].ravel(), V[ids].ravel(), barrier)
            dw = c.weight_gradient
            out[dw.indices] += (force @ lam[ids].ravel() / c.weight) * dw.data
    return out


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    scale = np.abs(b).max()
    assert scale > 0
    return float(np.abs(a - b).max() / scale)


CASES = [
    (2, 1, 1, 100.0, "ipc"),
    (2, 2, 2, 100.0, "ipc"),
    (3, 1, 2, 100.0, "ipc"),
    (3, 1, 1, 0.5, "ipc"),
    (3, 2, 1, 0.5, "ipc"),
    (2, 1, 1, 0.5, "convergent"),
    (3, 1, 1, 0.5, "convergent"),
]


@pytest.mark.parametrize(("dim", "degree", "order", "eps_v", "formulation"), CASES)
def test_vectorised_contact_adjoint_equals_the_loops(
    dim, degree, order, eps_v, formulation, monkeypatch
):
    model, contact, _, u, _ = _scene(
        dim, degree, order, eps_v, comm=MPI.COMM_SELF, formulation=formulation
    )
    lam = _Checker(model, contact, u).random()
    ev = contact._evaluate(u)
    lam_c = contact.adjoint.surface_vector(lam)
    lagging = contact.lagging
    T = lagging.tangential_collisions(lagging.mu_table(lagging.mu), contact.barrier, True)
    assert len(T) > 0
    # the friction collisions read from the normal set they are lagged from: ids as ipctk's
    # tangential collisions hold them
    x, C = lagging.lagged_state(shape_derivatives=True)
    gathered = friction_collision_arrays(C, contact.surface.mesh, x)
    ids, kind = gathered.ids, gathered.kind
    E, F = contact.surface.mesh.edges, contact.surface.mesh.faces
    groups = (T.vv_collisions, T.ev_collisions, T.ee_collisions, T.fv_collisions)
    loop_ids = [np.asarray(c.vertex_ids(E, F)) for g in groups for c in g]
    assert np.array_equal(ids, np.array(loop_ids))
    assert len(np.unique(kind)) >= 2  # more than one collision type in play
    # their weights: read for the merged ones, from the areas for the others; and those of
    # the whole set (the convergent formulation's negative mollified edge-edge terms read)
    weighted = friction_collision_arrays(C, contact.surface.mesh, x, weights=True)
    assert _rel(weighted.weight, np.array([c.weight for g in groups for c in g])) <= TOL
    whole = (C.vv_collisions, C.ev_collisions, C.ee_collisions, C.fv_collisions)
    mesh = contact.surface.mesh
    expected = np.array([c.weight for g in whole for c in g])
    assert _rel(read_weights(C, collision_arrays(C, mesh), mesh, x), expected) <= TOL

    # the friction force's rest-position adjoint, and its area-weight part on its own
    vectorised = contact.adjoint.friction_rest(ev, lam_c)
    reference = _reference_friction_rest_adjoint(contact.adjoint, ev, lam_c)
    assert _rel(vectorised, reference) <= TOL
    lagged = contact.adjoint.lagged_jacobian(ev).T @ lam_c
    assert _rel(vectorised - lagged, reference - lagged) <= TOL

    # the mollifier correction, pair by pair (3D), and the whole shape adjoint
    C = contact.builder.build(ev.x, shape_derivatives=True)
    x = np.asfortranarray(ev.x)
    mesh = contact.surface.mesh
    args = (C, mesh, x, contact.barrier, contact.stiffness)
    if dim == 3:
        mollified = contact_shape._mollified_pairs(C, mesh, mesh.rest_positions, ev.x)
        loop = list(_reference_mollified_pairs(C, mesh, mesh.rest_positions, ev.x))
        assert len(mollified) == len(loop) > 0
        A = contact_shape._ee_correction(*args)
        B = _reference_ee_correction(*args)
        assert abs(A - B).max() <= TOL * abs(B).max()

    # the barrier shape adjoint against ipctk's shape derivative (corrected in 3D): its product
    # with the Hessian of the same set, the weight terms and the mollifier threshold's terms
    contact.potential.hessian(ev)
    Hb_lam = ev.barrier_hessian @ lam_c
    batched = contact_shape.barrier_shape_adjoint(
        *args, lam_c, Hb_lam, contact.adjoint.merged_rows(C)
    )
    assert _rel(batched, _reference_barrier_shape_adjoint(*args, lam_c)) <= TOL
    gX = contact.adjoint_shape(u, lam)
    monkeypatch.setattr(
        step_adjoint,
        "barrier_shape_adjoint",
        lambda C, mesh, x, b, k, lam, Hb_lam, rows, arrays: _reference_barrier_shape_adjoint(
            C, mesh, x, b, k, lam
        ),
    )
    monkeypatch.setattr(ContactAdjoint, "friction_rest", _reference_friction_rest_adjoint)
    assert _rel(gX, contact.adjoint_shape(u, lam)) <= TOL


def test_edge_edge_distance_types_and_barrier():
    """Each ipctk edge-edge distance type and the barrier, batched, against ipctk per pair."""
    rng = np.random.default_rng(2)
    x = rng.standard_normal((40, 4, 3))
    for t in range(9):
        dtype = np.full(len(x), t)
        d, grad = contact_shape._edge_edge_distance(x, dtype)
        kind = ipctk.EdgeEdgeDistanceType(t)
        ref_d = [ipctk.edge_edge_distance(*p, kind) for p in x]
        ref_g = [ipctk.edge_edge_distance_gradient(*p, kind) for p in x]
        assert _rel(d, np.array(ref_d)) <= TOL
        assert _rel(grad.reshape(-1, 12), np.array(ref_g)) <= TOL
    barrier = ipctk.ClampedLogBarrier()
    s = np.linspace(1e-6, 2.0, 57)
    b, db = barrier_derivatives(barrier, s, 1.0)
    assert _rel(b, np.array([barrier(v, 1.0) for v in s])) <= TOL
    assert _rel(db, np.array([barrier.first_derivative(v, 1.0) for v in s])) <= TOL


def test_raw_sparse_vectors_only_for_the_reading_thread():
    """Inside the weight-gradient gather other threads still get real scipy matrices."""
    import threading

    import scipy.sparse

    from diffsolids.contact.derivatives.area_weights import _sparse_as_arrays

    parts = (np.ones(1), np.zeros(1, dtype=np.int32), np.array([0, 1], dtype=np.int32))
    seen = {}

    def other():
        seen["other"] = scipy.sparse.csc_matrix(parts, shape=(2, 1))

    original = scipy.sparse.csc_matrix
    with _sparse_as_arrays():
        mine = scipy.sparse.csc_matrix(parts, (2, 1))
        thread = threading.Thread(target=other)
        thread.start()
        thread.join()
    assert mine is parts
    assert type(seen["other"]) is original and seen["other"].toarray()[0, 0] == 1.0
    assert scipy.sparse.csc_matrix is original


def _ipctk_area_gradients(mesh, alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    if not mesh.are_area_jacobians_initialized():
        mesh.init_area_jacobians()
    out = np.zeros(mesh.ndof)
    for v in range(mesh.num_vertices):
        out += alpha[v] * sp.csc_matrix(mesh.vertex_area_gradient(v)).toarray().ravel()
    for e in range(mesh.num_edges):
        out += beta[e] * sp.csc_matrix(mesh.edge_area_gradient(e)).toarray().ravel()
    return out


@pytest.mark.parametrize("dim", [2, 3])
def test_area_gradients_equal_ipctk(dim):
    """Vertex and edge area gradients in bulk against ipctk's per-vertex and per-edge ones.

    Surface faces, codimensional edges and an isolated vertex (3D); closed and open polylines
    (2D).
    """
    rng = np.random.default_rng(dim)
    if dim == 3:
        faces = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [0, 2, 3]])
        edges = np.vstack([ipctk.edges(faces), [[4, 5]]])
        X = rng.random((7, 3))
    else:
        faces = np.zeros((0, 3), dtype=int)
        edges = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5]])
        X = rng.random((6, 2))
    mesh = ipctk.CollisionMesh(X, edges, faces)
    alpha = rng.standard_normal(mesh.num_vertices)
    beta = rng.standard_normal(mesh.num_edges)
    assert (
        _rel(area_gradient_adjoint(mesh, alpha, beta), _ipctk_area_gradients(mesh, alpha, beta))
        <= TOL
    )


def _probe(tip: np.ndarray) -> np.ndarray:
    """A small triangle pointing down with its tip at ``tip``."""
    return tip + np.array([[0, 0, 0], [0.1, 0.05, 0.2], [-0.05, 0.1, 0.2]])


@pytest.mark.parametrize(("formulation", "area_weighting"), [("ipc", True), ("ipc", False)])
def test_read_weights_equal_ipctks_with_merged_collisions(formulation, area_weighting):
    """A roof of two triangles and small triangles pointing at its ridge (one collision merged
    from the two faces' and the edges' candidates: weight 2 and more without area weights) and
    at its corner; the weights read and computed equal ipctk's one by one."""
    from diffsolids.contact.detection.collision_set import new_collision_set

    roof = np.array([[0, 0, 0], [1, 0, 0], [0.5, -1, -0.2], [0.5, 1, -0.2]], dtype=float)
    gap = 1e-3
    X = np.vstack([roof, _probe(np.array([0.3, 0.0, gap])), _probe(np.array([1.0 + gap, 0, 0]))])
    F = np.array([[0, 2, 1], [0, 1, 3], [4, 5, 6], [7, 8, 9]])
    mesh = ipctk.CollisionMesh(X, ipctk.edges(F), F)
    candidates = ipctk.Candidates()
    candidates.build(mesh, X, 2 * gap)
    C = new_collision_set(formulation, area_weighting)
    C.build(candidates, mesh, X, 2 * gap, 0.0)
    lists = (C.vv_collisions, C.ev_collisions, C.ee_collisions, C.fv_collisions)
    expected = np.array([c.weight for group in lists for c in group])
    assert len(C.vv_collisions) > 0 and len(C.ev_collisions) > 0
    if not area_weighting:
        assert expected.max() >= 2.0  # merged from several candidates
    weights = read_weights(C, collision_arrays(C, mesh), mesh, X)
    assert _rel(weights, expected) <= TOL


@pytest.mark.parametrize("dim", [2, 3])
def test_merged_weights_from_their_gradients_equal_ipctks(dim):
    """Euler's identity on the homogeneous areas: w = X . grad w / k (k = 1 in 2D, 2 in 3D)
    recovers every merged weight from its gradient; None in 3D with a codimensional edge."""
    from diffsolids.contact.detection.collision_set import new_collision_set

    gap = 1e-3
    if dim == 3:
        roof = np.array([[0, 0, 0], [1, 0, 0], [0.5, -1, -0.2], [0.5, 1, -0.2]], dtype=float)
        X = np.vstack([roof, _probe(np.array([0.3, 0.0, gap])), _probe(np.array([1 + gap, 0, 0]))])
        F = np.array([[0, 2, 1], [0, 1, 3], [4, 5, 6], [7, 8, 9]])
        E = ipctk.edges(F)
    else:  # a V-shaped ground and a wedge pointing at its corner
        X = np.array([[-1, 0.5], [0, 0], [1, 0.4], [0.2, 1], [0.0, gap], [-0.3, 1.1]], float)
        E = np.array([[0, 1], [1, 2], [3, 4], [4, 5]])
        F = np.zeros((0, 3), dtype=int)
    mesh = ipctk.CollisionMesh(X, E, F)
    mesh.init_area_jacobians()
    candidates = ipctk.Candidates()
    candidates.build(mesh, X, 2 * gap)
    C = new_collision_set("ipc", True, shape_derivatives=True)
    C.build(candidates, mesh, X, 2 * gap, 0.0)
    merged = merged_weight_collisions(C, dim)
    assert len(merged) > 0
    rows = weight_gradient_rows(merged, X.size)
    recovered = weights_from_gradients(C, mesh, rows)
    assert _rel(recovered, np.array([c.weight for c in merged])) <= TOL
    lists = (C.vv_collisions, C.ev_collisions, C.ee_collisions, C.fv_collisions)
    expected = np.array([c.weight for group in lists for c in group])
    assert _rel(read_weights(C, collision_arrays(C, mesh), mesh, X, recovered), expected) <= TOL
    if dim == 3:  # a segment in no face: lengths (degree 1) beside areas (degree 2)
        Xc = np.vstack([X, [[3, 3, 3], [4, 3, 3]]])
        Ec = np.vstack([E, [[10, 11]]])
        codim = ipctk.CollisionMesh(Xc, Ec, F)
        assert weights_from_gradients(C, codim, sp.csr_matrix((0, Xc.size))) is None


@pytest.mark.parametrize("dim", [2, 3])
def test_friction_kernel_with_weights_from_gradients_equals_read(dim, monkeypatch):
    """The friction coefficients' kernel after the shape kernel (merged weights recovered from
    the gradients it read) equals the kernel alone (merged weights read from ipctk)."""
    recovered = []
    original = step_adjoint.weights_from_gradients

    def spy(C, mesh, rows):
        out = original(C, mesh, rows)
        recovered.append(out)
        return out

    monkeypatch.setattr(step_adjoint, "weights_from_gradients", spy)
    values = []
    for shape_first in (False, True):
        model, contact, _, u, _ = _scene(dim, 1, 1, 0.5, comm=MPI.COMM_SELF)
        lam = _Checker(model, contact, u).random()
        ev = contact._evaluate(u)
        if shape_first:
            contact.adjoint.shape(ev, lam)
        values.append(contact.adjoint.friction(ev, lam))
    merged = [w for w in recovered if w is not None]
    assert len(merged) == 1 and len(merged[0]) > 0  # the second scene, merged collisions
    assert np.any(values[0] != 0.0)  # the pair in contact
    assert _rel(values[1], values[0]) <= TOL
