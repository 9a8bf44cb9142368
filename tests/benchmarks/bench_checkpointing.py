"""Checkpointing benchmark: memory and gradient time against the number of checkpoints.

A damped Neo-Hookean two-body bar in 2D (``--cells``, P1, BDF2, ``--steps`` steps, clamped at
one end, under gravity and an end traction; controls: three shape modes and E per body;
objective: a time-integrated target displacement plus the final kinetic energy). For each
policy (every state in memory; Revolve with 32, 8 and 2 checkpoints in memory; every state on
disk) one forward and one gradient are timed, then repeated under ``tracemalloc`` for memory:

* ``python_peak_mb``: tracemalloc's peak of Python-side allocations (numpy arrays: the states,
  checkpoints, adjoint vectors) during forward + gradient, above what was allocated before;
* ``factor_peak_mb``: the most memory of stored MUMPS factorisations held at once (MUMPS'
  own report; tracemalloc does not see PETSc allocations);
* ``peak_states``: states held at once (checkpoints, working states, adjoint dependencies);
* ``recomputed_steps`` and the gradient time (gradient = sweep incl. recomputations).

Every gradient is compared with the all-in-memory one (``max_rel_diff``). Serial only. Run
``python tests/benchmarks/bench_checkpointing.py``; the last line printed is a JSON object.
"""

import argparse
import json
import os
import time
import tracemalloc

os.environ.setdefault("OMP_NUM_THREADS", "1")


def _parse():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cells", type=int, nargs=2, default=[40, 10])
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--dt", type=float, default=0.01)
    p.add_argument("--snaps", type=int, nargs="*", default=[32, 8, 2])
    p.add_argument("--no-memory-run", action="store_true", help="skip the tracemalloc runs")
    return p.parse_args()


def _problem(args):
    import numpy as np
    from mpi4py import MPI

    import diffsolids as ds
    from diffsolids.controls import ParameterControl, ShapeControl
    from diffsolids.mesh import create_rectangle
    from diffsolids.objectives import Integral, final_value, target_displacement, time_integral

    length = 2.0
    dom = create_rectangle(
        MPI.COMM_SELF,
        [[0, 0], [length, 0.5]],
        args.cells,
        facets={1: lambda x: np.isclose(x[0], 0.0), 2: lambda x: np.isclose(x[0], length)},
        bodies={2: lambda x: x[0] > length / 2},
    )
    damping = {"damping_psi": 0.4, "damping_phi": 0.2}
    materials = {
        1: ds.NeoHookean(E=300.0, nu=0.3, density=1.0, **damping),
        2: ds.NeoHookean(E=480.0, nu=0.35, density=1.5, **damping),
    }
    model = ds.Model(dom, materials)
    model.add_body_force(np.array([0.0, -4.0]), name="gravity")
    model.add_traction(2, np.array([2.0, -6.0]))
    model.add_dirichlet(1, 0.0)
    sim = ds.Simulation(
        model,
        ds.BDF(2, args.dt, args.steps),
        ds.SolverOptions(rtol=1e-12),
        v0=np.array([0.0, 0.3]),
        progress=False,
    )
    rho = model.coefficients["density"]
    objective = time_integral(
        target_displacement(model, np.array([0.0, -0.05]), facets=2), "trapezoidal"
    ) + 0.1 * final_value(Integral(lambda f: 0.5 * rho * (f.v[0] ** 2 + f.v[1] ** 2) * f.dx, "ke"))

    def controls():
        X = model.domain.mesh.geometry.x
        x = X[:, 0] / length
        import scipy.sparse as sp

        n = len(X)
        modes = np.zeros((n, 2, 3))
        modes[:, 0, 0] = 0.2 * x
        modes[:, 1, 1] = 0.2 * x**2
        modes[:, 1, 2] = 0.1 * np.sin(np.pi * x) * (X[:, 1] - 0.25)
        return [
            ShapeControl(model, linear_map=sp.csr_matrix(modes.reshape(2 * n, 3))),
            ParameterControl(model, "E", "bodies", log=True),
        ]

    return sim, objective, controls


def _run(sim, objective, controls, policy, memory: bool):
    """(J, g, forward s, gradient s, stats, factor peak MB, python peak MB)."""
    from diffsolids.reduced_functional import ReducedFunctional

    rf = ReducedFunctional(sim, objective, controls(), checkpointing=policy)
    store = rf.factor_store
    factor_peak = [0.0]
    if store is not None:
        keep = store.keep

        def tracked(step, snes):
            keep(step, snes)
            factor_peak[0] = max(factor_peak[0], store.used_mb)

        store.keep = tracked
    q = rf.initial_parameters()
    if memory:
        tracemalloc.start()
        base = tracemalloc.get_traced_memory()[0]
    t0 = time.perf_counter()
    J = rf.forward(q)
    t1 = time.perf_counter()
    g = rf.derivative()
    t2 = time.perf_counter()
    python_peak = None
    if memory:
        python_peak = (tracemalloc.get_traced_memory()[1] - base) / 2**20
        tracemalloc.stop()
    run = getattr(rf.trajectory, "run", None)
    stats = dict(run.stats) if run is not None else {"peak_states": sim.integrator.num_steps + 1}
    rf._close_run()
    return J, g, t1 - t0, t2 - t1, stats, factor_peak[0], python_peak


def main():
    args = _parse()
    import numpy as np

    import diffsolids  # noqa: F401  (MPI before DOLFINx)
    from diffsolids.adjoint.checkpointing import Checkpointing

    sim, objective, controls = _problem(args)
    policies = {"all": Checkpointing("all")}
    for s in args.snaps:
        policies[f"revolve_{s}"] = Checkpointing("memory", snaps=s)
    policies["disk"] = Checkpointing("disk")
    # compile every kernel once (not timed)
    _run(sim, objective, controls, Checkpointing("all"), memory=False)
    result = {
        "steps": args.steps,
        "dofs": len(sim.u0),
        "state_kb": 2 * 8 * len(sim.u0) / 1024,
        "memory_measure": "tracemalloc peak (Python/numpy) + MUMPS-reported factor MB",
        "policies": {},
    }
    g_ref = None
    for name, policy in policies.items():
        J, g, t_fwd, t_grad, stats, factor_mb, _ = _run(
            sim, objective, controls, policy, memory=False
        )
        if g_ref is None:
            g_ref, J_ref = g, J
        row = {
            "forward_s": round(t_fwd, 3),
            "gradient_s": round(t_grad, 3),
            "gradient_over_forward": round(t_grad / t_fwd, 3),
            "recomputed_steps": stats.get("recomputed_steps", 0),
            "peak_states": stats.get("peak_states"),
            "factor_peak_mb": round(factor_mb, 3),
            "max_rel_diff": float(np.max(np.abs(g - g_ref)) / np.max(np.abs(g_ref))),
            "J_equal": bool(J_ref == J),
        }
        if not args.no_memory_run:
            *_, python_mb = _run(sim, objective, controls, policy, memory=True)
            row["python_peak_mb"] = round(python_mb, 3)
        result["policies"][name] = row
        print(name, json.dumps(row), flush=True)
    from diffsolids.parallel import peak_rss_mb

    result["peak_rss_mb"] = peak_rss_mb()  # this process's
    print(json.dumps(result))


if __name__ == "__main__":
    main()
