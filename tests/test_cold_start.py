"""Kernels compiled in the background: FFCx's cache key and files, lazy use, clear errors."""

import threading
from pathlib import Path

import numpy as np
import pytest
import ufl
from dolfinx import fem, mesh
from mpi4py import MPI

from diffsolids.solvers import jit
from diffsolids.solvers.forms import compile_args

pytestmark = pytest.mark.skipif(not jit.background_available(), reason="no POSIX C compiler")


@pytest.fixture(autouse=True)
def _background(monkeypatch):
    """Background builds are opt-in: these tests opt in."""
    monkeypatch.setenv("DIFFSOLIDS_JIT_BACKGROUND", "1")


def _residual(comm: MPI.Comm = MPI.COMM_SELF, coefficient: float = 0.5) -> ufl.Form:
    """A compressible Neo-Hookean residual on a unit cube at a nonzero displacement."""
    m = mesh.create_unit_cube(comm, 3, 3, 3)
    V = fem.functionspace(m, ("Lagrange", 1, (3,)))
    u = fem.Function(V)
    u.interpolate(lambda x: np.stack([0.1 * x[1] ** 2, 0.05 * x[0], 0.02 * x[2] * x[0]]))
    F = ufl.Identity(3) + ufl.grad(u)
    J = ufl.det(F)
    psi = coefficient * (ufl.tr(F.T * F) - 3) - ufl.ln(J) + 0.5 * ufl.ln(J) ** 2
    return ufl.derivative(psi * ufl.dx, u, ufl.TestFunction(V))


def _options(cache: Path, flags: list[str] | None = None) -> dict:
    return {"cache_dir": cache, "timeout": 60, "cffi_extra_compile_args": flags or compile_args()}


def _files(cache: Path) -> set[str]:
    return {p.name for p in cache.iterdir()}


def test_same_module_as_dolfinx_and_same_values(tmp_path):
    form = _residual()
    options = _options(tmp_path / "a")
    built = jit.build_form(form, options)
    assert isinstance(built, fem.Form)
    value = fem.assemble_vector(built).array.copy()
    name = jit.module_name(form, options)
    files = _files(tmp_path / "a")
    assert {f"{name}.c", f"{name}.c.cached"} <= files
    # DOLFINx's own fem.form finds the module in the cache: nothing is compiled again
    again = fem.form(form, jit_options=options)
    assert _files(tmp_path / "a") == files
    assert np.array_equal(fem.assemble_vector(again).array, value)
    # and the module DOLFINx compiles itself (cffi, setuptools) gives the same vector
    reference = fem.form(form, jit_options=_options(tmp_path / "b"))
    assert jit.module_name(form, _options(tmp_path / "b")) == name
    assert np.array_equal(fem.assemble_vector(reference).array, value)
    assert np.abs(value).max() > 1e-3  # a nonzero residual: the comparison can fail


def test_the_form_returns_before_its_compiler_and_waits_on_first_use(tmp_path, monkeypatch):
    release, started = threading.Event(), threading.Event()
    compile_ = jit._compile

    def held(*args):
        started.set()
        assert release.wait(60)
        compile_(*args)

    monkeypatch.setattr(jit, "_compile", held)
    form = _residual()
    built = jit.build_form(form, _options(tmp_path))
    assert isinstance(built, jit.LazyForm)
    assert started.wait(60)  # the compiler runs in the background, not finished yet
    assert not (tmp_path / f"{jit.module_name(form, _options(tmp_path))}.c.cached").exists()
    release.set()
    assert built.rank == 1  # first use: waits for the compiler, then loads the module
    assert fem.assemble_vector(built).array.any()


def test_a_form_built_twice_is_compiled_once(tmp_path):
    before = jit.compile_stats()["kernels_built"]
    form = _residual(coefficient=0.25)
    first, second = (
        jit.build_form(form, _options(tmp_path)),
        jit.build_form(form, _options(tmp_path)),
    )
    assert np.array_equal(fem.assemble_vector(second).array, fem.assemble_vector(first).array)
    assert jit.compile_stats()["kernels_built"] == before + 1
    # a later build finds the module in the cache
    third = jit.build_form(form, _options(tmp_path))
    assert third.rank == 1 and jit.compile_stats()["kernels_built"] == before + 1


def test_compiler_errors_name_the_command_and_do_not_block_a_retry(tmp_path):
    options = _options(tmp_path, ["-O2", "-fno-such-flag-diffsolids"])
    form = _residual()
    with pytest.raises(RuntimeError, match="C compiler failed") as err:
        _ = jit.build_form(form, options).rank
    assert "-fno-such-flag-diffsolids" in str(err.value)
    name = jit.module_name(form, options)
    assert not (tmp_path / f"{name}.c").exists() and (tmp_path / f"{name}.c.failed").exists()
    with pytest.raises(RuntimeError, match="C compiler failed"):  # tried again, not waited for
        jit.build_form(form, options, lazy=False)


@pytest.mark.parametrize(("name", "value"), [("DIFFSOLIDS_JIT_BACKGROUND", "0"), ("CC", "gcc")])
def test_background_builds_off_by_switch_or_compiler_environment(
    tmp_path, monkeypatch, name, value
):
    assert type(jit.build_form(_residual(), _options(tmp_path / "on"))) is jit.LazyForm
    monkeypatch.setenv(name, value)
    assert not jit.background_enabled()
    built = jit.build_form(_residual(), _options(tmp_path / "off"))
    assert type(built) is fem.Form  # DOLFINx's own build (it applies CC, CFLAGS, ...)
