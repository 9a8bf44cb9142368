"""Portability: binaries that run on this CPU, `import dolfinx` first, errors that reach the user.

The error-path tests run each failure in a child process (serial and on 2 ranks): a segfault, a
hang or an error replaced by mpi4py's ``SystemError`` while DOLFINx frees a communicator cannot
fail an in-process test.
"""

import importlib.util
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import diffsolids.portability as portability
from diffsolids.errors import PortabilityError

ROOT = Path(__file__).resolve().parents[1]
MPIEXEC = Path(sys.executable).parent / "mpiexec"


# -- compiled extensions against this CPU ---------------------------------------------------------
def test_pinned_ipctk_uses_no_avx512():
    if shutil.which("objdump") is None:
        pytest.skip("objdump (binutils) is not installed")
    so = Path(importlib.util.find_spec("ipctk").origin)
    used = portability.extension_instruction_sets(so)
    assert "AVX-512" not in used, f"{so.name} uses AVX-512: it crashes on AVX2-only CPUs"


@pytest.mark.parametrize(
    ("line", "family"),
    [
        ("vmovdqu8 %zmm0,(%rax)", "AVX-512"),
        ("vaddpd %ymm17,%ymm1,%ymm2", "AVX-512"),
        ("kmovw %k1,%eax", "AVX-512"),
        ("vfmadd231pd %ymm1,%ymm2,%ymm3", "AVX2/AVX"),
    ],
)
def test_instruction_set_patterns_recognise_their_family(line, family):
    found = {name for name, pattern, _ in portability._ISA_PATTERNS if pattern.search(line)}
    assert family in found
    assert not {name for name, p, _ in portability._ISA_PATTERNS if p.search("addsd %xmm1,%xmm0")}


