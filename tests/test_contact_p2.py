"""P2/P3 contact on the subdivided boundary (issue 13 item 7).

With ``boundary="nodes"`` every boundary facet of a P2/P3 body is split at its edge (and face)
nodes, so the collision surface passes through every node of the simulated boundary. The scene
(:func:`bulge_scene`): a block clamped on its sides, one element across, lifted by a body force
under a clamped lid 0.02 above it (shifted off the block's nodes: no vertex starts exactly above
a node, where the distance types switch); its top corners cannot move, so with the old vertex-only
surface the block's top stays a flat segment for the contact term while the P2/P3 edge bulges
through the lid between the corners. The tests:

- the subdivided surface itself: node counts, rest positions equal to the dof coordinates,
  sub-facets oriented as their parent, P1 unchanged, no same-body pairs at rest;
- a prescribed quadratic bulge (an exact P2 field) crosses a vertex of the lid: the subdivided
  surface sees the intersection, the vertex-only one does not; the deformed collision barrier
  on the subdivided surface has exact shape and state derivatives;
- the lifted block under the lid (or under a kinematic obstacle): every Newton iterate and
  every state is intersection-free on the subdivided surface; with ``boundary="vertices"`` the
  final state intersects it (the check fails with the old surface);
- gradients of the lifted block with respect to the shape (mesh vertices: the nodes' rest
  positions are convex combinations of them) and Young's modulus: central differences along a
  random direction and along the gradient, and a Taylor test (test_gradients_contact's
  ``check_gradient``).
"""

import ipctk
import numpy as np
import pytest
import ufl
from mpi4py import MPI
from test_gradients_contact import _direction, check_gradient

import diffsolids as ds
from diffsolids.contact import ContactTerm, Obstacle, suggest_barrier_stiffness
from diffsolids.contact.geometry.subdivision import neighbour_pairs
from diffsolids.contact.geometry.surface import CollisionSurface
from diffsolids.controls import ParameterControl, ShapeControl
from diffsolids.errors import ParameterError
from diffsolids.mesh.scene import combine_meshes, simplex_box
from diffsolids.objectives import DeformedCollisionBarrier, Integral, final_value
from diffsolids.optimize import BoundaryIntersection, check_trajectories
from diffsolids.reduced_functional import ReducedFunctional

GAP = 0.02
DHAT = 0.01
THICKNESS = 0.3


def _meshes(dim: int):
    if dim == 2:
        block = simplex_box([[0, 0], [1, THICKNESS]], [1, 1])
        lid = simplex_box([[0.3137, THICKNESS + GAP], [0.7137, 0.5 + GAP]], [2, 1])
    else:
        block = simplex_box([[0, 0, 0], [1, 1, THICKNESS]], [1, 1, 1])
        lid = simplex_box(
            [[0.3137, 0.2791, THICKNESS + GAP], [0.7137, 0.6791, 0.5 + GAP]], [1, 1, 1]
        )
    return block, lid


def bulge_model(dim: int, degree: int, comm=MPI.COMM_SELF, lid: bool = True) -> ds.Model:
    """The block (body 1, clamped on its sides) and the lid (body 2, clamped on its top)."""
    meshes = _meshes(dim) if lid else _meshes(dim)[:1]
    dom = combine_meshes(comm, meshes, names={"block": 1, "lid": 2} if lid else {"block": 1})
    materials = {1: ds.NeoHookean(E=1e4, nu=0.3), 2: ds.NeoHookean(E=1e5, nu=0.3)}
    model = ds.Model(dom, materials if lid else materials[1], degree=degree)
    lift = np.zeros(dim)
    lift[-1] = 1500.0 if dim == 2 else 3000.0
    model.add_body_force(lift, bodies=[1], name="lift")

    def sides(x):
        on = (x[0] < 1e-9) | (x[0] > 1 - 1e-9)
        if dim == 3:
            on |= (x[1] < 1e-9) | (x[1] > 1 - 1e-9)
        return on & (x[dim - 1] < THICKNESS + 1e-9)

    model.add_dirichlet(sides, 0.0)
    if lid:
        model.add_dirichlet(lambda x: x[dim - 1] > 0.5 + GAP - 1e-9, 0.0)
    return model


