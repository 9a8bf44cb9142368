"""Kernel compilation with the C compiler in the background: what a cold cache costs.

DOLFINx compiles a form in three stages, one after the other: UFL and FFCx generate C (Python),
setuptools sets up a build (Python, about 0.2 s a form) and runs the C compiler twice
(compile, link) while Python waits. A model's Newton forms, its objective and the adjoint's
partial derivatives are a few dozen forms, so a first gradient on an empty cache waits for all
of them in a row.

:func:`build_form` keeps the first stage and replaces the other two: the C source goes to the
cache as FFCx would write it and one compiler process builds the module in a background thread
while Python generates the next form's code (several compilers at once, one per core). The
returned :class:`LazyForm` is a :class:`dolfinx.fem.Form` whose compiled object is created on
first use, waiting then for its compiler. The module has the name, flags and cache files FFCx
gives it, so DOLFINx's own ``fem.form`` finds it in the cache (and this module finds DOLFINx's).

Compiler flags are :func:`~diffsolids.solvers.forms.compile_args` for every kernel, however big:
lower optimisation for the big kernels saves little compile time and costs assembly time. On the
damped 3D Neo-Hookean step the largest kernel, the adjoint's shape partial (293 kB of C for P1),
compiles in 2.0 s at ``-O2``; ``-O1`` saves 0.5 s and assembles 1.7x slower, ``-O0`` saves 1.7 s
and assembles 3.6x slower (a gradient assembles it once per time step). For P2 the largest
kernels (318 and 216 kB) compile in 2.4 and 1.5 s at ``-O2`` (without ``-march=native``);
``-O1`` saves 0.8 and 0.4 s, ``-O0`` assembles them 2.5x and 5x slower. Generating their C
takes longer than compiling it.

Off by default (``DIFFSOLIDS_JIT_BACKGROUND=1`` switches it on): on this project's shared 2-core
machine it saves nothing. The dynamic case of ``bench_gradient --cold`` (29 403-dof beam) costs
8-10 s of CPU for compiling its 14 kernels either way, 3-4 s of it UFL/FFCx code generation;
compiling the same 14 forms into empty caches, alternating the two ways, took 8.2-10.3 s through
DOLFINx and 7.8-12.8 s in the background (load average 3; at load 20, 22-34 s and 17-33 s).
With other jobs on both cores there is no idle core to compile on. Under MPI rank 0 builds (in
the foreground) and the other ranks then load the module, as in DOLFINx.
"""

import os
import shlex
import subprocess
import sys
import sysconfig
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import cffi
import cffi.recompiler
import ffcx
import ffcx.codegeneration
import ffcx.codegeneration.C.file_template
import ffcx.codegeneration.jit as ffcx_jit
import ffcx.compiler
import ffcx.naming
import ffcx.options
import numpy as np
import ufl
from dolfinx import default_scalar_type, fem
from dolfinx import jit as dolfinx_jit

from diffsolids.parallel import collective_comm

__all__ = [
    "LazyForm",
    "background_available",
    "background_enabled",
    "build_form",
    "compile_stats",
    "module_name",
]

_LOCK = threading.Lock()
_POOL: ThreadPoolExecutor | None = None
_STATS = {"kernels_built": 0, "codegen_seconds": 0.0, "compiler_seconds": 0.0, "wait_seconds": 0.0}
# builds started by this process, by cache file: a form compiled twice waits for the first build
# (FFCx's own wait for another process polls once a second)
_BUILDS: dict[Path, Future] = {}


# compiler settings from the environment that setuptools applies and this module does not
_SETUPTOOLS_ENV = ("CC", "CFLAGS", "CPPFLAGS", "LDFLAGS", "LDSHARED")


def background_available() -> bool:
    """Whether this platform can build in the background.

    Not on Windows, without a compiler in ``sysconfig``, or when the environment sets the
    compiler or its flags (``CC``, ``CFLAGS``, ``CPPFLAGS``, ``LDFLAGS``, ``LDSHARED``:
    DOLFINx's own build, through setuptools, then applies them).
    """
    if any(name in os.environ for name in _SETUPTOOLS_ENV):
        return False
    return not sys.platform.startswith("win32") and bool(sysconfig.get_config_var("LDSHARED"))


