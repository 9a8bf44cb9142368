"""The optimisation log: one printed line per accepted iterate, a CSV or JSON-lines file.

The lines and the file carry the numbers of the optimiser's history; nothing is printed or
written without ``log`` / ``log_file``; two ranks print the serial lines once.
"""

import json
import os
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from mpi4py import MPI
from optimize_script import bar_problem

from diffsolids.optimize import LBFGS, LBFGSOptions, OptimizationError, minimize
from diffsolids.optimize.monitor import (
    IterationLog,
    IterationRecord,
    control_summary,
    plot_log,
    read_log,
)

TESTS = Path(__file__).resolve().parent
OPTIONS = dict(max_iterations=4, gradient_rtol=0)


_ROW = re.compile(r"^\s*\d+\s+-?\d\.\d+e[+-]\d+\s")  # iteration, J, ...


def _table(out: str) -> tuple[str, list[list[str]]]:
    """The header and the rows (split on blanks) of a printed log."""
    lines = out.splitlines()
    heads = [i for i, s in enumerate(lines) if s.split()[:3] == ["iter", "J", "|grad|"]]
    assert len(heads) == 1, out
    rows = [s.split() for s in lines[heads[0] + 1 :] if _ROW.match(s)]
    return lines[heads[0]], rows


def test_log_prints_one_line_per_accepted_iterate_with_the_history_numbers(capsys):
    rf, _ = bar_problem(MPI.COMM_WORLD, bodies=2, regularised=True)
    result = minimize(rf, options=LBFGSOptions(**OPTIONS), log=True, progress=False)
    out = capsys.readouterr().out
    header, rows = _table(out)
    assert header.split() == [
        "iter",
        *("J", "|grad|", "|step|", "t", "trials", "fwd(s)", "grad(s)", "controls"),
    ]
    assert len(rows) == len(result.history) == result.iterations + 1
    for row, rec in zip(rows, result.history, strict=True):
        assert int(row[0]) == rec.iteration
        assert float(row[1]) == pytest.approx(rec.objective, rel=1e-9)
        assert float(row[2]) == pytest.approx(rec.gradient_norm, rel=1e-3)
        if rec.iteration == 0:
            assert row[3] == row[4] == "-" and row[5] == "0"
        else:
            assert float(row[3]) == pytest.approx(rec.step_norm, rel=1e-3)
            assert float(row[4]) == pytest.approx(rec.step_length, rel=1e-3)
            assert row[5] == str(rec.trials) and rec.trials >= 1
        assert float(row[6]) == pytest.approx(rec.forward_seconds, abs=0.006)
        assert float(row[7]) == pytest.approx(rec.gradient_seconds, abs=0.006)
        assert " ".join(row[8:]) == rec.parameter_summary
    # the controls: the two log-moduli of the bodies at the last iterate
    last = [float(x) for x in " ".join(rows[-1][8:]).split("=[")[1].rstrip("]").split(",")]
    assert np.allclose(last, result.q, rtol=1e-3)
    assert result.history[-1].parameter_norm == pytest.approx(np.linalg.norm(result.q), 1e-14)
    assert float(rows[-1][1]) < float(rows[0][1])


@pytest.mark.parametrize("suffix", [".csv", ".jsonl"])
def test_log_file_holds_the_history(tmp_path, suffix, capsys):
    rf, _ = bar_problem(MPI.COMM_WORLD, bodies=2, regularised=True)
    path = tmp_path / "sub" / f"log{suffix}"
    result = minimize(rf, options=LBFGSOptions(**OPTIONS), log_file=path, progress=False)
    assert capsys.readouterr().out == ""  # a file only: nothing printed
    text = path.read_text()
    if suffix == ".csv":
        head = text.splitlines()[0].split(",")
        assert head[:3] == ["iteration", "objective", "gradient_norm"]
        assert head[-2:] == ["J:misfit", "J:0.0001*u2"]
    else:
        assert [json.loads(s)["iteration"] for s in text.splitlines()] == list(range(5))
        assert json.loads(text.splitlines()[-1])["q"] == result.q.tolist()  # by default
    records = read_log(path)
    assert len(records) == len(result.history)
    for got, rec in zip(records, result.history, strict=True):
        assert got == rec  # every number, to the last digit
        assert got.parameter_summary.startswith("E[bodies, log]=[")


