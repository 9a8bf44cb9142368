"""A box thrown along a wavy polyline ground: J smooth in (v0, log mu), the gradient exact.

The ground samples a smooth wave every 5 cm (the puzzle demo's ground), so the box's vertices
slide across the polyline's kinks and its corners graze the crests. J bends sharply where a
contact barely activates (its slope along the gradient changes from ~300 to ~700 within 4e-4
m/s of the throw), so the central differences are taken with a small step.
"""

from smoothness_scenes import wavy

from diffsolids.verification import line_scan


def test_wavy_ground_gradient_random_and_along_gradient():
    scene = wavy(steps=25)
    J, d = scene.check_gradient(1e-6, seed=1, rtol=1e-5)
    scan = line_scan(scene.rf, scene.q0, d, scene.radius, 9)
    assert len(scan.jumps) == 0, str(scan)
    assert scene.rf(scene.q0) == J  # the same q gives the same J after the scan
