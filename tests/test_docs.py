"""The documentation cannot rot: every example script runs, and the site builds without warning.

Each ``docs/examples/*.py`` runs in a subprocess at a tiny size, and the checks read what it
prints or writes (Taylor rates, finite-difference errors, objective decrease, output files).
The Sphinx build runs as ``make docs`` does (``-W --keep-going``: any warning fails it).
"""

import itertools
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
EXAMPLES = DOCS / "examples"
BIN = Path(sys.executable).parent
DATA = Path(os.environ.get("DIFFSOLIDS_DATA", ROOT.parent / "shared" / "data" / "diffipc"))
# every example and the test that runs it (a new example without a test fails here)
COVERED = {
    "first_script.py": "test_first_script_serial_and_on_two_ranks",
    "tutorial_2d.py": "test_tutorial_2d_optimises_and_writes_paraview_files",
    "test_tutorial_2d.py": "test_the_tutorials_pytest_gradient_check_passes",
    "tutorial_3d.py": "test_tutorial_3d",
    "howto_extend.py": "test_howto_extend_gradients_through_the_new_pieces",
    "howto_polyfem.py": "test_howto_polyfem_builds_and_runs_the_scene",
    "howto_watch.py": "test_howto_watch_logs_every_iteration_and_plots_the_log",
    "howto_shape.py": "test_howto_shape_lowers_the_stress_and_writes_both_shapes",
}


