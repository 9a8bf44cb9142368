"""Target-trajectory benchmark: what matching a stored run at every step costs.

The paper's puzzle (fig14, 30 steps) and kangaroo (fig20, 60 steps) match the deformed surface
to a target run node by node at every step. ``target_trajectory`` holds the N + 1 target states
as Functions of one form, picked by the step's time, so its kernels read N + 1 coefficients. On
a 2D Neo-Hookean bar (P1, clamped at x = 0, under gravity; a target run with 1.2 x E) we time,
with a warm JIT cache (each form compiled by an untimed first run): the forward run, the
gradient with respect to a log E field and the per-state objective evaluation (series_values),
for the target trajectory and for a fixed target of the same surface (target_positions), and
report the ratios; the set-up (form compilation) time of a cold run is reported too.

Run ``python tests/benchmarks/bench_target_trajectory.py`` (``--steps``, ``--cells``). The last
line printed is a JSON object.
"""

import argparse
import json
import os
import tempfile
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")


def _parse():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=60, help="BDF1 steps (kangaroo: 60)")
    p.add_argument("--cells", type=int, nargs=2, default=[40, 8], help="cells along x and y")
    p.add_argument("--cold", action="store_true", help="compile into an empty FFCx cache")
    return p.parse_args()


def main() -> None:
    args = _parse()
    if args.cold:
        os.environ["XDG_CACHE_HOME"] = tempfile.mkdtemp()
    import numpy as np
    from mpi4py import MPI

    import diffsolids as ds
    from diffsolids.controls import ParameterControl
    from diffsolids.mesh import create_rectangle
    from diffsolids.objectives import (
        series_values,
        target_positions,
        target_trajectory,
        time_integral,
    )
    from diffsolids.reduced_functional import ReducedFunctional

    comm = MPI.COMM_WORLD
    domain = create_rectangle(
        comm,
        [[0, 0], [4, 0.5]],
        args.cells,
        facets={1: lambda x: np.isclose(x[0], 0.0), 2: lambda x: np.isclose(x[1], 0.5)},
    )
    model = ds.Model(domain, ds.NeoHookean(E=2e4, nu=0.3, density=10.0))
    model.add_gravity(9.81)
    model.add_dirichlet(1, 0.0)
    sim = ds.Simulation(model, ds.BDF(1, 0.01, args.steps), ds.SolverOptions(rtol=1e-10))
    control = ParameterControl(model, "E", "field", log=True)
    E = model.coefficients["E"]
    saved = E.x.array.copy()
    E.x.array[:] *= 1.2
    t0 = time.perf_counter()
    run = sim.run()
    target = type(run)(list(run.times), [u.copy() for u in run.u], [v.copy() for v in run.v])
    target_seconds = time.perf_counter() - t0
    E.x.array[:] = saved

    objectives = {
        "trajectory": target_trajectory(sim, target, facets=[2]),
        "fixed": target_positions(model, lambda x: x[:2] + np.array([[0.0], [-0.05]]), facets=2),
    }
    out = {"steps": args.steps, "dofs": model.V.dofmap.index_map.size_global * 2}
    out["target_run_s"] = target_seconds
    for name, series in objectives.items():
        t0 = time.perf_counter()
        rf = ReducedFunctional(sim, 10.0 * time_integral(series, "uniform"), [control])
        q = rf.initial_parameters()
        rf.value_and_gradient(q)  # compiles every form
        setup = time.perf_counter() - t0
        best = {"forward": np.inf, "gradient": np.inf, "values": np.inf}
        for _ in range(2):
            t0 = time.perf_counter()
            rf.forward(q)
            best["forward"] = min(best["forward"], time.perf_counter() - t0)
            t0 = time.perf_counter()
            rf.derivative()
            best["gradient"] = min(best["gradient"], time.perf_counter() - t0)
            t0 = time.perf_counter()
            series_values(sim, series, rf.trajectory)
            best["values"] = min(best["values"], time.perf_counter() - t0)
        out[f"{name}_setup_s"] = setup
        for key, value in best.items():
            out[f"{name}_{key}_s"] = value
    for key in ("forward", "gradient", "values"):
        out[f"{key}_ratio"] = out[f"trajectory_{key}_s"] / out[f"fixed_{key}_s"]
    if comm.rank == 0:
        for key, value in out.items():
            print(f"{key:>24}: {value:.4g}" if isinstance(value, float) else f"{key:>24}: {value}")
        from diffsolids.parallel import peak_rss_mb

        out["peak_rss_mb"] = peak_rss_mb()  # this process's
        print(json.dumps(out))


if __name__ == "__main__":
    main()
