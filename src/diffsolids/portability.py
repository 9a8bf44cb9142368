"""Binary compatibility of compiled dependencies with this CPU.

A wheel compiled for a wider instruction set than the CPU has (the PyPI wheel of ipctk 1.6.1 is
built for AVX-512) kills the process with SIGILL the first time it runs such an instruction: no
Python error, no message. Before the first contact computation, :func:`check_extension` runs
every ipctk entry point the package uses on a tiny 2D and 3D scene in a child process. If the
child dies of a signal, the caller gets a :class:`~diffsolids.errors.PortabilityError` that
names the package, the instruction sets its binary uses that the CPU lacks and the fix. The
verdict is cached per (extension file, CPU) in ``$XDG_CACHE_HOME/diffsolids`` so the check costs
one child process per machine and installed version.
"""

import contextlib
import functools
import hashlib
import importlib.metadata
import importlib.util
import json
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

from mpi4py import MPI

from diffsolids.errors import PortabilityError
from diffsolids.parallel import collective_comm

__all__ = [
    "IPCTK_SMOKE_TEST",
    "VERIFIED_IPCTK",
    "check_extension",
    "cpu_flags",
    "ensure_ipctk_runs",
    "extension_instruction_sets",
]

#: ipctk versions whose wheel was verified on CPUs with AVX2 but without AVX-512 (and whose 3D
#: edge-edge mollifier shape-derivative bug ``contact.derivatives.barrier_shape`` corrects).
VERIFIED_IPCTK = ("1.6.0",)

#: Every ipctk entry point the package calls, on one 2D and one 3D scene with active contact and
#: friction (run in a child process by :func:`ensure_ipctk_runs`).
IPCTK_SMOKE_TEST = """
import numpy as np
import ipctk

def scene(dim):
    if dim == 2:
        V = np.array([[0, 0], [1, 0], [1, 0.1], [0, 0.1],
                      [0.2, 0.1005], [0.8, 0.1005], [0.8, 0.3], [0.2, 0.3]], float)
        E = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4]], np.int32)
        return V, E, np.zeros((0, 3), np.int32)
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0],
                  [0.2, 0.2, 0.0005], [0.8, 0.3, 0.0005], [0.3, 0.8, 0.0005],
                  [0.4, 0.4, 0.3]], float)
    F = np.array([[0, 1, 2], [1, 3, 2], [4, 5, 6], [4, 6, 7], [4, 7, 5], [5, 7, 6]], np.int32)
    return V, ipctk.edges(F), F

ipctk.set_num_threads(1)
for dim in (2, 3):
    V, E, F = scene(dim)
    mesh = ipctk.CollisionMesh(np.asfortranarray(V), np.asfortranarray(E), np.asfortranarray(F))
    mesh.init_area_jacobians()
    ids = np.arange(len(V), dtype=np.int32)
    mesh.can_collide = ipctk.make_vertex_patches_filter(ids) & ipctk.make_vertex_patches_filter(ids)
    dhat, x = 1e-2, np.asfortranarray(V)
    C = ipctk.NormalCollisions()
    C.use_area_weighting = True
    C.enable_shape_derivatives = True
    C.build(mesh, x, dhat, 0.0, ipctk.LBVH())
    B = ipctk.BarrierPotential(dhat, 1.0)
    B(C, mesh, x), B.gradient(C, mesh, x), B.hessian(C, mesh, x), B.shape_derivative(C, mesh, x)
    ipctk.initial_barrier_stiffness(1.0, B.barrier, dhat, 1.0, np.zeros(x.size),
                                    B.gradient(C, mesh, x))
    labels = np.zeros(len(V))
    T = ipctk.TangentialCollisions()
    T.build(mesh, x, C, B, labels, labels, lambda a, b: 0.5)
    D = ipctk.FrictionPotential(1e-3)
    v = np.asfortranarray(np.full(V.shape, 1e-3))
    D(T, mesh, v), D.gradient(T, mesh, v), D.hessian(T, mesh, v)
    U = np.zeros_like(x)
    D.force(T, mesh, x, U, v, B)
    for wrt in (ipctk.FrictionPotential.DiffWRT.VELOCITIES,
                ipctk.FrictionPotential.DiffWRT.LAGGED_DISPLACEMENTS,
                ipctk.FrictionPotential.DiffWRT.REST_POSITIONS):
        D.force_jacobian(T, mesh, x, U, v, B, wrt)
    x1 = np.asfortranarray(x + 0.01)
    for ccd in (ipctk.AdditiveCCD(), ipctk.TightInclusionCCD(1e-6, 1000)):
        cand = ipctk.Candidates()
        cand.build(mesh, x, x1, dhat, ipctk.LBVH())
        cand.compute_collision_free_stepsize(mesh, x, x1, 0.0, ccd)
        C2 = ipctk.NormalCollisions()
        C2.build(cand, mesh, x, dhat, 0.0)
    ipctk.has_intersections(mesh, x)
    if dim == 3:
        ea0, ea1, eb0, eb1 = x[0], x[1], x[4], x[5]
        ipctk.edge_edge_cross_squarednorm(ea0, ea1, eb0, eb1)
        ipctk.edge_edge_cross_squarednorm_gradient(ea0, ea1, eb0, eb1)
print("ok")
"""

