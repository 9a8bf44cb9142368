"""Small optimisation problems for the optimiser tests, and a script running one of them.

Run as ``python tests/optimize_script.py --checkpoint DIR --output DIR [--iterations N]``: an
L-BFGS run of :func:`dynamic_problem` with checkpoints (the kill-and-resume test starts it,
kills it with SIGKILL and starts it again). Also importable (tests/ is on sys.path in pytest).
"""

import argparse
import sys

import numpy as np
import ufl
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import ParameterControl, ShapeControl
from diffsolids.mesh import create_rectangle
from diffsolids.objectives import Integral, final_value, time_integral
from diffsolids.reduced_functional import ReducedFunctional

E_TRUE = (2000.0, 500.0)
E_DYNAMIC = (300.0, 150.0)


def _bar(comm, n=(8, 2), bodies: int = 1):
    facets = {1: lambda x: np.isclose(x[0], 0.0), 2: lambda x: np.isclose(x[0], 4.0)}
    split = {2: lambda x: x[0] > 2.0} if bodies == 2 else None
    return create_rectangle(comm, [[0, 0], [4, 1]], list(n), facets=facets, bodies=split)


def bar_problem(comm=MPI.COMM_WORLD, bodies: int = 1, n=(8, 2), regularised: bool = False):
    """Static linear-elastic bar; recover its Young's moduli (log, per body) from a target.

    The target displacement is the solution with moduli ``E_TRUE[:bodies]``; the run starts
    from E = 1000 everywhere. Returns (rf, q_true).
    """
    from dolfinx import fem

    model = ds.Model(_bar(comm, n, bodies), ds.LinearElastic(E=1000.0, nu=0.3), degree=1)
    model.add_traction(2, [10.0, -2.0])
    model.add_dirichlet(1, 0.0)
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-12), progress=False)
    target = fem.Function(model.V)
    misfit = Integral(lambda f: ufl.inner(f.u - target, f.u - target) * f.dx, "misfit")
    objective = final_value(misfit)
    if regularised:
        energy = Integral(lambda f: ufl.inner(f.u, f.u) * f.dx, "u2")
        objective = objective + 1e-4 * final_value(energy)
    control = ParameterControl(model, "E", "bodies", log=True)
    rf = ReducedFunctional(sim, objective, control)
    q0 = rf.initial_parameters()
    q_true = np.log(np.array(E_TRUE[:bodies]))
    rf(q_true)
    target.x.array[:] = rf.trajectory.u[-1]
    rf.controls.assign(q0)
    return rf, q_true


def dynamic_problem(comm=MPI.COMM_WORLD):
    """Damped Neo-Hookean bar (BDF2, 8 steps) pulled down at its tip; recover two moduli.

    The objective is the misfit of the final state to the final state with moduli
    ``E_DYNAMIC`` plus a small time-integrated kinetic-energy-like term (two objective terms).
    Returns (rf, q_true).
    """
    from dolfinx import fem

    facets = {1: lambda x: np.isclose(x[0], 0.0), 2: lambda x: np.isclose(x[0], 2.0)}
    dom = create_rectangle(
        comm, [[0, 0], [2, 0.5]], [8, 2], facets=facets, bodies={2: lambda x: x[0] > 1.0}
    )
    material = ds.NeoHookean(E=200.0, nu=0.3, density=2.0, damping_psi=0.2)
    model = ds.Model(dom, material, degree=1)
    model.add_traction(2, [0.0, -12.0])
    model.add_dirichlet(1, 0.0)
    sim = ds.Simulation(model, ds.BDF(2, 0.05, 8), ds.SolverOptions(rtol=1e-11), progress=False)
    target = fem.Function(model.V)
    misfit = Integral(lambda f: ufl.inner(f.u - target, f.u - target) * f.dx, "misfit")
    motion = Integral(lambda f: ufl.inner(f.v, f.v) * f.dx, "v2")
    objective = final_value(misfit) + 1e-6 * time_integral(motion)
    rf = ReducedFunctional(sim, objective, ParameterControl(model, "E", "bodies", log=True))
    q0 = rf.initial_parameters()
    q_true = np.log(np.array(E_DYNAMIC))
    rf(q_true)
    target.x.array[:] = rf.trajectory.u[-1]
    rf.controls.assign(q0)
    return rf, q_true


def shape_problem(comm=MPI.COMM_WORLD, area_target: float = 0.3):
    """Shape of the top edge of a clamped, loaded block; drive its area to ``area_target``.

    Only the vertical positions of the top vertices are controls (a linear map); the rest
    area 4 x 1 can reach 0.3 only by folding the top row of cells through the row below, so
    long steps invert elements. Returns (rf, shape control).
    """
    import scipy.sparse as sp

    facets = {1: lambda x: np.isclose(x[0], 0.0)}
    dom = create_rectangle(comm, [[0, 0], [4, 1]], [8, 2], facets=facets)
    model = ds.Model(dom, ds.NeoHookean(E=1000.0, nu=0.3), degree=1)
    model.add_gravity(1.0)
    model.add_dirichlet(1, 0.0)
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-11), progress=False)
    # canonical vertex order = input order; select the top vertices (y = 1) on every rank
    mesh = dom.mesh
    x = mesh.geometry.x
    top_local = mesh.geometry.input_global_indices[np.isclose(x[:, 1], 1.0)]
    top = np.unique(np.concatenate(comm.allgather(top_local)))
    num_vertices = mesh.geometry.index_map().size_global
    rows = 2 * top + 1
    P = sp.csr_matrix(
        (np.ones(len(top)), (rows, np.arange(len(top)))), shape=(2 * num_vertices, len(top))
    )
    control = ShapeControl(model, linear_map=P)
    area = Integral(lambda f: 1.0 * f.dx, "area")
    sag = Integral(lambda f: ufl.inner(f.u, f.u) * f.dx, "u2")
    objective = (final_value(area) - area_target) ** 2 + final_value(sag)
    return ReducedFunctional(sim, objective, control), control


