"""The contact sparsity pattern follows the pairs that can meet, not the longest surface edge.

A coarse obstacle (one edge or face metres long) used to put every pair of surface vertices
within that length into the Newton matrix (issue 13, item 5). The pattern now holds the stencils
of the primitive pairs whose boxes, grown by dhat, overlap at the start of the step, and grows by
what the Hessians need: the broad phase is checked against brute force (and, with a motion
bound, against the Hessians of every collision set that bound allows), the pattern of a
spinning body against its finite-element pattern, and a solve against the same solve with a full
pattern (the old superset) and with none (every entry from the restart mechanism).
"""

import os
from pathlib import Path

import numpy as np
import pytest
from dolfinx import fem
from mpi4py import MPI
from scipy.spatial import cKDTree

import diffsolids as ds
import diffsolids.contact.energy.pattern as contact_pattern
from diffsolids.contact import ContactTerm, suggest_barrier_stiffness
from diffsolids.contact.detection.reach import box_overlaps, reach_blocks
from diffsolids.contact.geometry.surface import block_pattern
from diffsolids.mesh import read_mesh
from diffsolids.mesh.scene import combine_meshes, simplex_box
from diffsolids.simulation import Trajectory
from diffsolids.states import Phase, StepContext

COMM = MPI.COMM_WORLD
DHAT = 1e-3


def test_box_overlaps_is_brute_force():
    """Boxes of sizes over four orders of magnitude, within one set and between two."""
    rng = np.random.default_rng(3)
    size = 10.0 ** rng.uniform(-3, 1, size=(300, 3))
    lo = rng.uniform(-2, 2, size=(300, 3))
    hi = lo + size * rng.uniform(0.1, 1.0, size=(300, 3))
    lo_b, hi_b = lo[:120] + 0.3, hi[:120] + 0.3
    i, j = box_overlaps(lo, hi, lo_b, hi_b)
    brute = np.all((lo[:, None] <= hi_b[None]) & (lo_b[None] <= hi[:, None]), axis=2)
    assert sorted(zip(i, j, strict=True)) == sorted(zip(*np.nonzero(brute), strict=True))
    i, j = box_overlaps(lo, hi)
    brute = np.all((lo[:, None] <= hi[None]) & (lo[None] <= hi[:, None]), axis=2)
    expected = [(a, b) for a, b in zip(*np.nonzero(brute), strict=True) if a < b]
    assert np.all(i < j) and sorted(zip(i, j, strict=True)) == expected
    assert [len(a) for a in box_overlaps(lo[:0], hi[:0], lo_b, hi_b)] == [0, 0]


def _scene_3d():
    """A coarse clamped slab (4 m faces), a box just above it and a second box beside it."""
    slab = simplex_box([[-2, -2, 0], [2, 2, 0.1]], [1, 1, 1])
    box = simplex_box([[-0.2, -0.2, 0.15], [0.2, 0.2, 0.45]], [3, 3, 3])
    other = simplex_box([[0.3, -0.2, 0.12], [0.6, 0.2, 0.4]], [3, 3, 2])
    model = ds.Model(
        combine_meshes(MPI.COMM_SELF, [slab, box, other]), ds.LinearElastic(E=1e4, nu=0.3)
    )
    model.add_dirichlet(lambda x: x[2] < 0.1 + 1e-9, 0.0)
    contact = ContactTerm(model, dhat=DHAT, stiffness=1.0)
    contact._update_static()
    return contact.surface


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_reach_holds_every_hessian_the_motion_bound_allows(seed):
    """Each vertex moves by its body's translation plus at most ``deformation``: every pair then
    within 2 margin is in the pattern computed before the move, which stays far from dense."""
    import ipctk

    surf = _scene_3d()
    rng = np.random.default_rng(seed)
    nv = surf.num_vertices
    X = surf.rest_positions
    free = ~surf.static
    margin, shake = 0.01, 0.01
    translation = np.array([[0, 0, 0], [0.0, 0.0, -0.04], [-0.075, 0.01, -0.01]])[surf.body - 1]
    translation[~free] = 0.0
    shift = rng.normal(size=(nv, 3))
    shift *= shake * rng.uniform(0, 1, size=(nv, 1)) / np.linalg.norm(shift, axis=1)[:, None]
    shift[~free] = 0.0
    motion = np.linalg.norm(translation, axis=1) + shake * free
    keys = reach_blocks(
        X, X, surf.edges, surf.faces, surf.body, margin, motion, shake * free, surf.static
    )
    x1 = np.asfortranarray(X + translation + shift)
    C = ipctk.NormalCollisions()
    C.build(surf.mesh, x1, 2 * margin, 0.0, ipctk.LBVH())
    H = ipctk.BarrierPotential(2 * margin, 1.0).hessian(C, surf.mesh, x1)
    needed = block_pattern(H, dim=3, num_vertices=nv)
    a, b = np.divmod(needed, nv)
    assert np.any(free[a] & free[b] & (surf.body[a] != surf.body[b]))  # the boxes meet
    assert np.any(surf.static[a] & free[b])  # and the slab
    # blocks of static vertices have no matrix entries: the others are all in the pattern
    assert np.all(np.isin(needed[free[a] & free[b]], keys))
    a, b = np.divmod(keys, nv)
    cross = (surf.body[a] != surf.body[b]) & free[a] & free[b]
    boxes = np.count_nonzero(surf.body[free] == 2) * np.count_nonzero(surf.body[free] == 3)
    assert 0 < cross.sum() < 0.2 * 2 * boxes


