"""Run every optimisation demo at its default size, check its outcome and print a table.

``make demos`` calls this script. A demo is a file ``demos/<name>.py`` that defines
``main(argv=None, ...)``; the forward demo ``beam_swing`` and the plumbing modules are skipped.
Each demo runs in its own subprocess as ``python demos/<name>.py --check --out
output/demos/<name>`` (or under ``mpiexec -n N`` with ``--np N``); its ``result.json`` gives the
row of the table. The exit code is 1 when any demo crashed, wrote no result or missed one of
its stated outcomes.

Examples:
    ``python demos/run_all.py`` (all demos), ``python demos/run_all.py bridge_stress --tiny``,
    ``python demos/run_all.py --np 2 --list``.
"""

import argparse
import ast
import json
import os
import subprocess
import sys
import time
from pathlib import Path

DEMOS = Path(__file__).resolve().parent
ROOT = DEMOS.parent
# forward demos and modules that are not demos
SKIP = {"beam_swing", "common", "run_all", "check_gradients", "shape_tools"}

__all__ = ["discover", "main", "run_one"]


def defines_main(path: Path) -> bool:
    """Whether a script defines a top-level ``main`` (read with ast, not imported)."""
    try:
        tree = ast.parse(path.read_text(), filename=str(path))
    except SyntaxError:
        return True  # let the run report the error
    return any(isinstance(n, ast.FunctionDef) and n.name == "main" for n in tree.body)


def discover(names: list[str] | None = None, directory: Path = DEMOS) -> list[str]:
    """Names of the demos to run (all optimisation demos, or the requested ones that exist)."""
    found = sorted(
        p.stem
        for p in directory.glob("*.py")
        if p.stem not in SKIP and not p.stem.startswith("_") and defines_main(p)
    )
    if not names:
        return found
    missing = [n for n in names if n not in found]
    if missing:
        raise SystemExit(f"run_all: no demo named {', '.join(missing)} (found: {', '.join(found)})")
    return [n for n in found if n in names]


def run_one(
    name: str, out: Path, extra: list[str], ranks: int, timeout: float, directory: Path = DEMOS
) -> dict:
    """Run one demo in a subprocess; returns a row of the table."""
    out.mkdir(parents=True, exist_ok=True)
    result = out / "result.json"
    result.unlink(missing_ok=True)  # never report a stale result
    cmd = [sys.executable, str(directory / f"{name}.py"), "--check", "--out", str(out)]
    if ranks > 1:
        mpiexec = Path(sys.executable).with_name("mpiexec")
        cmd = [str(mpiexec if mpiexec.exists() else "mpiexec"), "-n", str(ranks), *cmd]
    cmd += extra
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    t0 = time.perf_counter()
    cpu0 = os.times()
    log = out / "run.log"
    try:
        with log.open("w") as f:
            proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env=env, timeout=timeout)
        code = proc.returncode
    except subprocess.TimeoutExpired:
        code = "timeout"
    cpu1 = os.times()
    row = {
        "demo": name,
        "code": code,
        "wall": time.perf_counter() - t0,
        "cpu": (cpu1.children_user - cpu0.children_user)
        + (cpu1.children_system - cpu0.children_system),
        "log": str(log),
    }
    if result.exists():
        row["result"] = json.loads(result.read_text())
    return row


def status(row: dict) -> str:
    """ok, FAIL (an outcome missed), CRASH (no result or a non-zero exit without one)."""
    res = row.get("result")
    if res is None or row["code"] == "timeout":
        return "CRASH"
    outcomes = res.get("outcomes", [])
    if any(not o["passed"] for o in outcomes):
        return "FAIL"
    if row["code"] != 0 or not outcomes:
        return "CRASH"
    return "ok"


# the table's columns: title, alignment and width, format of a number (values "-" when missing)
TITLES = ("demo", "status", "J initial", "J final", "its", "fwd/it", "grad/it", "wall", "cpu")
WIDTHS = ("<22", "<6", ">11", ">11", ">4", ">7", ">7", ">7", ">7")
FORMATS = ("s", "s", ".4e", ".4e", "d", ".2f", ".2f", ".1f", ".1f")
# the numbers of result.json in the columns from "J initial" to "grad/it"
RESULT_KEYS = (
    "initial_objective",
    "final_objective",
    "iterations",
    "forward_seconds",
    "gradient_seconds",
)


def _cell(value, width: str, fmt: str) -> str:
    """One cell: a number (or text) in its column's format, "-" when it is missing."""
    if fmt != "s" and not isinstance(value, int | float):
        return f"{'-':{width}}"
    return format(value, width + fmt)


def table(rows: list[dict]) -> str:
    """The summary table."""
    header = " ".join(f"{t:{w}}" for t, w in zip(TITLES, WIDTHS, strict=True)) + "  outcomes"
    lines = [header, "-" * len(header)]
    for row in rows:
        res = row.get("result") or {}
        outcome = "; ".join(
            f"{o['name']} {o['value']:.4g} ({'ok' if o['passed'] else 'FAIL'})"
            for o in res.get("outcomes", [])
        )
        if not res:
            outcome = f"exit {row['code']}, see {row['log']}"
        values = [row["demo"], status(row), *(res.get(k) for k in RESULT_KEYS)]
        values += [row["wall"], row["cpu"]]
        cells = (_cell(*c) for c in zip(values, WIDTHS, FORMATS, strict=True))
        lines.append(" ".join(cells) + f"  {outcome}")
    return "\n".join(lines)


def main(argv=None) -> int:
    """Run the demos; returns the exit code."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("names", nargs="*", help="demos to run (default: all)")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--tiny", action="store_true", help="smoke-test size")
    size.add_argument("--full", action="store_true", help="paper-like resolution")
    p.add_argument("--np", type=int, default=1, help="MPI ranks per demo (default 1)")
    p.add_argument("--out", type=Path, default=ROOT / "output" / "demos", help="output root")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds per demo")
    p.add_argument("--list", action="store_true", help="only list the demos")
    p.add_argument("--demos-dir", type=Path, default=DEMOS, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    names = discover(args.names, args.demos_dir)
    if args.list:
        print("\n".join(names))
        return 0
    if not names:
        print("run_all: no optimisation demos found")
        return 0
    extra = ["--tiny"] if args.tiny else (["--full"] if args.full else [])
    rows = []
    for name in names:
        print(f"run_all: {name} ...", flush=True)
        row = run_one(name, args.out / name, extra, args.np, args.timeout, args.demos_dir)
        print(f"run_all: {name}: {status(row)} in {row['wall']:.1f} s", flush=True)
        rows.append(row)
    print()
    print(table(rows))
    failed = [r["demo"] for r in rows if status(r) != "ok"]
    if failed:
        print(f"\nrun_all: {len(failed)} of {len(rows)} demos failed: {', '.join(failed)}")
        return 1
    print(f"\nrun_all: all {len(rows)} demos achieved their outcomes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