def ceiling(dim: int) -> Obstacle:
    """A fixed obstacle at the height of the lid's bottom, wider than the block's bulge."""
    z = THICKNESS + GAP
    if dim == 2:
        return Obstacle([[0.1137, z], [0.9137, z]], name="ceiling")
    square = [[0.1137, 0.0791, z], [0.9137, 0.0791, z], [0.9137, 0.8791, z], [0.1137, 0.8791, z]]
    return Obstacle(square, faces=[[0, 1, 2], [0, 2, 3]], name="ceiling")


def bulge_scene(
    dim: int,
    degree: int,
    boundary: str = "nodes",
    comm=MPI.COMM_SELF,
    obstacle: bool = False,
):
    """The lifted block under the lid or the ceiling: (model, contact, simulation, objective)."""
    model = bulge_model(dim, degree, comm, lid=not obstacle)
    obstacles = [ceiling(dim)] if obstacle else []
    kw = {"boundary": boundary, "obstacles": obstacles}
    probe = ContactTerm(model, dhat=DHAT, stiffness=1.0, **kw)
    kappa = suggest_barrier_stiffness(probe, ds.Static())
    contact = ContactTerm(model, dhat=DHAT, stiffness=kappa, **kw)
    model.add_numeric_term(contact)
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-12), progress=False)
    objective = final_value(Integral(lambda f: f.u[dim - 1] * f.dx(1), "lift")) + final_value(
        Integral(lambda f: 10.0 * ufl.dot(f.u, f.u) * f.dx(2), "lid_strain")
    )
    return model, contact, sim, objective


def _intersects(surface: CollisionSurface, u: np.ndarray) -> bool:
    x = surface.current_rest_positions() + surface.gather(u)
    return bool(ipctk.has_intersections(surface.mesh, np.asfortranarray(x), ipctk.LBVH()))


