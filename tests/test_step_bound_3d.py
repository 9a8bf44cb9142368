"""The 3D near-pair step bound (face-vertex and edge-edge): never exceeded, not absurdly small."""

import time

import ipctk
import numpy as np
import pytest

from diffsolids.contact.detection.step_bound import _plane_bounds
from diffsolids.contact.geometry.distances import pair_distances

ETA = 0.1  # 1 - AdditiveCCD's conservative rescaling


def _distance(kind: str, P: np.ndarray) -> float:
    if kind == "fv":
        return float(np.sqrt(ipctk.point_triangle_distance(P[0], P[1], P[2], P[3])))
    return float(np.sqrt(ipctk.edge_edge_distance(P[0], P[1], P[2], P[3])))


def _bound(kind: str, start: np.ndarray, end: np.ndarray) -> tuple[float, bool]:
    """The bound of one pair given as 4 points at x0 and x1."""
    b, near, _, _ = _plane_bounds(start, end, [np.array([k]) for k in range(4)], kind, ETA)
    return float(b[0]), bool(near[0])


def _hits(kind: str, start: np.ndarray, end: np.ndarray) -> tuple[bool, float]:
    ccd = ipctk.TightInclusionCCD(tolerance=1e-9, conservative_rescaling=1.0)
    call = ccd.point_triangle_ccd if kind == "fv" else ccd.edge_edge_ccd
    return call(*start, *end)


@pytest.mark.parametrize("kind", ["fv", "ee"])
def test_bound_holds_on_random_colliding_paths(kind):
    """Along random straight paths on which ipctk's CCD finds a collision, the distance stays
    above the margin (eta d0 for these plane-distance pairs) up to the bound, and the bound is
    a sizeable part of the time of impact (median over the paths; edges' lines can meet
    outside the edges, before they do: a smaller part there)."""
    rng = np.random.default_rng(7)
    ratios, checked = [], 0
    while checked < 150:
        start = rng.uniform(-1.0, 1.0, (4, 3))
        end = start + rng.uniform(-1.0, 1.0, (4, 3)) * rng.choice([0.1, 1.0, 3.0])
        hit, toi = _hits(kind, start, end)
        d0 = _distance(kind, start)
        if not hit or d0 < 1e-3:
            continue
        checked += 1
        bound, _ = _bound(kind, start, end)
        assert bound <= toi * (1 + 1e-9) + 1e-12, (start, end, bound, toi)
        for t in np.linspace(0.0, min(bound, 1.0), 201):
            d = _distance(kind, start + t * (end - start))
            assert d > 0.0
        ratios.append(bound / toi)
    ratios = np.array(ratios)
    assert ratios.min() > 0.0
    assert np.median(ratios) > {"fv": 0.5, "ee": 0.3}[kind], np.percentile(ratios, [5, 25, 50])


def test_sliding_vertex_a_tiny_gap_above_a_triangle():
    """A vertex 1e-9 above a triangle, sliding 0.3 along it and sinking 2e-9 per step: it
    reaches the plane at t = 0.5; the bound is close to where the gap falls to eta d0
    (t = 0.45), is near, and costs no iterations (AdditiveCCD needs ~|motion| / d)."""
    tri = np.array([[-1.0, -1.0, 0.0], [2.0, -1.0, 0.0], [-1.0, 2.0, 0.0]])
    p0 = np.array([0.1, 0.1, 1e-9])
    p1 = p0 + np.array([0.3, 0.2, -2e-9])
    start, end = np.vstack([p0, tri]), np.vstack([p1, tri])
    tic = time.perf_counter()
    bound, near = _bound("fv", start, end)
    assert time.perf_counter() - tic < 0.1
    assert near
    assert 0.44 < bound <= 0.45 + 1e-6
    # and the distance never reaches zero up to it
    for t in np.linspace(0.0, bound, 101):
        assert _distance("fv", start + t * (end - start)) >= 0.99e-10


def test_sliding_edges_a_tiny_gap_apart_and_separating_motion():
    """Two crossing edges 1e-9 apart sliding across each other: the bound stops them before
    the lines meet; moving apart, the bound is inf (the pair never meets in the step)."""
    a = np.array([[-1.0, 0.0, 1e-9], [1.0, 0.0, 1e-9]])
    b = np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    shift = np.array([0.2, 0.1, -4e-9])  # lines meet at t = 0.25
    start = np.vstack([a, b])
    end = np.vstack([a + shift, b])
    bound, near = _bound("ee", start, end)
    assert near and 0.2 < bound <= 0.225 + 1e-6
    away = np.vstack([a + shift * [1, 1, -1], b])
    bound, near = _bound("ee", start, away)
    assert near and bound == np.inf


def test_vectorised_over_many_pairs():
    """Thousands of pairs in one call (no Python loop over pairs): well under a second."""
    rng = np.random.default_rng(3)
    n = 20000
    x0 = rng.uniform(-1.0, 1.0, (4 * n, 3))
    x1 = x0 + 0.1 * rng.uniform(-1.0, 1.0, (4 * n, 3))
    corners = [np.arange(k, 4 * n, 4) for k in range(4)]
    tic = time.perf_counter()
    for kind in ("fv", "ee"):
        b, near, floored, floor = _plane_bounds(x0, x1, corners, kind, ETA)
        assert b.shape == near.shape == floored.shape == floor.shape == (n,)
        assert np.all((b > 0) | ~np.isfinite(b) | near | (b == 0))
    assert time.perf_counter() - tic < 2.0


