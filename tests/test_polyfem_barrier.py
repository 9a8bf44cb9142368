"""PolyFEM's damping-transient gradient test (``smoothness_scenes.damping``), two barriers.

With the scene's barrier as PolyFEM means it (kappa 1e5, pairs not area weighted) the disk
rests on the slab a few 1e-11 m away: positions of order 1 m carry ~3e-16 m of round-off, a
relative error of ~1e-5 in the gap and in the contact force, so J has noise that central
differences amplify as h shrinks. With the suggested stiffness (area weighted, the runner's
default) the gap is ~dhat / 10 and central differences verify the damping gradient.
"""

import numpy as np
from contact_checks import central_differences
from smoothness_scenes import damping, damping_polyfem

STEPS = 20  # the disk lands at step 9 and slides


def test_suggested_barrier_gradient_against_central_differences():
    scene = damping(steps=STEPS)
    _, g = scene.rf.value_and_gradient(scene.q0)
    rows, report = central_differences(scene.rf, scene.q0, g, scene.contact, (1e-3, 1e-4), 5)
    errors = {(r.direction, r.h): r.error for r in rows}
    for direction in ("random", "gradient"):
        assert min(errors[direction, h] for h in (1e-3, 1e-4)) <= 1e-6, report
    gaps = [r.min_distance for r in scene.contact.records if r.num_collisions]
    assert gaps and min(gaps) > 1e-6, gaps


def test_polyfem_barrier_rests_pairs_at_round_off_distances():
    scene = damping_polyfem(steps=STEPS)
    scene.rf(scene.q0)
    gaps = [r.min_distance for r in scene.contact.records if r.num_collisions]
    assert gaps and min(gaps) < 1e-9, gaps
    assert np.all(np.isfinite(scene.rf.gradient(scene.q0)))