def background_enabled() -> bool:
    """Whether :func:`build_form` compiles in the background.

    Only with ``DIFFSOLIDS_JIT_BACKGROUND=1`` (off by default, see the module docstring) and
    where :func:`background_available`.
    """
    return os.environ.get("DIFFSOLIDS_JIT_BACKGROUND", "0") == "1" and background_available()


def compile_stats() -> dict:
    """What this process compiled in the background.

    Returns:
        ``kernels_built``; seconds of ``codegen`` (UFL, FFCx), of ``compiler`` runs (summed over
        parallel runs) and of ``wait`` on first use (for the compiler, and loading the module).
    """
    with _LOCK:
        return dict(_STATS)


def _cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def _pool() -> ThreadPoolExecutor:
    global _POOL
    with _LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(_cores(), thread_name_prefix="diffsolids-cc")
        return _POOL


def _options(jit_options: dict) -> tuple[dict, dict]:
    """FFCx and JIT options as ``fem.form`` -> ``ffcx_jit`` -> ``compile_forms`` merge them."""
    p_ffcx = ffcx.options.get_options(ffcx.get_options({"scalar_type": default_scalar_type}))
    return p_ffcx, dolfinx_jit.get_options(jit_options)


def module_name(form: ufl.Form, jit_options: dict) -> str:
    """The name FFCx gives the compiled module of ``form`` (its cache key).

    Args:
        form: A UFL form.
        jit_options: DOLFINx JIT options (compiler flags, cache directory).
    """
    p_ffcx, p_jit = _options(jit_options)
    tag = ffcx_jit._compute_option_signature(p_ffcx) + ffcx_jit._compilation_signature(
        p_jit["cffi_extra_compile_args"], p_jit["cffi_debug"]
    )
    return "libffcx_forms_" + ffcx.naming.compute_signature([form], tag)


def _compiler_command(c_file: Path, so_file: Path, flags: list[str]) -> list[str]:
    """One compiler run that compiles and links as setuptools does in two (same flags)."""
    var = sysconfig.get_config_var
    include = [ffcx.codegeneration.get_include_path()]
    venv_include = Path(sys.exec_prefix, "include")
    if venv_include.is_dir():
        include.append(str(venv_include))
    include.append(sysconfig.get_paths()["include"])
    return [
        *shlex.split(var("LDSHARED")),
        *shlex.split(var("CFLAGS") or ""),
        *shlex.split(var("CCSHARED") or ""),
        *(f"-I{d}" for d in include),
        str(c_file),
        "-std=c17",
        *flags,
        *(f"-l{lib}" for lib in ffcx.codegeneration.C.file_template.libraries),
        "-o",
        str(so_file),
    ]


def _compile(c_file: Path, so_file: Path, flags: list[str], ready: Path) -> None:
    """Run the compiler; on success write FFCx's ready marker, else mark the source failed."""
    command = _compiler_command(c_file, so_file, flags)
    t0 = time.perf_counter()
    run = subprocess.run(command, capture_output=True, text=True)
    with _LOCK:
        _STATS["compiler_seconds"] += time.perf_counter() - t0
    if run.returncode != 0:
        c_file.replace(c_file.with_suffix(".c.failed"))  # later runs compile again, not wait
        with _LOCK:
            _BUILDS.pop(c_file, None)
        raise RuntimeError(
            f"the C compiler failed on the kernels of {c_file.name} (exit {run.returncode}):\n"
            f"{shlex.join(command)}\n{run.stderr[-4000:]}"
        )
    ready.write_text(shlex.join(command) + "\n" + run.stdout + run.stderr)
    with _LOCK:
        _STATS["kernels_built"] += 1


