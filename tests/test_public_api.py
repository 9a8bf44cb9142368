"""The public entry point: a problem script with one import, and checks that leave q as it was."""

import numpy as np
import pytest
from mpi4py import MPI

import diffsolids as ds


def test_every_public_name_exists():
    missing = [name for name in ds.__all__ if not hasattr(ds, name)]
    assert not missing


def _script():
    """A 2D block under gravity on a clamped slab with contact, a UFL objective, shape control."""
    slab = ds.mesh.simplex_box([[0, 0], [1, 0.1]], [8, 1])
    block = ds.mesh.simplex_box([[0.3, 0.1 + 5e-4], [0.6, 0.3]], [3, 2])
    domain = ds.combine_meshes(MPI.COMM_WORLD, [slab, block], names={"slab": 1, "block": 2})
    model = ds.Model(domain, ds.NeoHookean(E=2e4, nu=0.3, density=100.0))
    model.add_gravity(9.81)
    model.add_dirichlet(lambda x: x[1] < 0.05, 0.0)
    integrator = ds.BDF(1, 0.01, 3)
    model.add_numeric_term(ds.ContactTerm(model, dhat=1e-3))  # kappa chosen at the first step
    sim = ds.Simulation(model, integrator, ds.SolverOptions(rtol=1e-12), progress=False)
    height = ds.Integral(lambda f: (f.X[1] + f.u[1]) * f.dx(2), "height of block")
    rf = ds.ReducedFunctional(sim, ds.final_value(height), [ds.ShapeControl(model, "boundary")])
    return rf


def test_a_one_import_script_and_checks_that_restore_the_parameters():
    rf = _script()
    q0 = rf.initial_parameters()
    x0 = rf.model.domain.mesh.geometry.x.copy()
    rng = np.random.default_rng(0)
    d = 1e-3 * rng.standard_normal(len(q0))
    g = rf.gradient(q0)
    along = 1e-3 * g / np.abs(g).max()
    for direction in (d, along):
        result = ds.finite_difference_check(rf, q0, direction, [1e-2, 1e-3], gradient=g)
        assert result.relative_error <= 1e-6, str(result)
    assert ds.taylor_test(rf, q0, d, h0=0.2, num=3).min_rate >= 1.9
    # the perturbed evaluations left the model at q0
    assert np.array_equal(rf.initial_parameters(), q0)
    assert np.array_equal(rf.model.domain.mesh.geometry.x, x0)


def test_moved_scene_helpers_keep_a_warning_alias():
    import importlib

    scenes = importlib.import_module("diffsolids.contact.scenes")
    for name in ("combine_meshes", "simplex_box", "simplex_ball"):
        with pytest.warns(DeprecationWarning, match=f"moved to diffsolids.mesh.{name}"):
            assert getattr(scenes, name) is getattr(ds.mesh, name)
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        scenes.nothing  # noqa: B018


def test_moved_polyfem_scene_reader_keeps_warning_aliases():
    import importlib

    import diffsolids.io
    import diffsolids.polyfem

    old_module = importlib.import_module("diffsolids.io.polyfem_scene")
    for name in ("read_polyfem_scene", "PolyFEMScene", "PolyFEMSetup", "BoxSideSelection"):
        for holder in (diffsolids.io, old_module):
            with pytest.warns(DeprecationWarning, match=f"moved to diffsolids.polyfem.{name}"):
                assert getattr(holder, name) is getattr(diffsolids.polyfem, name)
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        diffsolids.io.nothing  # noqa: B018


MOVED_CONTACT_MODULES = {
    "diffsolids.contact.flat": "diffsolids.contact.geometry.flat",
    "diffsolids.contact.collisions": "diffsolids.contact.detection.collision_set",
    "diffsolids.contact.potential": "diffsolids.contact.energy.contact_potential",
    "diffsolids.contact.adjoint": "diffsolids.contact.derivatives.step_adjoint",
    "diffsolids.contact.polyfem": "diffsolids.polyfem.contact",
}


@pytest.mark.parametrize(("old", "new"), list(MOVED_CONTACT_MODULES.items()))
def test_moved_contact_modules_keep_warning_aliases(old, new):
    import subprocess
    import sys

    # a fresh interpreter: an alias imported once is cached in sys.modules and warns only once
    script = f"""
import importlib, warnings
warnings.simplefilter("error", DeprecationWarning)
try:
    importlib.import_module({old!r})
except DeprecationWarning as w:
    print("warned:", w)
warnings.simplefilter("ignore", DeprecationWarning)
print(importlib.import_module({old!r}) is importlib.import_module({new!r}))
"""
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True
    ).stdout.splitlines()
    assert out == [f"warned: {old} moved to {new} (the old path goes in 0.6)", "True"]


def test_an_unknown_contact_module_is_still_an_import_error():
    with pytest.raises(ModuleNotFoundError, match=r"diffsolids\.contact\.nothing"):
        import diffsolids.contact.nothing  # noqa: F401


def test_moved_canonical_layout_keeps_a_warning_alias():
    import importlib

    import diffsolids.controls

    old_module = importlib.import_module("diffsolids.controls.ordering")
    with pytest.warns(DeprecationWarning, match="moved to diffsolids.mesh.CanonicalLayout"):
        assert old_module.CanonicalLayout is ds.mesh.CanonicalLayout
    assert diffsolids.controls.CanonicalLayout is ds.mesh.CanonicalLayout


def test_peak_rss_mb_sees_an_allocation():
    import subprocess
    import sys

    # an array larger than the high-water mark so far (imports may have left one above the
    # current resident size), touched: the peak must reach at least its size
    code = (
        "import numpy as np\n"
        "from diffsolids.parallel import peak_rss_mb\n"
        "before = peak_rss_mb()\n"
        "size = before + 200.0\n"
        "a = np.ones(int(size * 2**20 / 8))\n"
        "print(before, size, peak_rss_mb())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    before, size, after = (float(x) for x in out.stdout.split())
    assert before > 0 and size <= after <= size + before + 50
