"""Run under ``mpiexec -n 2``: the transient contact demos (tiny) on 2 ranks equal serial runs.

Each demo runs on COMM_WORLD and on COMM_SELF in the same process: the optimiser's objective
history (initial value, every accepted iterate) must agree to round-off, and the report's
invariants must hold in both runs.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from demo_modules import load_demo
from mpi4py import MPI

RTOL = 1e-7


def _history(out: Path) -> np.ndarray:
    lines = (out / "history.jsonl").read_text().splitlines()
    return np.array([json.loads(line)["objective"] for line in lines])


@pytest.mark.parametrize(
    "name", ["throw", "sliding_friction", "puzzle_initial_velocity", "shock_protection"]
)
def test_dynamic_demo_world_equals_self(name, tmp_path):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    root = Path(comm.bcast(str(tmp_path), root=0))
    main = load_demo(name).main
    histories = []
    for c, label in ((comm, "world"), (MPI.COMM_SELF, f"self{comm.rank}")):
        out = root / label
        report = main(["--tiny", "--out", str(out), "--no-plot"], comm=c)
        assert all(o.passed for o in report.outcomes), report.outcomes
        c.Barrier()
        histories.append(_history(out))
    par, ser = histories
    assert len(par) == len(ser) >= 2
    assert par[-1] < par[0]
    assert np.allclose(par, ser, rtol=RTOL, atol=0.0), (par, ser)