def _start(form: ufl.Form, jit_options: dict) -> Future | None:
    """Generate the C of ``form`` and start its compiler.

    Returns None if the cache has the module or another process is building it.
    """
    p_ffcx, p_jit = _options(jit_options)
    name = module_name(form, jit_options)
    cache = Path(p_jit["cache_dir"])
    cache.mkdir(parents=True, exist_ok=True)
    c_file = cache / f"{name}.c"
    with _LOCK:
        if c_file in _BUILDS:
            return _BUILDS[c_file]
    try:
        with open(c_file, "x"):  # FFCx's claim on the module: others wait for the marker
            pass
    except FileExistsError:
        return None
    try:
        t0 = time.perf_counter()
        code, _ = ffcx.compiler.compile_ufl_objects([form], namespace=name, options=p_ffcx)
        decl = (
            ffcx_jit.UFC_HEADER_DECL.format(np.dtype(p_ffcx["scalar_type"]).name)
            + ffcx_jit.UFC_INTEGRAL_DECL
            + ffcx_jit.UFC_FORM_DECL
            + f"extern ufcx_form {ffcx.naming.form_name(form, 0, name)};\n"
        )
        builder = cffi.FFI()
        builder.cdef(decl)
        cffi.recompiler.make_c_source(builder, name, code[1], str(c_file))  # as ffi.compile
        with _LOCK:
            _STATS["codegen_seconds"] += time.perf_counter() - t0
    except BaseException:
        c_file.replace(c_file.with_suffix(".c.failed"))
        raise
    so_file = cache / (name + sysconfig.get_config_var("EXT_SUFFIX"))
    flags = list(p_jit["cffi_extra_compile_args"])
    build = _pool().submit(_compile, c_file, so_file, flags, c_file.with_suffix(".c.cached"))
    with _LOCK:
        _BUILDS[c_file] = build
    return build


class LazyForm(fem.Form):
    """A compiled form whose C module is still being compiled; created on first use.

    Behaves as the :class:`dolfinx.fem.Form` that ``fem.form`` returns (it is one): the first
    access to its compiled object waits for the compiler and loads the module from the cache.

    Args:
        form: The UFL form.
        jit_options: DOLFINx JIT options it is compiled with.
        build: The background compilation (None: the module is, or will be, in the cache).
    """

    def __init__(self, form: ufl.Form, jit_options: dict, build: Future | None):
        self._ufl_form = form
        self._jit_options = jit_options
        self._build = build
        self._compiled: fem.Form | None = None

    def _resolve(self) -> fem.Form:
        if self._compiled is None:
            t0 = time.perf_counter()
            if self._build is not None:
                self._build.result()  # raises the compiler's error
            self._compiled = fem.form(self._ufl_form, jit_options=self._jit_options)
            self._build = None
            with _LOCK:
                _STATS["wait_seconds"] += time.perf_counter() - t0
        return self._compiled

    @property
    def _cpp_object(self):
        return self._resolve()._cpp_object

    @property
    def _ufcx_form(self):
        return self._resolve()._ufcx_form

    @property
    def _code(self):
        return self._resolve()._code

    @property
    def _module(self):
        return self._resolve()._module


def build_form(form: ufl.Form, jit_options: dict, lazy: bool = True) -> fem.Form:
    """Compile a UFL form, its C compiler in the background (see the module docstring).

    Args:
        form: A UFL form with integrals.
        jit_options: DOLFINx JIT options (compiler flags, cache directory, timeout).
        lazy: Return before the compiler has finished (serial runs only).

    Returns:
        A :class:`LazyForm` (serial, ``lazy``) or the compiled ``fem.Form``.

    Raises:
        RuntimeError: The C compiler failed (its command line and messages included).
    """
    if not background_enabled() or not isinstance(form, ufl.Form) or form.empty():
        return fem.form(form, jit_options=jit_options)
    p_jit = dolfinx_jit.get_options(jit_options)
    if p_jit.get("cffi_debug") or p_jit.get("cffi_libraries") or p_jit.get("cffi_verbose"):
        return fem.form(form, jit_options=jit_options)  # options only DOLFINx's build applies
    domains = list(form.subdomain_data())  # the integration domain, as fem.form finds it
    if len(domains) != 1 or domains[0].ufl_cargo() is None:
        return fem.form(form, jit_options=jit_options)
    comm = domains[0].ufl_cargo().comm
    if comm.size == 1:
        build = _start(form, jit_options)
        if lazy:
            return LazyForm(form, jit_options, build)
        if build is not None:
            build.result()
        return fem.form(form, jit_options=jit_options)
    error = None
    if comm.rank == 0:  # as DOLFINx's JIT: rank 0 compiles, the others load from the cache
        try:
            build = _start(form, jit_options)
            if build is not None:
                build.result()
        except Exception as e:  # reported on every rank below
            error = f"{type(e).__name__}: {e}"
    error = collective_comm(comm).bcast(error, root=0)
    if error is not None:
        raise RuntimeError(f"JIT compilation on rank 0 failed: {error}")
    return fem.form(form, jit_options=jit_options)