def _scene_2d(comm, num_steps: int):
    """Two blocks on a clamped slab whose top is one 10 m edge, a third falling onto one of
    them: within the old reach (the longest edge) every pair of the blocks' vertices."""
    slab = simplex_box([[-5, 0], [5, 0.1]], [1, 1])
    resting = simplex_box([[-0.24, 0.1 + 0.5 * DHAT], [-0.04, 0.3 + 0.5 * DHAT]], [8, 8])
    falling = simplex_box([[-0.2, 0.31], [0.0, 0.41]], [8, 4])
    far = simplex_box([[1.0, 0.1 + 0.5 * DHAT], [1.2, 0.2 + 0.5 * DHAT]], [4, 2])
    model = ds.Model(
        combine_meshes(comm, [slab, resting, falling, far]),
        ds.NeoHookean(E=1e5, nu=0.3, density=1000.0),
    )
    model.add_gravity(9.81)
    model.add_dirichlet(lambda x: x[1] < 0.1 + 1e-9, 0.0)
    integ = ds.BDF(2, 0.01, num_steps)
    probe = ContactTerm(model, dhat=DHAT, stiffness=1.0)
    contact = ContactTerm(model, dhat=DHAT, stiffness=suggest_barrier_stiffness(probe, integ))
    model.add_numeric_term(contact)
    return model, integ, contact


