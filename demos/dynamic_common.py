"""Helpers of the transient contact demos (throw, sliding friction, puzzle, shock protection).

A contact term with the suggested barrier stiffness, deformed centres of mass per state, the
invariants every run checks (no inverted element and no intersection in any reported state),
trajectory output, an optimiser stop condition that keeps the accepted trajectories, and the
closing figures and summary line every run prints.
"""

import time

import numpy as np
from common import finish
from dolfinx import fem
from mpi4py import MPI

from diffsolids.contact import ContactTerm, suggest_barrier_stiffness
from diffsolids.errors import IntersectionError
from diffsolids.io import TrajectoryWriter
from diffsolids.parallel import collective_comm

__all__ = [
    "CentreOfMass",
    "TrajectoryKeeper",
    "add_contact",
    "body_nodes",
    "check_invariants",
    "check_states",
    "finish_transient",
    "write_states",
]


def add_contact(model, integrator, dhat: float, **kwargs) -> ContactTerm:
    """A ContactTerm with the barrier stiffness of ``suggest_barrier_stiffness``, in the model."""
    probe = ContactTerm(model, dhat=dhat, stiffness=1.0, **kwargs)
    kappa = suggest_barrier_stiffness(probe, integrator)
    contact = ContactTerm(model, dhat=dhat, stiffness=kappa, **kwargs)
    model.add_numeric_term(contact)
    return contact


def body_nodes(model, body) -> np.ndarray:
    """Local nodes (block indices of the displacement space) of the cells of a body."""
    return np.unique(model.V.dofmap.list[model.domain.cells_of(body)])


class CentreOfMass:
    """Deformed centres of mass of bodies, per state (forms compiled once)."""

    def __init__(self, model, bodies):
        self.model = model
        f = model.fields
        rho = model.coefficients["density"]
        self.forms = {}
        for body in bodies:
            dx = f.dx(model.domain.body_id(body))
            mass = fem.form(rho * dx)
            moments = [fem.form(rho * (f.X[k] + f.u[k]) * dx) for k in range(model.dim)]
            self.forms[body] = (mass, moments)

    def path(self, body, states) -> np.ndarray:
        """(len(states), dim) centres of mass of ``body`` for displacement arrays (collective)."""
        comm = self.model.domain.comm
        u = self.model.fields.u
        saved = u.x.array.copy()
        mass, moments = self.forms[body]
        out = []
        for state in states:
            u.x.array[:] = state
            m = collective_comm(comm).allreduce(fem.assemble_scalar(mass), op=MPI.SUM)
            out.append(
                [
                    collective_comm(comm).allreduce(fem.assemble_scalar(f), op=MPI.SUM) / m
                    for f in moments
                ]
            )
        u.x.array[:] = saved
        return np.array(out)


def check_states(sim, contact, trajectories) -> tuple[int, int, float]:
    """States with an inverted element, intersecting states and the smallest gap (collective).

    Every state of every given trajectory is checked: det F > 0 at the quadrature points (the
    solver's inversion guard) and no intersection of the collision surface (ipctk).
    """
    u = sim.model.fields.u
    saved = u.x.array.copy()
    inverted = intersecting = 0
    gap = np.inf
    for traj in trajectories:
        for i, state in enumerate(traj.u):
            u.x.array[:] = state
            inverted += int(sim.solver.inverted())
            try:
                gap = min(gap, contact.check_configuration(contact.surface.gather(state), i))
            except IntersectionError:
                intersecting += 1
    u.x.array[:] = saved
    return inverted, intersecting, float(gap)


def check_invariants(report, inverted: int, intersecting: int, gap: float) -> None:
    """Add the checks every run makes: objective decreased, no inverted element, no intersection.

    ``inverted``, ``intersecting`` and ``gap`` are the counts of :func:`check_states`.
    """
    report.check(
        "objective decreased",
        report.final_objective,
        report.initial_objective,
        report.final_objective < report.initial_objective,
    )
    report.check("no inverted element", inverted, 0, inverted == 0, "(states with one)")
    report.check(
        "no intersection",
        intersecting,
        0,
        intersecting == 0,
        f"(intersecting states; smallest gap {gap:.2e} m)",
    )


def write_states(model, traj, path) -> None:
    """Write a trajectory (u, v and von Mises stress per state) to VTX or XDMF."""
    with TrajectoryWriter(model, path) as writer:
        for t, u, v in zip(traj.times, traj.u, traj.v, strict=True):
            writer.write(t, u, v)


class TrajectoryKeeper:
    """An optimiser stop condition keeping the trajectories of the first and last iterates.

    ``minimize(..., stop_conditions=[keeper])``; ``keeper.first`` and ``keeper.last`` are the
    trajectories of the initial and the final iterate (no extra forward solve). With ``stop``,
    a callable ``stop(trajectory) -> bool`` ends the run when it returns True (collective); the
    optimiser then reports the reason "user: <name>".
    """

    def __init__(self, stop=None, name: str = "stop"):
        self.first = None
        self.last = None
        self.stop = stop
        self.name = name

    def __call__(self, record, optimizer) -> str | bool:
        """Keep the accepted trajectory; stop (returning the name) when ``stop`` says so."""
        traj = optimizer.point.trajectory
        if self.first is None:
            self.first = traj
        self.last = traj
        return self.name if self.stop is not None and self.stop(traj) else False


def finish_transient(report, args, comm, model, result, times, files, figures, headline):
    """Record a transient demo's figures, write ``result.json`` and print its summary line.

    Args:
        report: The DemoReport.
        args: Parsed arguments (``steps``, ``dt``, ``out``).
        comm: Communicator of the run.
        model: The Model (its dof count).
        result: The OptimizationResult.
        times: (wall-clock start, CPU start) of the run.
        files: Files the run wrote.
        figures: The demo's own figures for ``report.extra``.
        headline: The demo's part of the summary line (the run's size and cost follow).
    """
    t0, cpu0 = times
    cpu = collective_comm(comm).allreduce(time.process_time() - cpu0, op=MPI.SUM)
    dofs = model.V.dofmap.index_map.size_global * model.dim
    report.extra.update(
        {"dofs": dofs, "ranks": comm.size, "steps": args.steps, "dt": args.dt, **figures}
    )
    report.extra.update(
        {
            "forward_solves": result.num_forward,
            "cpu_seconds_all_ranks": cpu,
            "files": [str(f) for f in files],
        }
    )
    report.wall_seconds = time.perf_counter() - t0
    finish(report, args, comm)
    if comm.rank == 0:
        print(
            f"{headline}; {dofs} dofs, {args.steps} steps, {result.num_forward} forward solves; "
            f"CPU {cpu:.1f} s (all ranks)",
            flush=True,
        )
    return report