# -- the subdivided surface ---------------------------------------------------------------------
@pytest.mark.parametrize(("dim", "degree"), [(2, 2), (2, 3), (3, 2), (3, 3)])
def test_subdivided_surface_layout(dim, degree):
    model = bulge_model(dim, degree)
    V = model.V
    old = CollisionSurface(model.domain, V, boundary="vertices")
    new = CollisionSurface(model.domain, V, boundary="nodes")
    nv = old.num_vertices
    assert new.subdivided and not old.subdivided
    assert new.num_surface_vertices == nv
    assert np.array_equal(new.rest_positions[:nv], old.rest_positions)
    parents = old.edges if dim == 2 else old.faces
    if dim == 2:  # k - 1 nodes per edge, k segments
        assert new.num_vertices == nv + (degree - 1) * len(parents)
        assert len(new.edges) == degree * len(parents)
    else:  # (k - 1) per edge, (k - 1)(k - 2)/2 per face, k^2 triangles
        extra = (degree - 1) * len(old.edges) + (degree - 1) * (degree - 2) // 2 * len(parents)
        assert new.num_vertices == nv + extra
        assert len(new.faces) == degree**2 * len(parents)
    # every collision vertex is an FE node at its dof coordinates (W is a 0/1 selection)
    coords = V.tabulate_dof_coordinates()[:, :dim]
    gathered = new.gather(np.ascontiguousarray(coords).ravel())
    assert np.abs(gathered - new.rest_positions).max() < 1e-14
    assert np.array_equal(new.current_rest_positions(), new.rest_positions)
    # sub-facets keep the orientation of their parent (sub-facets of facet f: rows f*k^(d-1)..)
    per = degree ** (dim - 1)
    sub = new.edges if dim == 2 else new.faces
    X, Xp = new.rest_positions, old.rest_positions
    if dim == 2:
        d_sub = X[sub[:, 1]] - X[sub[:, 0]]
        d_par = np.repeat(Xp[parents[:, 1]] - Xp[parents[:, 0]], per, axis=0)
    else:
        d_sub = np.cross(X[sub[:, 1]] - X[sub[:, 0]], X[sub[:, 2]] - X[sub[:, 0]])
        d_par = np.repeat(
            np.cross(Xp[parents[:, 1]] - Xp[parents[:, 0]], Xp[parents[:, 2]] - Xp[parents[:, 0]]),
            per,
            axis=0,
        )
    cosine = np.einsum("ij,ij->i", d_sub, d_par) / (
        np.linalg.norm(d_sub, axis=1) * np.linalg.norm(d_par, axis=1)
    )
    assert np.allclose(cosine, 1.0, atol=1e-12)
    assert np.array_equal(new.primitive_body, np.repeat(old.primitive_body, per))
    # split facets put primitives of one body ~h/(2k) apart: none collides at rest with dhat
    # 1.5 times the shortest sub-facet edge (the parent-facet adjacency filter) ...
    domain = combine_meshes(MPI.COMM_SELF, _meshes(dim)[:1])
    Vb = ds.Model(domain, ds.NeoHookean(E=1.0, nu=0.3), degree=degree).V
    alone = CollisionSurface(domain, Vb, boundary="nodes")
    Xa = alone.rest_positions
    dhat = 1.5 * np.linalg.norm(Xa[alone.edges[:, 0]] - Xa[alone.edges[:, 1]], axis=1).min()
    assert dhat < 0.9 * THICKNESS  # the shortest parent edge
    x = np.asfortranarray(alone.rest_positions)
    C = ipctk.NormalCollisions()
    C.build(alone.mesh, x, dhat, 0.0, ipctk.LBVH())
    assert len(C) == 0
    assert not ipctk.has_intersections(alone.mesh, x)
    # ... while without it the same-body neighbours would
    alone.mesh.can_collide = ipctk.make_vertex_patches_filter(
        np.arange(alone.num_vertices, dtype=np.int32)
    )
    C.build(alone.mesh, x, dhat, 0.0, ipctk.LBVH())
    assert len(C) > 0


@pytest.mark.parametrize(("dim", "degree"), [(2, 3), (3, 2), (3, 3)])
def test_neighbour_filter_refuses_exactly_the_star_pairs(dim, degree):
    """The per-colour patch filters refuse the node pairs of one vertex star, and only those."""
    model = bulge_model(dim, degree)
    surf = CollisionSurface(model.domain, model.V, boundary="nodes")
    sub = surf._subdivision
    refused = {tuple(p) for p in neighbour_pairs(sub.facet_nodes, sub.parents).tolist()}
    n = surf.num_body_vertices
    i, j = np.triu_indices(n, k=1)
    filt = surf._neighbours
    passed = np.array([filt(a, b) for a, b in zip(i.tolist(), j.tolist(), strict=True)])
    assert {(a, b) for a, b, ok in zip(i.tolist(), j.tolist(), passed, strict=True) if not ok} == (
        refused
    )
    # pairs of different bodies are never in a star
    body = surf.body
    assert np.all(body[[a for a, _ in refused]] == body[[b for _, b in refused]])


def test_p1_surface_is_unchanged():
    model = bulge_model(3, 1)
    old = CollisionSurface(model.domain, model.V, boundary="vertices")
    new = CollisionSurface(model.domain, model.V, boundary="nodes")
    assert not new.subdivided
    for name in ("rest_positions", "edges", "faces", "body", "primitive_body"):
        assert np.array_equal(getattr(new, name), getattr(old, name)), name
    G = np.random.default_rng(0).standard_normal((new.num_vertices, 3))
    S = model.shape_space
    assert new.shape_map(S).pull_back(G) is G
    with pytest.raises(ParameterError, match="boundary"):
        CollisionSurface(model.domain, model.V, boundary="faces")


