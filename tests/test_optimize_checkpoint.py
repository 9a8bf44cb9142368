"""Checkpoints: a run stopped (or killed with SIGKILL) resumes with the same iterates."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI
from optimize_script import dynamic_problem

from diffsolids.optimize import LBFGS, LBFGSOptions

SCRIPT = Path(__file__).with_name("optimize_script.py")
OPTIONS = {"gradient_rtol": 0.0}


def _run(iterations, checkpoint=None, output=None):
    rf, _ = dynamic_problem(MPI.COMM_WORLD)
    opt = LBFGS(
        rf,
        LBFGSOptions(max_iterations=iterations, **OPTIONS),
        checkpoint_dir=checkpoint,
        output_dir=output,
        write_parameters=True,
        plot_every=0,
    )
    return opt, opt.run()


def _assert_same_iterates(a, b, rtol):
    assert [r.iteration for r in a] == [r.iteration for r in b]
    Ja = np.array([r.objective for r in a])
    Jb = np.array([r.objective for r in b])
    assert np.all(np.abs(Ja - Jb) <= rtol * np.abs(Jb)), np.abs(Ja - Jb) / np.abs(Jb)
    qa = np.array([r.q for r in a])
    qb = np.array([r.q for r in b])
    assert np.all(np.abs(qa - qb) <= rtol * np.abs(qb))


def test_resume_continues_with_the_same_iterates(tmp_path):
    ckpt = tmp_path / "checkpoint"
    _, stopped = _run(3, ckpt, tmp_path / "out")
    assert stopped.iterations == 3 and stopped.reason == "max_iterations"
    # files of a checkpoint interrupted while being replaced: ignored on resume
    rank = MPI.COMM_WORLD.rank
    (ckpt / f"trajectory_it000004_m000_rank{rank:04d}.npz").write_bytes(b"partial")
    (ckpt / ".state.npz.999.tmp").write_bytes(b"partial")
    _, resumed = _run(7, ckpt, tmp_path / "out")
    assert resumed.resumed_from == 3
    _, reference = _run(7)
    _assert_same_iterates(resumed.history, reference.history, 1e-10)
    # only this process's forward solves are counted: 4 more iterations
    assert resumed.num_gradient == 4
    lines = (tmp_path / "out" / "history.jsonl").read_text().splitlines()
    assert [json.loads(s)["iteration"] for s in lines] == list(range(8))
    # exactly one trajectory per rank is kept
    assert len(list(ckpt.glob("trajectory_*_rank*.npz"))) == 1


def test_checkpoint_holds_the_warm_start_trajectory(tmp_path):
    opt, _ = _run(2, tmp_path)
    accepted = opt.point.trajectory
    rf, _ = dynamic_problem(MPI.COMM_WORLD)
    resumed = LBFGS(rf, LBFGSOptions(max_iterations=2, **OPTIONS), checkpoint_dir=tmp_path)
    result = resumed.run()  # nothing left to do: resumes and stops at once
    assert result.resumed_from == 2 and result.iterations == 2
    assert resumed.point.trajectory is not None
    for a, b in zip(resumed.point.trajectory.u, accepted.u, strict=True):
        assert np.array_equal(a, b)
    assert np.array_equal(resumed.point.q, opt.point.q)
    assert np.array_equal(resumed.point.g, opt.point.g)
    assert len(resumed.memory) == len(opt.memory)
    for a, b in zip(resumed.memory.s, opt.memory.s, strict=True):
        assert np.array_equal(a, b)


def _script(checkpoint, output, iterations):
    cmd = [sys.executable, str(SCRIPT), "--checkpoint", str(checkpoint), "--output", str(output)]
    cmd += ["--iterations", str(iterations)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def _history(path):
    if not path.is_file():
        return []
    return [json.loads(s) for s in path.read_text().splitlines() if s.endswith("}")]


def _wait_for_records(proc, out, count):
    """Wait until the script's history has ``count`` records (or the script ended)."""
    deadline = time.monotonic() + 600
    while len(_history(out / "history.jsonl")) < count and proc.poll() is None:
        assert time.monotonic() < deadline, "the optimisation script made no progress"
        time.sleep(0.01)


def test_killed_run_resumes_like_an_uninterrupted_one(tmp_path):
    iterations = 10
    ckpt, out = tmp_path / "ckpt", tmp_path / "out"
    proc = _script(ckpt, out, iterations)
    _wait_for_records(proc, out, 4)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, proc.stdout.read().decode()
    killed_at = len(_history(out / "history.jsonl"))
    assert 4 <= killed_at <= iterations
    resumed = _script(ckpt, out, iterations)
    log = resumed.communicate()[0].decode()
    assert resumed.returncode == 0, log
    resumed_from = int(log.split("resumed_from=")[1].split()[0])
    assert killed_at - 2 <= resumed_from <= killed_at - 1  # the last (or the one before, if it was
    # being written when the process died) checkpoint before the kill
    reference = _script(tmp_path / "ckpt_ref", tmp_path / "out_ref", iterations)
    log_ref = reference.communicate()[0].decode()
    assert reference.returncode == 0, log_ref
    a, b = _history(out / "history.jsonl"), _history(tmp_path / "out_ref" / "history.jsonl")
    assert [d["iteration"] for d in a] == list(range(iterations + 1))
    Ja, Jb = np.array([d["objective"] for d in a]), np.array([d["objective"] for d in b])
    assert np.all(np.abs(Ja - Jb) <= 1e-10 * np.abs(Jb)), np.abs(Ja - Jb) / np.abs(Jb)
    qa, qb = np.array([d["q"] for d in a]), np.array([d["q"] for d in b])
    assert np.all(np.abs(qa - qb) <= 1e-10 * np.abs(qb))


def test_ctrl_c_stops_at_the_accepted_point_with_a_checkpoint(tmp_path):
    iterations = 30
    ckpt, out = tmp_path / "ckpt", tmp_path / "out"
    proc = _script(ckpt, out, iterations)
    _wait_for_records(proc, out, 3)
    proc.send_signal(signal.SIGINT)
    log = proc.communicate()[0].decode()
    assert proc.returncode == 0, log  # no PETSc error, no traceback: a result
    assert "interrupted" in log and "Traceback" not in log and "PETSc" not in log, log
    history = _history(out / "history.jsonl")
    stopped_at = len(history) - 1
    assert 2 <= stopped_at < iterations
    assert f"stopped after {stopped_at} iterations (interrupted)" in log, log
    resumed = _script(ckpt, out, stopped_at + 1)  # the checkpoint resumes where it stopped
    log = resumed.communicate()[0].decode()
    assert resumed.returncode == 0, log
    assert int(log.split("resumed_from=")[1].split()[0]) == stopped_at