def contact_problem(comm=MPI.COMM_WORLD, gap: float = 0.1):
    """A block at rest above a thick slab (BDF1, IPC contact), its rest height the control.

    The objective, the block's final height, falls as the block is lowered towards the slab
    (the barrier pushes back only within dhat), so long steps move it into the slab: trial
    shapes that intersect or touch the slab are refused by the contact term with an
    IntersectionError. Returns (rf, contact term).
    """
    import scipy.sparse as sp

    from diffsolids.contact import ContactTerm
    from diffsolids.mesh.scene import combine_meshes, simplex_box

    slab = simplex_box([[0.0, -0.7], [1.0, 0.3]], [4, 4])
    block = simplex_box([[0.3137, 0.3 + gap], [0.7137, 0.6 + gap]], [2, 2])
    dom = combine_meshes(comm, [slab, block])
    model = ds.Model(dom, ds.NeoHookean(E=1e4, nu=0.3, density=10.0), degree=1)
    model.add_dirichlet(lambda x: np.isclose(x[1], -0.7), 0.0)
    contact = ContactTerm(model, dhat=0.02, stiffness=1e3)
    model.add_numeric_term(contact)
    sim = ds.Simulation(model, ds.BDF(1, 0.05, 4), ds.SolverOptions(rtol=1e-10), progress=False)
    mesh = dom.mesh
    upper = mesh.geometry.input_global_indices[mesh.geometry.x[:, 1] > 0.3 + 1e-9]
    upper = np.unique(np.concatenate(comm.allgather(upper)))
    n = mesh.geometry.index_map().size_global
    P = sp.csr_matrix(
        (np.ones(len(upper)), (2 * upper + 1, np.zeros(len(upper)))), shape=(2 * n, 1)
    )
    height = Integral(lambda f: (f.X[1] + f.u[1]) * f.dx(2), "height")
    rf = ReducedFunctional(sim, final_value(height), ShapeControl(model, linear_map=P))
    return rf, contact


def observed_run(rf, options, fail_above: float | None = None, **kwargs):
    """An L-BFGS run recording every forward trial and every ``on_accept`` call (collective).

    Two observers run per accepted iterate: ``first`` records the record, the optimiser's
    accepted q, the controls' q (what the model holds) and a collective (``allreduce`` of 1, so
    a call missing on one rank hangs), ``second`` its iteration; a stop condition records the
    observer calls it sees. With ``fail_above``, forward solves with a Young's modulus above
    it raise NewtonConvergenceError (invalid trials). Returns (result, trials, calls).
    """
    from diffsolids.errors import NewtonConvergenceError
    from diffsolids.optimize import minimize

    comm = rf.comm
    trials, calls = [], []

    def forward(q):
        trials.append(np.array(q, dtype=float))
        if fail_above is not None and np.exp(np.max(q)) > fail_above:
            rf.controls.assign(q)
            raise NewtonConvergenceError(1, 50, 1.0, 1e-9, "DIVERGED_MAX_IT (test)")
        return type(rf).forward(rf, q)

    def first(rec, opt):
        everywhere = comm.allreduce(1, op=MPI.SUM) == comm.size
        calls.append(("first", rec, opt.point.q.copy(), rf.controls.value().copy(), everywhere))

    def second(rec, opt):
        calls.append(("second", rec.iteration))

    def stop(rec, opt):
        calls.append(("stop", rec.iteration))
        return False

    rf.forward = forward
    try:
        result = minimize(
            rf,
            rf.initial_parameters(),
            options,
            on_accept=[first, second],
            stop_conditions=[stop],
            write_parameters=True,
            plot_every=0,
            **kwargs,
        )
    finally:
        del rf.forward
    return result, trials, calls


def check_observed_run(result, trials, calls) -> None:
    """The observers of :func:`observed_run` ran once per accepted iterate, in order."""
    history = result.history
    n = len(history)
    # per accepted iterate: first, second (in the order given), then the stop condition
    kinds = [c[0] for c in calls]
    assert kinds == ["first", "second", "stop"] * n, kinds
    firsts = calls[0::3]
    assert all(c[1] is rec for c, rec in zip(firsts, history, strict=True))
    assert [c[1].iteration for c in firsts] == list(range(n))
    assert [c[1] for c in calls[1::3]] == list(range(n))
    for _, rec, q, held, everywhere in firsts:
        assert np.array_equal(q, rec.q) and np.array_equal(held, q)  # the model holds it
        assert everywhere  # called on every rank
    # rejected (Armijo or invalid) trials happened and none of them was observed
    assert len(trials) == sum(r.trials for r in history) + 1  # and the initial point
    accepted = {tuple(rec.q) for rec in history}
    rejected = {tuple(q) for q in trials} - accepted
    assert rejected, "the run should have rejected some trials"
    assert not rejected & {tuple(c[2]) for c in firsts}


def main(argv=None) -> int:
    """Run the dynamic problem with checkpoints (resuming if the directory has one)."""
    from diffsolids.optimize import LBFGSOptions, minimize

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--output", required=True)
    parser.add_argument("--iterations", type=int, default=10)
    args = parser.parse_args(argv)
    rf, _ = dynamic_problem(MPI.COMM_WORLD)
    options = LBFGSOptions(max_iterations=args.iterations, gradient_rtol=0.0)
    result = minimize(
        rf,
        options=options,
        checkpoint_dir=args.checkpoint,
        output_dir=args.output,
        write_parameters=True,
        plot_every=0,
    )
    print(result, flush=True)
    print(f"resumed_from={result.resumed_from}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