@pytest.mark.parametrize(("dim", "degree"), [(2, 2), (2, 3), (3, 2), (3, 3)])
def test_shape_pull_back_is_the_transpose_of_the_node_positions(dim, degree):
    """Node rest positions are P X_vertices; pull_back applies P^T (a dot-product test)."""
    model = bulge_model(dim, degree)
    surf = CollisionSurface(model.domain, model.V, boundary="nodes")
    S = model.shape_space
    smap = surf.shape_map(S)
    rng = np.random.default_rng(1)
    x0 = model.domain.mesh.geometry.x.copy()
    dX = rng.standard_normal(x0.shape) * 1e-3
    dX[:, dim:] = 0.0
    G = rng.standard_normal((surf.num_vertices, dim))
    try:
        model.domain.mesh.geometry.x[:] = x0 + dX
        moved = surf.current_rest_positions() - surf.rest_positions
    finally:
        model.domain.mesh.geometry.x[:] = x0
    lhs = float(np.sum(G[: surf.num_body_vertices] * moved[: surf.num_body_vertices]))
    pulled = smap.pull_back(G)
    nodes = smap.nodes  # geometry nodes of the owned surface vertices, in the order of cv
    rhs = float(np.sum(pulled[smap.cv] * dX[nodes, :dim]))
    assert rhs == pytest.approx(lhs, rel=1e-12)
    assert not np.allclose(pulled[: surf.num_surface_vertices], G[: surf.num_surface_vertices])


def _bulge(model: ds.Model, height: float) -> np.ndarray:
    """A displacement lifting the block's top midpoint by ``height`` (corners fixed)."""
    dim = model.dim
    X = model.V.tabulate_dof_coordinates()[:, :dim]
    u = np.zeros((len(X), dim))
    block = X[:, dim - 1] < THICKNESS + 1e-9
    shape = 4 * X[block, 0] * (1 - X[block, 0])  # exact in P2
    if dim == 3:
        shape = shape * 4 * X[block, 1] * (1 - X[block, 1])
    u[block, dim - 1] = height * shape * X[block, dim - 1] / THICKNESS
    return u.ravel()


@pytest.mark.parametrize(("dim", "degree"), [(2, 2), (2, 3), (3, 2)])
def test_a_prescribed_bulge_is_seen_between_vertices(dim, degree):
    """An exact P2 bulge of the block's top passes a lid vertex; only the split surface sees it."""
    model = bulge_model(dim, degree)
    V = model.V
    u = _bulge(model, 2.5 * GAP)
    old = CollisionSurface(model.domain, V, boundary="vertices")
    new = CollisionSurface(model.domain, V, boundary="nodes")
    assert not _intersects(old, u)
    assert _intersects(new, u)
    assert not _intersects(new, np.zeros(u.size))
    boundary = BoundaryIntersection(model)
    if boundary.surface.subdivided:  # with the invariants.py diff of issue 13 item 7
        assert boundary.intersects(u) and not boundary.intersects()