# instruction-set families a binary may use, by the registers or mnemonics that betray them,
# and the /proc/cpuinfo flag a CPU must have to run them
_ISA_PATTERNS = (
    (
        "AVX-512",
        re.compile(
            r"%zmm|%[xy]mm(?:1[6-9]|2\d|3[01])\b|%k[0-7]\b|\bk(?:mov|and|or|xor|not)[bwdq]\b"
        ),
        "avx512f",
    ),
    ("AVX2/AVX", re.compile(r"%ymm"), "avx2"),
)


@functools.cache
def cpu_flags() -> frozenset[str]:
    """The instruction-set flags of this CPU (``/proc/cpuinfo``; empty where there is none)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return frozenset()
    for line in text.splitlines():
        if line.startswith("flags"):
            return frozenset(line.split(":", 1)[1].split())
    return frozenset()


def extension_instruction_sets(path: Path) -> set[str] | None:
    """Instruction-set families used by a compiled extension, from its disassembly.

    Args:
        path: The shared library.

    Returns:
        Names of the families found (``"AVX-512"``, ``"AVX2/AVX"``), or None where no ``objdump``
        is installed (the check then relies on the child process alone).
    """
    objdump = shutil.which("objdump")
    if objdump is None:
        return None
    out = subprocess.run(
        [objdump, "-d", "--no-show-raw-insn", str(path)],
        capture_output=True,
        text=True,
        check=False,
        timeout=300,
    ).stdout
    return {name for name, pattern, _ in _ISA_PATTERNS if pattern.search(out)}


def _cache_file(extension: Path) -> Path:
    root = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "diffsolids"
    stat = extension.stat()
    cpu = ",".join(sorted(cpu_flags()))
    key = f"{extension.resolve()}|{stat.st_size}|{stat.st_mtime_ns}|{sys.version}|{cpu}"
    return root / f"binary-check-{hashlib.sha256(key.encode()).hexdigest()[:20]}.json"


def _diagnose(package: str, extension: Path, returncode: int, stderr: str) -> str:
    try:
        version = importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        version = "(unknown version)"
    if returncode > 0:  # a Python error: an API this package does not know, not the CPU
        return (
            f"{package} {version} failed diffsolids' test of the {package} functions it uses "
            f"(exit status {returncode}): {stderr.strip()[-800:]}\nInstall the version "
            f"pyproject.toml pins: pip install '{package}=={VERIFIED_IPCTK[-1]}'"
        )
    name = signal.Signals(-returncode).name
    how = f"killed by {name}" + (" (illegal instruction)" if name == "SIGILL" else "")
    used = extension_instruction_sets(extension)
    flags = cpu_flags()
    missing = (
        sorted(n for n, _, flag in _ISA_PATTERNS if n in used and flag not in flags)
        if used is not None and flags
        else []
    )
    lacks = (
        f"its binary {extension.name} uses {', '.join(missing)} instructions and this CPU has no "
        f"{', '.join(f for n, _, f in _ISA_PATTERNS if n in missing)}"
        if missing
        else "its binary may need instructions this CPU lacks"
    )
    return (
        f"{package} {version} cannot run on this CPU: a test of the {package} functions "
        f"diffsolids uses was {how}; {lacks}. Fix: install a build verified on CPUs without "
        f"AVX-512: pip install '{package}=={VERIFIED_IPCTK[-1]}' (the version pyproject.toml "
        "pins), then run again."
    )


def check_extension(package: str, smoke_test: str, comm: MPI.Comm | None = None) -> None:
    """Run ``smoke_test`` in a child process; raise if the child crashes (collective on comm).

    Args:
        package: Import name (and distribution name) of the compiled package, e.g. ``"ipctk"``.
        smoke_test: Python source exercising the package's entry points; exits 0 on success.
        comm: Ranks that must agree (each checks its own CPU); every rank raises if one fails.

    Raises:
        PortabilityError: The child died of a signal (SIGILL: an instruction this CPU lacks)
            or failed; the message names the package, the missing instruction sets and the fix.
    """
    problem = _local_problem(package, smoke_test)
    if comm is not None and comm.size > 1:
        problems = collective_comm(comm).allgather(problem)
        problem = next((p for p in problems if p is not None), None)
    if problem is not None:
        raise PortabilityError(problem)


@functools.cache
def _local_problem(package: str, smoke_test: str) -> str | None:
    """This process's verdict: None, or the message of the failed child (once per process)."""
    spec = importlib.util.find_spec(package)
    if spec is None or spec.origin is None:
        return f"{package} is not installed: pip install -e '.[dolfinx]'"
    extension = Path(spec.origin)
    cache = _cache_file(extension)
    key = hashlib.sha256(smoke_test.encode()).hexdigest()
    with contextlib.suppress(OSError, ValueError):
        if json.loads(cache.read_text()).get(key) == "ok":
            return None
    # a plain child process, not an MPI rank
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PMI_", "MPI", "HYDRA_"))}
    child = subprocess.run(
        [sys.executable, "-c", smoke_test],
        capture_output=True,
        text=True,
        env={**env, "OMP_NUM_THREADS": "1"},
        check=False,
        timeout=600,
    )
    if child.returncode != 0:
        return _diagnose(package, extension, child.returncode, child.stderr)
    with contextlib.suppress(OSError):  # a read-only cache only costs a child process next time
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps({key: "ok"}))
        tmp.replace(cache)
    return None


def ensure_ipctk_runs(comm: MPI.Comm | None = None) -> None:
    """:func:`check_extension` of ipctk with :data:`IPCTK_SMOKE_TEST` (the child runs once)."""
    check_extension("ipctk", IPCTK_SMOKE_TEST, comm)