@pytest.mark.parametrize("kind", ["fv", "ee"])
def test_pair_distances_are_ipctks(kind):
    """The vectorised distances that decide which pairs are near: ipctk's, pair by pair."""
    rng = np.random.default_rng(11)
    P = [rng.uniform(-1.0, 1.0, (500, 3)) for _ in range(4)]
    P[0][:100, 2] = 1e-9  # vertices (edges) just above a plane through the others
    for Q in P[1:]:
        Q[:100, 2] = 0.0
    d = pair_distances(P, kind)
    expected = [_distance(kind, np.array([Q[k] for Q in P])) for k in range(500)]
    assert d == pytest.approx(expected, rel=1e-9, abs=1e-15)


def test_a_vertex_beside_a_triangle_in_its_plane_is_not_near():
    """A vertex 4 mm beside a triangle, 1e-10 from its plane, crossing it: not a near pair
    (ipctk's narrow phase keeps it; the plane test would stop it for nothing)."""
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    p0 = np.array([-4e-3, 0.5, -1e-10])
    start = np.vstack([p0, tri])
    end = np.vstack([p0 + np.array([-0.02, 0.0, 1e-9]), tri])
    _, near = _bound("fv", start, end)
    assert not near


def _rocking_triangle(height: float, alpha: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """A triangle rocking from z = alpha x to z = -alpha x under a vertex moving from x = -0.5
    to 0.5 at z = ``height``: the linear paths bring the vertex closest to the triangle's plane
    in the middle of the step (plane distance height + 2 alpha (t - 1/2)^2)."""
    tri0 = np.array([[-1.0, -1.0, -alpha], [1.0, -1.0, alpha], [0.0, 1.0, 0.0]])
    tri1 = tri0 * [1.0, 1.0, -1.0]
    p0, p1 = np.array([-0.5, -0.5, height]), np.array([0.5, -0.5, height])
    return np.vstack([p0, tri0]), np.vstack([p1, tri1])


def test_a_dip_inside_the_step_does_not_cut_it():
    """The vertex's gap falls from 5e-10 to 1e-11 in the middle of the step and is back at the
    end: the step is collision-free (the gap stays far above the floor), so the bound is inf
    instead of a cut at the dip; where the vertex reaches the plane (or passes it) in the
    middle, the step is still cut before it."""
    start, end = _rocking_triangle(1e-11)
    bound, near = _bound("fv", start, end)
    assert near and bound == np.inf
    for t in np.linspace(0.0, 1.0, 201):
        assert _distance("fv", start + t * (end - start)) >= 0.99e-11
    for height in (0.0, -1e-11):
        start, end = _rocking_triangle(height)
        bound, near = _bound("fv", start, end)
        d = [_distance("fv", start + t * (end - start)) for t in np.linspace(0.0, bound, 101)]
        assert near and 0.0 < bound < 0.5 and min(d) > 0.0


def _grid(n: int, z: float, shift: float, offset: int) -> tuple[np.ndarray, np.ndarray]:
    """An n x n vertex grid of the unit square at height z, triangulated, its ids from offset."""
    s = np.linspace(0.0, 1.0, n)
    X, Y = np.meshgrid(s + shift, s + shift, indexing="ij")
    V = np.column_stack([X.ravel(), Y.ravel(), np.full(n * n, z)])
    k = np.arange(n * n).reshape(n, n)[:-1, :-1].ravel()
    F = np.concatenate(
        [np.column_stack([k, k + n, k + 1]), np.column_stack([k + 1, k + n, k + n + 1])]
    )
    return V, F + offset


def test_near_pairs_screened_by_box_distance_as_without_screening():
    """The pairs farther apart at x0 than the near radius are left out before the bounds: the
    bounds and the near pairs of a sheet sliding 1e-11 m above a ground, with a second sheet
    within dhat but not near, are those computed on every candidate."""
    import diffsolids.contact.detection.step_bound as step_bound

    n = 12
    parts = [_grid(n, 0.0, 0.0, 0), _grid(n, 1e-11, 0.013, n * n), _grid(n, 5e-4, 0.031, 2 * n * n)]
    V = np.concatenate([p[0] for p in parts])
    F = np.concatenate([p[1] for p in parts])
    E = ipctk.edges(F)
    mesh = ipctk.CollisionMesh(V, E, F)
    x0 = np.asfortranarray(V)
    x1 = x0.copy()
    x1[n * n :, 0] += 2e-3  # both sheets slide; the near one slightly down
    x1[n * n : 2 * n * n, 2] -= 1e-12
    x1 = np.asfortranarray(x1)
    candidates = ipctk.Candidates()
    candidates.build(mesh, x0, x1, 1e-3, ipctk.HashGrid())
    radius = step_bound._near_radius(x0, x1, ETA)
    for name, cands, bounds in step_bound._near_pair_kinds(candidates, mesh):
        assert len(cands) > 0, name
        screened = bounds(x0, x1, ETA, radius)
        full = bounds(x0, x1, ETA, np.inf)
        assert screened[1].any() and not screened[1].all(), name  # near and far pairs
        assert np.array_equal(screened[1], full[1]), name
        near = full[1]
        assert np.array_equal(screened[0][near], full[0][near]), name
        assert np.array_equal(screened[2] & near, full[2] & near), name