@pytest.mark.parametrize(("dim", "degree"), [(2, 2), (2, 3), (3, 2)])
def test_deformed_collision_barrier_derivatives(dim, degree):
    """The deformed barrier on the split surface: shape and state derivatives (central
    differences along a random direction and along the gradient)."""
    model = bulge_model(dim, degree)
    J = DeformedCollisionBarrier(model, 0.05, stiffness=1.0)
    assert J.surface.subdivided
    u = _bulge(model, 0.75 * GAP)  # within dhat of the lid, not through it
    model.fields.u.x.array[:] = u
    assert J.evaluate(model) > 0
    gs = J.shape_gradient(model).reshape(-1, dim)
    gu = J.state_gradient(model)
    S = model.shape_space
    node_of = np.empty(len(gs), dtype=np.int64)
    node_of[S.dofmap.list.ravel()] = model.domain.mesh.geometry.dofmaps[0].ravel()
    x = model.domain.mesh.geometry.x
    x0 = x.copy()
    rng = np.random.default_rng(0)
    h = 1e-4

    def moved(d):
        vals = []
        for t in (h, -h):
            x[node_of, :dim] = x0[node_of, :dim] + t * d
            vals.append(J.evaluate(model))
        x[:] = x0
        return (vals[0] - vals[1]) / (2 * h)

    for d in (rng.standard_normal(gs.shape) * 1e-2, gs / np.abs(gs).max() * 1e-2):
        exact = float(np.sum(gs * d))
        assert moved(d) == pytest.approx(exact, rel=1e-6)
    for du in (rng.standard_normal(u.size) * 1e-3, gu / np.abs(gu).max() * 1e-3):
        vals = []
        for t in (h, -h):
            model.fields.u.x.array[:] = u + t * du
            vals.append(J.evaluate(model))
        model.fields.u.x.array[:] = u
        assert (vals[0] - vals[1]) / (2 * h) == pytest.approx(float(gu @ du), rel=1e-6)


# -- contact on the subdivided surface --------------------------------------------------------
class _NodeMonitor:
    """Every Newton iterate checked for intersections of the subdivided surface."""

    def __init__(self, sim: ds.Simulation, surface: CollisionSurface) -> None:
        self.surface, self.checked, self.bad = surface, 0, []
        sim.solver.snes.setMonitor(self)

    def __call__(self, snes, it: int, fnorm: float) -> None:
        self.checked += 1
        if _intersects(self.surface, snes.getSolution().array_r):
            self.bad.append(it)


@pytest.mark.parametrize(
    ("dim", "degree", "obstacle"),
    [(2, 2, False), (2, 3, False), (3, 2, False), (3, 3, False), (2, 2, True), (3, 2, True)],
)
def test_the_curved_boundary_does_not_pass_through(dim, degree, obstacle):
    nodes = {}
    # under the obstacle, the old surface has static vertices only (its corners are clamped),
    # which the contact pattern's broad phase does not handle yet: the lid cases compare
    for boundary in ("nodes",) if obstacle else ("vertices", "nodes"):
        model, contact, sim, _ = bulge_scene(dim, degree, boundary, obstacle=obstacle)
        surface = CollisionSurface(model.domain, model.V, contact.obstacles, boundary="nodes")
        monitor = _NodeMonitor(sim, surface)
        traj = sim.run()
        nodes[boundary] = [_intersects(surface, u) for u in traj.u]
        if boundary == "nodes":
            assert monitor.checked > 0 and monitor.bad == []
            assert contact.surface.subdivided
            checks = check_trajectories(sim, [traj], contact)
            assert (checks.states, checks.intersecting) == (len(traj.u), 0)
            assert contact.records[-1].num_collisions > 0
            assert 0 < contact.records[-1].min_distance < DHAT
        else:  # the old surface: no contact at all, the edge bulges through the lid
            assert contact.records[-1].num_collisions == 0
    assert nodes["nodes"] == [False] * len(nodes["nodes"])
    assert obstacle or nodes["vertices"][-1]


# -- gradients ----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("dim", "degree", "obstacle"),
    [(2, 2, False), (2, 3, False), (3, 2, False), (3, 3, False), (2, 2, True)],
)
def test_shape_and_material_gradients(dim, degree, obstacle):
    model, contact, sim, objective = bulge_scene(dim, degree, obstacle=obstacle)
    controls = [ShapeControl(model, "all"), ParameterControl(model, "E", "bodies", log=True)]
    rf = ReducedFunctional(sim, objective, controls)
    n_shape = controls[0].size
    direction = np.concatenate(
        [_direction(n_shape, 1e-4), _direction(rf.size - n_shape, 1e-2, seed=1)]
    )
    check_gradient(rf, contact, direction, taylor_h0=0.1)
    assert contact.surface.subdivided