def test_nothing_without_the_option(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rf, _ = bar_problem(MPI.COMM_WORLD, bodies=1)
    opt = LBFGS(rf, LBFGSOptions(max_iterations=2), progress=False)
    assert opt.log is None
    opt.run()
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""
    assert list(tmp_path.iterdir()) == []


def test_a_bad_log_file_name_is_refused(tmp_path):
    rf, _ = bar_problem(MPI.COMM_WORLD, bodies=1)
    with pytest.raises(OptimizationError, match=r"log\.txt.*\.csv.*\.jsonl"):
        LBFGS(rf, log_file=tmp_path / "log.txt")


def test_log_with_progress_bar_and_resume(tmp_path, capsys):
    """Lines on stdout next to the bar on stderr; a resumed run rewrites the file from its
    checkpointed history and continues it."""
    rf, _ = bar_problem(MPI.COMM_WORLD, bodies=2)
    path = tmp_path / "log.csv"
    kwargs = dict(log=True, log_file=path, checkpoint_dir=tmp_path / "ckpt", progress=True)
    first = minimize(rf, options=LBFGSOptions(max_iterations=2, gradient_rtol=0), **kwargs)
    captured = capsys.readouterr()
    assert "optimisation" in captured.err  # the bar
    assert len(_table(captured.out)[1]) == 3
    rf, _ = bar_problem(MPI.COMM_WORLD, bodies=2)
    second = minimize(rf, options=LBFGSOptions(max_iterations=4, gradient_rtol=0), **kwargs)
    assert second.resumed_from == 2
    out = capsys.readouterr().out
    assert "(resumed after iteration 2)" in out
    assert [int(r[0]) for r in _table(out)[1]] == [3, 4]
    records = read_log(path)
    assert [r.iteration for r in records] == list(range(5))
    assert records[:3] == first.history
    assert records == second.history


def test_control_summary_shows_small_controls_and_norms_of_large_ones():
    class C:
        def __init__(self, name, size):
            self.name, self.size = name, size

    controls = SimpleNamespace(
        controls=[C("E", 1), C("v0", 2), C("shape", 4)], offsets=np.array([0, 1, 3, 7])
    )
    q = np.array([2.5e5, 1.5, -0.25, 3.0, 0.0, 4.0, 0.0])
    assert control_summary(controls, q) == "E=2.5e+05 v0=[1.5, -0.25] |shape|=5"
    line = IterationLog(MPI.COMM_WORLD).header()
    assert line.split()[:2] == ["iter", "J"]


def test_log_columns_never_merge():
    wide = IterationRecord(
        iteration=12345,
        objective=-1.234567891e-300,
        gradient_norm=2.5e-100,
        step_norm=2.376e-02,
        step_length=1.24e-4,
        trials=12,
        invalid_trials=11,
        forward_seconds=12345.678,
        gradient_seconds=9876.54,
        parameter_summary="E=1",
    )
    row = IterationLog(MPI.COMM_WORLD).line(wide).split()
    assert row == [
        "12345",
        "-1.234567891e-300",
        "2.500e-100",
        "2.376e-02",
        "0.000124",
        "12(11!)",
        "12345.68",
        "9876.54",
        "E=1",
    ]


SCRIPT = """
import sys
from mpi4py import MPI
from optimize_script import bar_problem
from diffsolids.optimize import LBFGSOptions, minimize
rf, _ = bar_problem(MPI.COMM_WORLD, bodies=2, regularised=True)
minimize(rf, options=LBFGSOptions(max_iterations=3, gradient_rtol=0), log=True,
         log_file=sys.argv[1], progress=False)
"""


def _columns(out: str) -> list[list[str]]:
    """The rows without the two timing columns."""
    return [r[:6] + r[8:] for r in _table(out)[1]]


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="starts its own two ranks")
def test_two_ranks_print_the_serial_log_once(tmp_path):
    script = tmp_path / "run.py"
    script.write_text(SCRIPT)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]),
    }
    mpiexec = Path(sys.executable).parent / "mpiexec"
    outs = []
    for n, name in ((1, "serial.jsonl"), (2, "parallel.jsonl")):
        proc = subprocess.run(
            [str(mpiexec), "-n", str(n), sys.executable, str(script), str(tmp_path / name)],
            capture_output=True,
            text=True,
            timeout=300,
            env=env,
            check=False,
        )
        assert proc.returncode == 0, proc.stderr[-4000:]
        outs.append(proc.stdout)
    assert _columns(outs[1]) == _columns(outs[0])  # printed once, same digits
    serial, parallel = read_log(tmp_path / "serial.jsonl"), read_log(tmp_path / "parallel.jsonl")
    assert len(serial) == len(parallel) == 4
    for a, b in zip(serial, parallel, strict=True):
        assert b.objective == pytest.approx(a.objective, rel=1e-10)
        assert b.gradient_norm == pytest.approx(a.gradient_norm, rel=1e-8)
        assert b.parameter_summary == a.parameter_summary


def test_plot_log_draws_objective_and_gradient_panels(tmp_path):
    history = [
        IterationRecord(0, 1.0, {"a": 0.75, "b": 0.25}, gradient_norm=1.0),
        IterationRecord(1, 0.1, {"a": 0.05, "b": 0.05}, gradient_norm=0.1, remeshed=True),
        IterationRecord(2, 0.01, {"a": 0.005, "b": 0.005}, gradient_norm=1e-3),
    ]
    svg = plot_log(history, tmp_path / "log.svg", title="a run").read_text()
    assert svg.count('id="axes_') == 2 and "a run" in svg
    assert plot_log(history, tmp_path / "log.png").read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(OptimizationError, match="at least one record"):
        plot_log([], tmp_path / "empty.svg")