def test_ipctk_smoke_test_runs_here(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert portability._local_problem.__wrapped__("ipctk", portability.IPCTK_SMOKE_TEST) is None
    assert list((tmp_path / "diffsolids").glob("binary-check-*.json"))  # verdict cached


def test_a_child_killed_by_sigill_raises_a_portability_error(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(portability, "cpu_flags", lambda: frozenset({"sse2", "avx", "avx2"}))
    monkeypatch.setattr(portability, "extension_instruction_sets", lambda path: {"AVX-512"})
    sigill = "import os, signal; os.kill(os.getpid(), signal.SIGILL)"
    with pytest.raises(PortabilityError) as info:
        portability.check_extension("ipctk", sigill)
    text = str(info.value)
    assert re.match(r"ipctk \d+\.\d+\.\d+ cannot run on this CPU", text)
    assert "killed by SIGILL (illegal instruction)" in text
    assert "uses AVX-512 instructions and this CPU has no avx512f" in text
    assert f"pip install 'ipctk=={portability.VERIFIED_IPCTK[-1]}'" in text
    assert not list((tmp_path / "diffsolids").glob("*.json"))  # a failure is never cached


def test_a_failing_child_is_reported_with_its_error(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    with pytest.raises(
        PortabilityError, match=r"(?s)exit status 1\): .*AttributeError: .*no_such_api"
    ):
        portability.check_extension("ipctk", "import ipctk; ipctk.no_such_api()")


# -- `import dolfinx` as a script's first line ----------------------------------------------------
@pytest.mark.parametrize(
    "first_lines",
    [
        "import dolfinx",
        "import ufl, dolfinx",
        "import dolfinx.fem.petsc",
        "import petsc4py; petsc4py.init(); from petsc4py import PETSc",
    ],
)
def test_dolfinx_can_be_imported_first(first_lines):
    child = subprocess.run(
        [sys.executable, "-c", f"{first_lines}\nprint('imported')"],
        capture_output=True,
        text=True,
        check=False,
        timeout=300,
    )
    assert child.returncode == 0 and "imported" in child.stdout, (
        f"{first_lines!r} failed (run `make setup`, which installs diffsolids_mpi_first's "
        f".pth file):\n{child.stderr}"
    )


# -- no object collective on a communicator DOLFINx or PETSc owns ---------------------------------
_OBJECT_COLLECTIVE = re.compile(
    r"(?:\bcomm|tompi4py\(\))\.(?:allgather|allreduce|bcast|gather|scatter|reduce|alltoall|"
    r"scan|exscan|send|recv|isend|irecv|sendrecv)\("
)


def test_object_collectives_go_through_collective_comm():
    offenders = [
        f"{path.relative_to(ROOT)}:{n}: {line.strip()}"
        for folder in ("src", "demos", "forms")
        for path in sorted((ROOT / folder).rglob("*.py"))
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if _OBJECT_COLLECTIVE.search(line)
    ]
    assert not offenders, "use diffsolids.parallel.collective_comm(comm):\n" + "\n".join(offenders)


# -- every documented error reaches the user as itself, serial and on 2 ranks ---------------------
_PRELUDE = """
import numpy as np
from mpi4py import MPI
import diffsolids as ds
from diffsolids.mesh import create_rectangle

COMM = MPI.COMM_WORLD
MAT = ds.NeoHookean(E=1e4, nu=0.3, density=1.0)

def strip():
    return create_rectangle(COMM, [[0, 0], [1, 0.2]], [10, 2],
                            facets={1: lambda x: np.isclose(x[0], 0.0),
                                    2: lambda x: np.isclose(x[0], 1.0)},
                            names={"left": 1, "right": 2})
"""

_SCENARIOS = {
    "nan_modulus": (
        "ds.Model(strip(), ds.NeoHookean(E=float('nan'), nu=0.3))",
        "ParameterError: material parameter E = nan is not finite",
    ),
    "negative_density": (
        "ds.Model(strip(), ds.NeoHookean(E=1e4, nu=0.3, density=-1.0))",
        "ParameterError: density = -1.0 must be positive",
    ),
    "missing_tag": (
        "ds.Model(strip(), MAT).add_dirichlet('clamp', 0.0)",
        "TagError: ",
    ),
    "missing_geo_file": (
        "from diffsolids.mesh import from_geo\n"
        "print(ds.Model(strip(), MAT), from_geo('no_such_scene.geo', COMM))",
        "MeshError: gmsh geometry file no_such_scene.geo does not exist",
    ),
    "inverted_mesh": (
        "d = strip()\n"
        "x = d.mesh.geometry.x\n"
        "x[np.isclose(x[:, 0], 0.5) & np.isclose(x[:, 1], 0.2), 1] = -0.5\n"
        "ds.Simulation(ds.Model(d, MAT), ds.Static())",
        "InvertedElementError: ",
    ),
    "diverging_newton": (
        "def solve(model):\n"
        "    model.add_dirichlet('left', 0.0)\n"
        "    model.add_traction('right', lambda t: [0.3e4 * t, 0.0])\n"
        "    return ds.Simulation(model, ds.Static(num_steps=2, dt=1.0),\n"
        "                         ds.SolverOptions(max_iterations=1), progress=False).run()\n"
        "solve(ds.Model(strip(), MAT))",
        "NewtonConvergenceError: Newton solve of step 1 failed after 1 iterations",
    ),
    "intersecting_bodies": (
        "from diffsolids.contact import ContactTerm\n"
        "from diffsolids.mesh.scene import combine_meshes, simplex_box\n"
        "def solve():\n"
        "    lower = simplex_box([[0, 0], [1, 0.2]], [4, 1])\n"
        "    upper = simplex_box([[0.3, 0.15], [0.6, 0.45]], [2, 2])\n"
        "    model = ds.Model(combine_meshes(COMM, [lower, upper]), MAT)\n"
        "    model.add_numeric_term(ContactTerm(model, dhat=1e-3, stiffness=1e6))\n"
        "    return ds.Simulation(model, ds.Static(), progress=False).run()\n"
        "solve()",
        "IntersectionError: ",
    ),
    "binary_for_another_cpu": (
        "import diffsolids.portability as portability\n"
        "from diffsolids.contact import ContactTerm\n"
        "portability.IPCTK_SMOKE_TEST = 'import os, signal; os.kill(os.getpid(), signal.SIGILL)'\n"
        "ContactTerm(ds.Model(strip(), MAT), dhat=1e-3, stiffness=1e6)",
        "PortabilityError: ipctk ",
    ),
}


@pytest.mark.parametrize("ranks", [1, 2])
@pytest.mark.parametrize("scenario", sorted(_SCENARIOS))
def test_error_reaches_the_user_as_itself(scenario, ranks, tmp_path):
    code, expected = _SCENARIOS[scenario]
    script = tmp_path / f"{scenario}.py"
    script.write_text(_PRELUDE + textwrap.dedent(code) + "\n")
    cmd = [sys.executable, str(script)]
    if ranks > 1:  # each rank's stderr to its own file (interleaved output can split a line)
        cmd = [str(MPIEXEC), "-errfile-pattern=stderr.%r", "-n", str(ranks), *cmd]
    child = subprocess.run(
        cmd, capture_output=True, text=True, check=False, timeout=300, cwd=tmp_path
    )
    errs = [child.stderr]
    if ranks > 1:
        errs = [(tmp_path / f"stderr.{r}").read_text() for r in range(ranks)]
    err = "\n".join(errs)
    assert child.returncode == 1, f"exit {child.returncode} (a crash or a signal):\n{err}"
    # every rank raised the same error, as itself
    for rank_err in errs:
        assert f"diffsolids.errors.{expected}" in rank_err, err
        assert len(re.findall(r"diffsolids\.errors\.\w+: ", rank_err)) == 1, err
    for bad in ("SystemError", "Exception ignored", "Segmentation", "Fatal Python error"):
        assert bad not in err, err


@pytest.mark.skipif(importlib.util.find_spec("adios2") is None, reason="adios2 not installed")
def test_adios2_imported_first_gets_an_explanation_and_second_works():
    def child(code: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)

    first = child("import adios2\nimport diffsolids")
    if first.returncode == 0:
        pytest.skip("this adios2 build coexists with DOLFINx's own ADIOS2")
    assert "Import diffsolids (or dolfinx) before adios2" in first.stderr, first.stderr
    second = child("import diffsolids\nimport adios2\nprint(adios2.FileReader)")
    assert second.returncode == 0, second.stderr
