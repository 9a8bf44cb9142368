"""Contact with a flat obstacle does not depend on its triangulation (both formulations).

The block of issue 38 dropped flat on a ground of 1, 2 or 4 coplanar triangles (the same
square), the 2D box on a ground of one or four collinear segments: the motion is the same to
round-off. Without the flat-region treatment the IPC collision set made the shared edge under
the block's diagonal a barrier ridge that pushed the landing to one of two mirror states.
"""

import subprocess
import sys

import numpy as np
import pytest
from smoothness_scenes import drop, drop_2d

import diffsolids as ds
from diffsolids.contact.detection.collision_arrays import collision_arrays, read_weights
from diffsolids.contact.geometry.flat import flat_edge_mask, flat_vertex_mask
from diffsolids.contact.geometry.obstacle import _edges_of
from diffsolids.verification import line_scan

STEPS = 8  # the impact is step 5


def _fan(height: float = 0.0):
    V = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0], [0.1, 0.2, height]], float)
    F = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    return V, F, _edges_of(F)


def test_flat_edges_and_vertices_3d():
    V, F, E = _fan()
    edges = flat_edge_mask(V, F, E)
    inner = (E == 4).any(axis=1)
    assert np.array_equal(edges, inner)  # the four edges to the middle; the rim is no joint
    assert np.array_equal(flat_vertex_mask(V, E, edges), [False] * 4 + [True])
    V, F, E = _fan(height=0.01)  # a pyramid: no flat joint
    edges = flat_edge_mask(V, F, E)
    assert not edges.any() and not flat_vertex_mask(V, E, edges).any()


@pytest.mark.parametrize("height", [1e-9, -1e-9, 1e-12])
def test_a_crease_above_round_off_is_no_flat_joint(height):
    """Normals 1e-9 apart pass the angle test; the crease is geometry at barrier distances."""
    V, F, E = _fan(height=height)
    edges = flat_edge_mask(V, F, E)
    assert not edges.any() and not flat_vertex_mask(V, E, edges).any()
    V, F, E = _fan(height=1e-16)  # round-off: flat
    assert flat_edge_mask(V, F, E).sum() == 4


def test_a_kink_above_round_off_is_no_flat_vertex_2d():
    X = np.array([[0, 0], [1, 0], [2, 1e-9], [3, 0], [4, 0]], float)
    segments = np.column_stack([np.arange(4), np.arange(1, 5)])
    assert np.array_equal(flat_vertex_mask(X, segments, None), [0, 0, 0, 0, 0])
    X[2, 1] = 1e-17
    assert np.array_equal(flat_vertex_mask(X, segments, None), [0, 1, 1, 1, 0])


def test_flat_vertices_2d():
    X = np.array([[0, 0], [1, 0], [2, 0], [3, 0.1], [4, 0.2]], float)
    segments = np.column_stack([np.arange(4), np.arange(1, 5)])
    assert np.array_equal(flat_vertex_mask(X, segments, None), [0, 1, 0, 1, 0])


def _final(triangles: int, formulation: str):
    scene = drop(triangles, steps=STEPS, formulation=formulation)
    J = scene.rf(scene.q0)
    its = [r.iterations for r in scene.rf.trajectory.records]
    return J, scene.rf.trajectory.u[-1].copy(), its


@pytest.mark.parametrize("formulation", ["ipc", "convergent"])
def test_drop_independent_of_the_ground_triangulation(formulation):
    J1, u1, _ = _final(1, formulation)
    for triangles in (2, 4):
        J, u, its = _final(triangles, formulation)
        assert abs(J - J1) <= 1e-9 * abs(J1), (triangles, J, J1)
        assert np.abs(u - u1).max() <= 1e-9
        assert its[4] <= 10, its  # the impact step: 5 iterations measured (before: 55-71)


@pytest.mark.parametrize("formulation", ["ipc", "convergent"])
def test_2d_drop_independent_of_the_ground_segments(formulation):
    one = drop_2d(steps=15, formulation=formulation, joints=())
    J1 = one.rf(one.q0)
    joints = drop_2d(steps=15, formulation=formulation)
    J = joints.rf(joints.q0)
    assert abs(J - J1) <= 1e-9 * abs(J1), (J, J1)
    u1, u = one.rf.trajectory.u[-1], joints.rf.trajectory.u[-1]
    assert np.abs(u - u1).max() <= 1e-9