def _vertex_pairs(contact, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Unique (a, b) collision-vertex pairs of global matrix entries (of all ranks' rows)."""
    surf = contact.surface
    gdofs = surf.global_dofs()
    order = np.argsort(gdofs)
    to_vertex = order // surf.dim
    a = to_vertex[np.searchsorted(gdofs, rows, sorter=order)]
    b = to_vertex[np.searchsorted(gdofs, cols, sorter=order)]
    pairs = np.concatenate(COMM.allgather(np.stack([a, b], axis=1)))
    return np.unique(pairs, axis=0)


def _pairs_within(surf, x: np.ndarray, distance: float) -> set:
    """Stencil vertex pairs (both orders) of vertex-edge pairs of two bodies within distance."""
    p0, p1 = x[surf.edges[:, 0]], x[surf.edges[:, 1]]
    e = p1 - p0
    t = np.einsum("vek,ek->ve", x[:, None] - p0[None], e) / np.einsum("ek,ek->e", e, e)
    closest = p0[None] + np.clip(t, 0, 1)[..., None] * e[None]
    v, k = np.nonzero(np.linalg.norm(x[:, None] - closest, axis=2) <= distance)
    other = surf.body[v] != surf.body[surf.edges[k, 0]]
    v, k = v[other], k[other]
    pairs = set()
    for w in (surf.edges[k, 0], surf.edges[k, 1]):
        pairs |= set(zip(v.tolist(), w.tolist(), strict=True))
        pairs |= set(zip(w.tolist(), v.tolist(), strict=True))
    return pairs


def _run(monkeypatch, reach=None, num_steps: int = 8):
    if reach is not None:
        monkeypatch.setattr(contact_pattern, "reach_blocks", reach)
    model, integ, contact = _scene_2d(COMM, num_steps)
    sim = ds.Simulation(model, integ, ds.SolverOptions(rtol=1e-9))
    traj = sim.run()
    return model, integ, contact, sim, traj


def test_coarse_obstacle_pattern_follows_the_pairs_within_reach(monkeypatch):
    """Pattern pairs of two bodies stay below a multiple of the pairs within a distance well
    above dhat plus the motion of a step, at every step; a landing restarts a Newton solve at
    most once per step."""
    model, integ, contact, sim, traj = _run(monkeypatch)
    surf = contact.surface
    assert all(r.num_collisions > 0 for r in contact.records)  # the resting block
    assert contact.records[-1].min_distance < DHAT  # the falling block has landed too
    assert sim.solver.patterns.misses <= integ.num_steps
    free = ~surf.static
    bc = model.dirichlet_dofs()
    u = fem.Function(model.V)
    for i in range(1, integ.num_steps + 1):
        contact.begin_step(StepContext.of(integ, i, traj, Phase.BACKWARD))
        u.x.array[:] = traj.u[i]
        pairs = _vertex_pairs(contact, *contact.matrix_pattern(u, bc))
        a, b = pairs.T
        pattern = (surf.body[a] != surf.body[b]).sum()
        near = set()
        for j in (i - 1, i):
            near |= _pairs_within(surf, surf.rest_positions + surf.gather(traj.u[j]), 0.05)
        near = {(p, q) for p, q in near if free[p] and free[q]}
        assert len(near) > 0
        assert pattern <= 2 * len(near), (i, pattern, len(near))
        # what the Jacobian can need: the stencils of every pair within 2 dhat at u^{i-1}
        x = surf.rest_positions + surf.gather(traj.u[i - 1])
        close = {(p, q) for p, q in _pairs_within(surf, x, 2 * DHAT) if free[p] and free[q]}
        assert close <= set(map(tuple, pairs.tolist()))


def test_spinning_body_adds_no_contact_entries():
    """A body spinning alone (its rim moves 0.04 m, 40 dhat and more than an edge, per step)
    keeps the finite-element pattern: no pair of its surface comes within 2 dhat. (Boxes grown
    by each vertex's motion relative to the body's translation, the old reach, held far pairs
    of its surface.)"""
    square = simplex_box([[-0.1, -0.1], [0.1, 0.1]], [8, 8])
    model = ds.Model(combine_meshes(COMM, [square]), ds.NeoHookean(E=1e5, nu=0.3, density=1000.0))
    contact = ContactTerm(model, dhat=DHAT, stiffness=1e3)
    model.add_numeric_term(contact)
    spin = 40.0  # rad/s
    integ = ds.BDF(2, 0.01, 4)
    sim = ds.Simulation(
        model,
        integ,
        ds.SolverOptions(rtol=1e-9),
        v0=lambda x: np.stack([-spin * x[1], spin * x[0]]),
        progress=False,
    )
    traj = sim.run()
    rim = np.linalg.norm(contact.surface.gather(traj.u[-1] - traj.u[-2]), axis=1).max()
    assert rim > 40 * DHAT
    assert all(r.num_collisions == 0 for r in contact.records)
    fe = sim.solver.create_matrix()
    assert sim.solver.A.getInfo()["nz_allocated"] == fe.getInfo()["nz_allocated"] > 0
    assert sim.solver.patterns.rebuilds == 0


def _all_pairs(x, *args, **kwargs):
    nv = len(x)
    return np.arange(nv * nv, dtype=np.int64)


def _no_pairs(x, *args, **kwargs):
    return np.zeros(0, dtype=np.int64)


def test_solve_is_the_same_with_a_full_or_an_empty_reach(monkeypatch):
    """The reach only saves matrix rebuilds: with every pair (a superset like the old reach) or
    none (every entry added by a restart) the solve takes the same Newton iterations and ends
    at the same state to round-off."""
    _, _, _, sim, traj = _run(monkeypatch)
    _, _, _, full_sim, full = _run(monkeypatch, _all_pairs)
    _, _, _, empty_sim, empty = _run(monkeypatch, _no_pairs)
    iterations = [r.iterations for r in traj.records]
    assert [r.iterations for r in full.records] == iterations
    assert [r.iterations for r in empty.records] == iterations
    scale = np.abs(traj.u[-1]).max()
    for other in (full, empty):
        for u, v in zip(traj.u, other.u, strict=True):
            assert np.abs(u - v).max() <= 1e-9 * scale
    assert full_sim.solver.patterns.misses == 0
    # the restart mechanism fills the matrix
    assert empty_sim.solver.patterns.misses > 0
    assert sim.solver.patterns.misses <= empty_sim.solver.patterns.misses


FIG1 = (
    Path(os.environ.get("DIFFSOLIDS_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    / "diffipc"
    / "fig1_bunnies"
)


def test_fig1_pool_pattern_is_sparse():
    """The paper's fig1 scene: a pool with 3.2 m faces, two bunnies 7 cm apart, the first thrown
    at 2 m/s. The first step's pattern holds a few per cent of the bunnies' vertex pairs (the
    longest-edge reach held all pairs of the two bunnies: half of them), all within reach."""
    if not FIG1.is_dir():
        pytest.skip(f"the paper's data is not at {FIG1} (set DIFFSOLIDS_DATA)")
    bunny = FIG1 / "stanford-bunny.obj_.msh"
    meshes = [read_mesh(FIG1 / "flat-pool.msh", MPI.COMM_SELF)] + [
        read_mesh(bunny, MPI.COMM_SELF, scale=6.0, translation=t) for t in ([0, 0, 0], [1, 0, 0])
    ]
    domain = combine_meshes(COMM, meshes)
    model = ds.Model(domain, ds.NeoHookean(E=1e6, nu=0.48, density=1240.0))
    model.add_dirichlet(lambda x: x[1] < 0.17, 0.0)
    contact = ContactTerm(model, dhat=DHAT, stiffness=1e5)
    v0 = fem.Function(model.V)
    v0.x.array.reshape(-1, 3)[model.V.dofmap.list[domain.cell_tags.find(2)]] = [2.0, 0.5, 0.0]
    traj = Trajectory(times=[0.0], u=[np.zeros_like(v0.x.array)], v=[v0.x.array.copy()])
    contact.begin_step(StepContext.of(ds.BDF(1, 0.05, 1), 1, traj))
    surf = contact.surface
    nv = surf.num_vertices
    free = np.flatnonzero(~surf.static)
    a, b = np.divmod(contact.pattern.reach(contact._step), nv)
    pattern = set(zip(a.tolist(), b.tolist(), strict=True))
    free_pairs = {(p, q) for p, q in pattern if p < q and not surf.static[[p, q]].any()}
    assert len(free_pairs) < 0.05 * len(free) * (len(free) - 1) / 2
    # each box grows by dhat + 2 dt |v0| at most: pairs of primitives within sqrt(3) twice
    # that in the max norm, their vertices within one edge more each
    x = surf.rest_positions
    h = np.linalg.norm(np.diff(x[surf.edges], axis=1), axis=-1).reshape(-1)
    h_free = h[~surf.static[surf.edges].all(axis=1)].max()
    reach = 3**0.5 * 2 * (DHAT + 2 * 0.05 * np.linalg.norm([2.0, 0.5])) + 2 * h_free
    within = cKDTree(x[free]).query_pairs(reach, output_type="ndarray")
    within = {tuple(sorted(pq)) for pq in free[within].tolist()}
    assert free_pairs <= within


@pytest.mark.parametrize(("dim", "formulation"), [(2, "ipc"), (3, "ipc"), (3, "convergent")])
def test_collision_stencils_are_the_barrier_hessians_blocks(dim, formulation):
    """The pattern takes the barrier's blocks from the collisions' stencils (no Hessian): they
    are the nonzero blocks of the exact barrier Hessian."""
    from test_contact_kernels import _scene

    from diffsolids.contact.detection.collision_arrays import collision_arrays, stencil_blocks

    _, contact, _, u, _ = _scene(dim, 1, 1, 0.5, comm=MPI.COMM_SELF, formulation=formulation)
    ev = contact._evaluate(u)
    contact.potential.hessian(ev)
    nv = contact.surface.num_vertices
    exact = block_pattern(ev.barrier_hessian, dim=dim, num_vertices=nv)
    stencils = stencil_blocks(collision_arrays(ev.collisions, contact.surface.mesh), nv)
    assert np.any(exact // nv != exact % nv)  # off-diagonal blocks in play
    assert np.array_equal(stencils, exact)
