"""The initial Newton guess of a step (SolverOptions.initial_guess, read by the Simulation).

Every choice converges to the same states (to the Newton tolerance, here an absolute residual
tolerance, the same for all of them); the predictor u^{i-1} + dt v^{i-1} (TimeStep.extrapolation)
saves Newton iterations on a smooth dynamic scene, a spinning throw of a free body.
"""

import numpy as np
import pytest
from mpi4py import MPI

import diffsolids as ds

CHOICES = ("predictor", "previous", "zero")
ATOL = 1e-9  # the same absolute residual tolerance (N) for every guess


def _spinning_throw(comm: MPI.Comm) -> ds.Model:
    dom = ds.mesh.create_rectangle(comm, [[0, 0], [1, 0.2]], [10, 2])
    model = ds.Model(dom, ds.NeoHookean(E=1e4, nu=0.3, density=10.0))
    model.add_gravity(9.81)
    return model


def _spin(x: np.ndarray) -> np.ndarray:
    """Translation (1, 0.5) and angular velocity 4 about the strip's centre."""
    return np.stack([1.0 - 4.0 * (x[1] - 0.1), 0.5 + 4.0 * (x[0] - 0.5)])


def _run(model: ds.Model, integ: ds.Integrator, choice: str, **kwargs) -> ds.Trajectory:
    options = ds.SolverOptions(rtol=0.0, atol=ATOL, initial_guess=choice)
    return ds.Simulation(model, integ, options, progress=False, **kwargs).run()


def _max(comm: MPI.Comm, a: np.ndarray) -> float:
    return comm.allreduce(float(np.abs(a).max(initial=0.0)), op=MPI.MAX)


@pytest.fixture(scope="module")
def throws() -> tuple[MPI.Comm, dict[str, ds.Trajectory]]:
    model = _spinning_throw(MPI.COMM_WORLD)
    runs = {c: _run(model, ds.BDF(2, 0.04, 15), c, v0=_spin) for c in CHOICES}
    return model.domain.comm, runs


def test_every_guess_converges_to_the_same_states(throws):
    comm, runs = throws
    ref = runs["predictor"]
    u_scale = max(_max(comm, u) for u in ref.u)
    v_scale = max(_max(comm, v) for v in ref.v)
    assert u_scale > 1.0 and v_scale > 1.0  # the body moves by its length and spins
    for choice in ("previous", "zero"):
        traj = runs[choice]
        assert all(r.residual <= ATOL for r in traj.records)
        du = max(_max(comm, a - b) for a, b in zip(traj.u, ref.u, strict=True))
        dv = max(_max(comm, a - b) for a, b in zip(traj.v, ref.v, strict=True))
        assert du <= 1e-10 * u_scale, (choice, du)
        assert dv <= 1e-10 * v_scale, (choice, dv)


def test_the_predictor_saves_newton_iterations(throws):
    _, runs = throws
    counts = {c: runs[c].newton_iterations() for c in CHOICES}
    print("Newton iterations of 15 BDF2 steps:", counts)  # measured: 48, 74, 151
    assert counts["predictor"] < 0.8 * counts["previous"] < counts["zero"]
    # from the start the body has moved dt v: the predictor starts closer in every step
    per_step = zip(runs["predictor"].records, runs["previous"].records, strict=True)
    assert all(p.iterations <= q.iterations for p, q in per_step)


def test_static_load_steps_reach_the_same_states_from_every_guess():
    dom = ds.mesh.create_rectangle(
        MPI.COMM_WORLD, [[0, 0], [2, 0.2]], [10, 2], facets={1: lambda x: np.isclose(x[0], 0)}
    )
    model = ds.Model(dom, ds.NeoHookean(E=1e4, nu=0.3, density=10.0))
    model.add_body_force(lambda t: np.array([0.0, -9.81 * t]))  # ramped load steps
    model.add_dirichlet(1, 0.0)
    runs = {c: _run(model, ds.Static(3, 1.0 / 3.0), c) for c in CHOICES}
    comm = model.domain.comm
    scale = _max(comm, runs["predictor"].u[-1])
    assert scale > 0.01
    for choice in ("previous", "zero"):
        pairs = zip(runs[choice].u, runs["predictor"].u, strict=True)
        du = max(_max(comm, a - b) for a, b in pairs)
        assert du <= 1e-10 * scale, (choice, du)
    # a static step has no velocity: "predictor" is the previous state
    assert runs["predictor"].newton_iterations() == runs["previous"].newton_iterations()


def test_a_guess_changed_to_an_unknown_value_is_refused():
    model = _spinning_throw(MPI.COMM_WORLD)
    options = ds.SolverOptions()
    sim = ds.Simulation(model, ds.BDF(1, 0.04, 1), options, progress=False)
    options.initial_guess = "extrapolated"
    with pytest.raises(ds.ParameterError, match="initial_guess = 'extrapolated'"):
        sim.run()