@pytest.mark.parametrize(
    ("formulation", "area_weighting"), [("ipc", True), ("ipc", False), ("convergent", True)]
)
@pytest.mark.parametrize("dim", [2, 3])
def test_collision_weights_from_areas_equal_ipctks(dim, formulation, area_weighting):
    """The set's weights (the merged and flat-corrected ones read, the others from the areas
    or 1) equal ipctk's, one by one, on a ground with flat joints after the landing (3D: the
    ground of 4 triangles, whose flat centre vertex is under a vertex of the block)."""
    if dim == 3:
        scene = drop(4, steps=6, formulation=formulation)
    else:
        scene = drop_2d(steps=15, formulation=formulation)
    scene.rf(scene.q0)
    model, contact = scene.rf.simulation.model, scene.contact
    model.fields.u.x.array[:] = scene.rf.trajectory.u[-1]
    x = contact._evaluate(model.fields.u).x
    builder = contact.builder
    builder.area_weighting = area_weighting
    try:
        C = builder.whole_set(x)
    finally:
        builder.area_weighting = True
    mesh = contact.surface.mesh
    lists = (C.vv_collisions, C.ev_collisions, C.ee_collisions, C.fv_collisions)
    expected = np.array([c.weight for group in lists for c in group])
    assert len(expected) > 0
    if dim == 3 and formulation == "convergent":  # the pair at the ground's flat centre vertex
        assert len(C.vv_collisions) > 0
    weights = read_weights(C, collision_arrays(C, mesh), mesh, x)
    assert np.abs(weights - expected).max() <= 1e-14 * np.abs(expected).max()
    if area_weighting:  # the adjoint's weights once it holds the merged weight gradients
        S = builder.whole_set(x, shape_derivatives=True)
        contact.adjoint.merged_rows(S)
        held = contact.adjoint.weighted_arrays(S, x).weight
        assert np.abs(held - expected).max() <= 1e-12 * np.abs(expected).max()


def test_drop_gradient_and_scan():
    scene = drop(2, steps=STEPS)
    J, g = scene.rf.value_and_gradient(scene.q0)
    for d in (np.array([1.0]), g / np.linalg.norm(g)):
        fd = ds.finite_difference_check(scene.rf, scene.q0, d, steps=[1e-4], gradient=g)
        assert fd.relative_error <= 1e-5, str(fd)
    scan = line_scan(scene.rf, scene.q0, np.array([1.0]), scene.radius, 9)
    assert len(scan.jumps) == 0, str(scan)
    assert scene.rf(scene.q0) == J  # the same q gives the same J after the scan


@pytest.mark.slow
def test_drop_2d_gradient_random_and_along_gradient():
    scene = drop_2d(steps=20)
    _, d = scene.check_gradient(1e-4, seed=3, rtol=1e-5)
    # taylor_test's default steps shrink past the non-asymptotic first ones (rates 1.65, 1.88,
    # 2.52 from h = 8.3e-3 on 30 steps) to rate 2
    taylor = ds.taylor_test(scene.rf, scene.q0, d)
    assert np.all(np.abs(taylor.rates_second - 2.0) <= 0.15) and not taylor.note, str(taylor)


def test_line_scan_finds_a_jump():
    smooth = line_scan(lambda q: float(np.sin(q[0])), np.zeros(1), np.ones(1), 1.0, 21)
    assert len(smooth.jumps) == 0 and smooth.deviations.max() < 0.01
    step = line_scan(lambda q: float(q[0] + (q[0] > 0.01)), np.zeros(1), np.ones(1), 1.0, 21)
    assert list(step.jumps) == [10, 11], str(step)
    with pytest.raises(ValueError, match="num >= 3"):
        line_scan(lambda q: 0.0, np.zeros(1), np.ones(1), 1.0, 2)


def test_formulation_errors_in_a_child_process():
    code = (
        "import numpy as np\n"
        "from mpi4py import MPI\n"
        "import diffsolids as ds\n"
        "box = ds.mesh.simplex_box([[0, 0], [1, 1]], [2, 2])\n"
        "model = ds.Model(ds.combine_meshes(MPI.COMM_SELF, [box]), ds.NeoHookean(E=1e5, nu=0.3))\n"
        "for kw in ({'formulation': 'max'}, {'area_weighting': False, "
        "'formulation': 'convergent'}):\n"
        "    try:\n"
        "        ds.ContactTerm(model, dhat=1e-3, **kw)\n"
        "    except ds.ParameterError as e:\n"
        "        print('refused:', e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "contact formulation 'max'" in out.stdout
    assert "needs area_weighting=True" in out.stdout


def test_nearest_face_of_a_flat_region_leaves_the_candidates_whole():
    import ipctk

    from diffsolids.contact.geometry.flat import FlatRegions, flat_edge_mask, flat_primitive_regions

    ground = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    faces = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    edges = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]], dtype=np.int32)
    flat = flat_edge_mask(ground, faces, edges)
    assert flat.tolist() == [False, True, False, False, False]  # the diagonal
    regions = flat_primitive_regions(ground, edges, faces, flat)
    assert regions.tolist() == [0, 0]
    # a lone body vertex 4 over the ground, near the diagonal
    V = np.vstack([ground, [[0.55, 0.5, 5e-4]]])
    mesh = ipctk.CollisionMesh(V, edges, faces)
    regions = FlatRegions(3, np.flatnonzero(flat), np.zeros(0), np.concatenate([regions]))
    candidates = ipctk.Candidates()
    candidates.build(mesh, V, 1e-2)
    assert sorted(c.face_id for c in candidates.fv_candidates if c.vertex_id == 4) == [0, 1]
    whole = len(candidates.fv_candidates)
    for x, face in ((0.55, 0), (0.45, 1)):  # below / above the diagonal x = y
        X = V.copy()
        X[4, 0] = x
        kept = regions.nearest(candidates, np.asfortranarray(X), mesh)
        assert [c.face_id for c in kept.fv_candidates if c.vertex_id == 4] == [face]
        assert len(candidates.fv_candidates) == whole  # the segment's candidates stay whole