def _run(args: list[str], cwd: Path = ROOT, timeout: float = 300) -> str:
    """Run a command, fail with its output unless it exits with 0; its stdout."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.run(
        args, cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env, check=False
    )
    assert proc.returncode == 0, f"{args} failed:\n{proc.stdout}\n{proc.stderr[-4000:]}"
    return proc.stdout


def _number(pattern: str, text: str) -> float:
    match = re.search(pattern, text)
    assert match, f"{pattern!r} not in the output:\n{text}"
    return float(match.group(1))


def test_every_example_has_a_test():
    examples = {p.name for p in EXAMPLES.glob("*.py")}
    assert examples == set(COVERED)
    tests = {name for name in globals() if name.startswith("test_")}
    assert set(COVERED.values()) <= tests


def test_first_script_serial_and_on_two_ranks():
    serial = _run([sys.executable, "docs/examples/first_script.py"])
    assert _number(r"Taylor rate ([\d.]+)", serial) >= 1.9
    assert 0.05 < _number(r"sag ([\d.e+-]+) m", serial) < 0.2
    assert _number(r"dsag/dE ([\d.e+-]+)", serial) < 0  # stiffer: less sag
    parallel = _run(
        [str(BIN / "mpiexec"), "-n", "2", sys.executable, "docs/examples/first_script.py"]
    )
    assert parallel.strip() == serial.strip()  # printed once, same digits


def test_tutorial_2d_optimises_and_writes_paraview_files(tmp_path):
    out = _run(
        [
            sys.executable,
            "docs/examples/tutorial_2d.py",
            *("--steps", "10", "--dt", "0.05", "--iterations", "2", "--out", str(tmp_path)),
        ]
    )
    J0 = _number(r"initial throw .*: J = ([\d.e+-]+)", out)
    J1 = _number(r"optimised throw .*: J = ([\d.e+-]+)", out)
    assert J1 < 0.5 * J0
    assert "inverted states 0, intersecting 0" in out
    for label in ("initial", "final"):
        assert (tmp_path / f"{label}.bp").is_dir() and (tmp_path / f"{label}_cells.bp").is_dir()
    rows = _log_rows(out)
    assert [int(r[0]) for r in rows] == list(range(len(rows))) and len(rows) >= 2
    assert float(rows[-1][1]) < float(rows[0][1])
    log = (tmp_path / "log.csv").read_text().splitlines()
    assert log[0].startswith("iteration,objective,gradient_norm") and len(log) == len(rows) + 1


def test_the_tutorials_pytest_gradient_check_passes():
    out = _run(
        [sys.executable, "-m", "pytest", "-q", "-s", "-p", "no:cacheprovider", "docs/examples"]
    )
    assert "1 passed" in out
    rates = [
        float(r)
        for r in re.findall(r"^\s*[\d.e+-]+\s+\S+\s+[\d.]+\s+\S+\s+([\d.]+)\s*$", out, re.M)
    ]
    assert rates and min(rates) > 1.8


def test_tutorial_3d(tmp_path):
    out = _run(
        [
            sys.executable,
            "docs/examples/tutorial_3d.py",
            *("--steps", "4", "--iterations", "1", "--out", str(tmp_path)),
        ]
    )
    assert _number(r"Taylor rate ([\d.]+)", out) >= 1.8
    J0, J1 = (float(x) for x in re.search(r"J ([\d.e+-]+) -> ([\d.e+-]+)", out).groups())
    assert J1 < J0
    assert (tmp_path / "final.bp").is_dir()


def test_howto_extend_gradients_through_the_new_pieces():
    out = _run([sys.executable, "docs/examples/howto_extend.py"])
    errors = re.search(r"relative errors: random ([\d.e+-]+), along the gradient ([\d.e+-]+)", out)
    assert errors, out
    assert max(float(e) for e in errors.groups()) < 1e-6


_LOG_ROW = re.compile(r"^\s*\d+\s+-?\d\.\d+e[+-]\d+\s")  # iteration, J, ...


def _log_rows(out: str) -> list[list[str]]:
    """The rows of the optimisation log printed by ``log=True`` (after its header)."""
    lines = out.splitlines()
    heads = [i for i, s in enumerate(lines) if s.split()[:2] == ["iter", "J"]]
    assert len(heads) == 1, out
    return [s.split() for s in lines[heads[0] + 1 :] if _LOG_ROW.match(s)]


def test_howto_watch_logs_every_iteration_and_plots_the_log(tmp_path):
    out = _run([sys.executable, "docs/examples/howto_watch.py", "--out", str(tmp_path)])
    rows = _log_rows(out)
    assert len(rows) >= 10 and "gradient_rtol" in out  # converged
    J = [float(r[1]) for r in rows]
    assert all(b <= a for a, b in itertools.pairwise(J)) and J[-1] < 1e-12 * J[0]
    assert "E = [200000.  50000.]" in out  # the measured moduli recovered
    log = (tmp_path / "log.csv").read_text().splitlines()
    assert len(log) == len(rows) + 1 and log[0].endswith(",J:misfit")
    for line, row in zip(log[1:], rows, strict=True):
        assert float(line.split(",")[1]) == pytest.approx(float(row[1]), rel=1e-9)
    svg = (tmp_path / "log.svg").read_text()
    assert svg.lstrip().startswith("<?xml") and svg.count('id="axes_') == 2


def test_howto_shape_lowers_the_stress_and_writes_both_shapes(tmp_path):
    script = "docs/examples/howto_shape.py"
    out = _run([sys.executable, script, "--out", str(tmp_path), "--iterations", "8"])
    J = [float(r[1]) for r in _log_rows(out)]
    assert len(J) == 9 and J[-1] < 0.85 * J[0]
    from output_checks import read_vtx

    initial = read_vtx(tmp_path / "initial.bp")["steps"][0]["geometry"]
    final = read_vtx(tmp_path / "final.bp")["steps"][0]["geometry"]
    assert np.abs(initial).max() == pytest.approx(3.0)  # the plate as it was
    assert np.abs(final - initial).max() > 0.05  # the optimised shape


@pytest.mark.skipif(not (DATA / "fig20_kangaroo").is_dir(), reason="paper data not found")
def test_howto_polyfem_builds_and_runs_the_scene():
    out = _run(
        [sys.executable, "docs/examples/howto_polyfem.py", "--data", str(DATA), "--steps", "3"]
    )
    assert "'stiffness': 100000.0" in out and "'friction': 0.5" in out
    assert "3 steps" in out
    assert 0 < _number(r"largest displacement ([\d.]+) m", out) < 0.2


def test_the_documentation_builds_without_a_warning(tmp_path):
    sphinx = shutil.which("sphinx-build", path=str(BIN))
    assert sphinx, "sphinx-build missing: install the docs extra (pip install -e '.[docs]')"
    out = tmp_path / "html"
    proc = subprocess.run(
        [
            sphinx,
            "-W",
            "--keep-going",
            "-q",
            "-b",
            "html",
            "-d",
            str(tmp_path / "doctrees"),
            "docs",
            str(out),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-6000:]
    assert not proc.stderr.strip(), proc.stderr[-6000:]
    for page in ("index", "getting_started", "tutorial", "api/index", "api/diffsolids"):
        assert (out / f"{page}.html").is_file(), page
    # the plot of the tutorial's optimisation log, drawn at build time, is on the how-to page
    assert (ROOT / "docs" / "api" / "figures" / "tutorial_2d_log.svg").is_file()
    assert "tutorial_2d_log.svg" in (out / "howto.html").read_text()
