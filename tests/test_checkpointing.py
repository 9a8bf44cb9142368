"""Time-step checkpointing of the adjoint: the gradient of the all-in-memory sweep, bit for bit.

Scenes: a damped Neo-Hookean two-body bar (BDF2, 30 steps; a shape control through three modes
and E per body) under an objective reading u, v and the BDF predictor; the incline block
sliding with friction 0.2 (BDF2, 8 steps; shape, damping and friction controls). Each policy
(Revolve with 1, 3 and N checkpoints, multistage, every state on disk, multistage on disk) must
give the value and gradient of ``Checkpointing("all")`` to 1e-12 (they agree exactly: the
recomputed Newton solves repeat the first forward's), recompute what its schedule says, and
hold fewer states. Central differences check the checkpointed gradient itself.
"""

import functools

import numpy as np
import pytest
from gradient_scenes import Scene, build_model, objective, shape_linear_map
from mpi4py import MPI
from test_gradients_contact import incline_scene

import diffsolids as ds
from diffsolids.adjoint import checkpointing as ckpt
from diffsolids.adjoint.checkpointing import (
    CheckpointedRun,
    Checkpointing,
    CheckpointingError,
    state_depth,
)
from diffsolids.controls import FrictionControl, ParameterControl, ShapeControl
from diffsolids.errors import ParameterError
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.verification import finite_difference_check

BEAM_STEPS = 30
CONTACT_STEPS = 8
RTOL = 1e-12


@functools.cache
def beam(comm=MPI.COMM_WORLD):
    """(simulation, objective, controls factory) of the damped bar, BDF2."""
    model = build_model(Scene(2, 1, "neo_hookean", True), comm)
    v0 = np.zeros(2)
    v0[-1] = 0.3
    sim = ds.Simulation(
        model, ds.BDF(2, 0.02, BEAM_STEPS), ds.SolverOptions(rtol=1e-13), v0=v0, progress=False
    )
    J = objective("target", model, True) + 0.1 * objective("u_tilde", model, True)

    def controls():
        return [
            ShapeControl(model, linear_map=shape_linear_map(model)),
            ParameterControl(model, "E", "bodies", log=True),
        ]

    return sim, J, controls


@functools.cache
def incline(comm=MPI.COMM_WORLD):
    model, contact, sim, J = incline_scene(1, 2, num_steps=CONTACT_STEPS, comm=comm)

    def controls():
        return [
            ShapeControl(model, "all"),
            ParameterControl(model, "damping_psi", "bodies"),
            FrictionControl(contact, pairs=[("slab", "block")]),
        ]

    return sim, J, controls, contact


def reduced_functional(scene, policy):
    sim, J, controls = scene[:3]
    return ReducedFunctional(sim, J, controls(), checkpointing=policy)


@functools.cache
def reference(name: str):
    """(q, J, g, contact records) of the all-in-memory run."""
    scene = beam() if name == "beam" else incline()
    rf = reduced_functional(scene, Checkpointing("all"))
    q = rf.initial_parameters()
    J, g = rf.value_and_gradient(q)
    assert getattr(rf.trajectory, "run", None) is None  # the plain Trajectory
    return q, J, g.copy(), _records(scene)


def _records(scene):
    if len(scene) < 4:
        return None
    return [(r.num_collisions, r.min_distance) for r in scene[3].records]


def _relative(a, b) -> float:
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


POLICIES = {
    "revolve-1": Checkpointing("memory", snaps=1),
    "revolve-3": Checkpointing("memory", snaps=3),
    "revolve-N": Checkpointing("memory", snaps=BEAM_STEPS),
    "multistage-4": Checkpointing("memory", snaps=4, schedule="multistage"),
    "disk": Checkpointing("disk"),
    "disk-3": Checkpointing("disk", snaps=3),
}


@pytest.mark.parametrize("name", list(POLICIES))
def test_beam_gradient_equals_all_in_memory(name, tmp_path):
    policy = POLICIES[name]
    if policy.policy == "disk":
        policy = Checkpointing("disk", snaps=policy.snaps, directory=tmp_path)
    q, J_ref, g_ref, _ = reference("beam")
    rf = reduced_functional(beam(), policy)
    J, g = rf.value_and_gradient(q)
    run = rf.trajectory.run
    assert pytest.approx(J_ref, rel=RTOL, abs=0) == J
    assert _relative(g, g_ref) <= RTOL
    depth = state_depth(rf.simulation)
    assert depth == 2
    stats = run.stats
    assert stats["forward_steps"] == BEAM_STEPS
    snaps = policy.snaps
    if policy.policy == "disk" and snaps is None:
        assert stats["recomputed_steps"] == 0
        assert stats["peak_states"] <= 2 * depth + 2  # working states, adjoint's, u^0, u^N
    else:
        assert stats["recomputed_steps"] > 0
        if snaps < BEAM_STEPS:
            assert stats["peak_states"] < BEAM_STEPS // 2
    if policy.policy == "disk":
        assert len(list(tmp_path.iterdir())) == 1  # one directory of this run's files
    if name in ("revolve-3", "disk"):
        # a second gradient (the schedule is spent, or its factors freed): the same again
        assert _relative(rf.derivative(), g_ref) <= RTOL
    rf.forward(q)  # the next forward frees the previous run's checkpoints
    assert run.closed
    if policy.policy == "disk":
        rf._close_run()
        assert list(tmp_path.iterdir()) == []


def test_without_factor_store_the_gradient_is_still_that_of_all_in_memory():
    """factor_memory_mb=0: the adjoint starts from step N's factors in both runs."""
    sim, J, controls = beam()
    ref = ReducedFunctional(sim, J, controls(), factor_memory_mb=0, checkpointing=None)
    q = ref.initial_parameters()
    assert ref.checkpointing.resolve(sim).policy == "all"  # auto, on a tiny run
    g_ref = ref.gradient(q)
    rf = ReducedFunctional(
        sim, J, controls(), factor_memory_mb=0, checkpointing=Checkpointing("memory", snaps=3)
    )
    assert rf.factor_store is None and sim.solver.factor_store is None
    assert _relative(rf.gradient(q), g_ref) <= RTOL
    assert _relative(rf.derivative(), g_ref) <= RTOL  # again: a new forward, the same factors


def test_beam_checkpointed_gradient_against_finite_differences():
    rf = reduced_functional(beam(), Checkpointing("memory", snaps=3))
    q = rf.initial_parameters()
    g = rf.gradient(q)
    rng = np.random.default_rng(3)
    d = rng.standard_normal(rf.size) * 0.02
    steps = np.array([1e-2])
    random = finite_difference_check(rf, q, d, steps, gradient=g)
    along = finite_difference_check(rf, q, 0.02 * g / np.linalg.norm(g), steps, gradient=g)
    for res in (random, along):
        assert abs(res.adjoint) > 0, str(res)
        assert res.relative_error <= 1e-6, str(res)


@pytest.mark.parametrize("name", ["revolve-1", "revolve-3", "revolve-N", "disk"])
def test_contact_friction_gradient_equals_all_in_memory(name, tmp_path):
    policy = POLICIES[name]
    if name == "revolve-N":
        policy = Checkpointing("memory", snaps=CONTACT_STEPS)
    elif name == "disk":
        policy = Checkpointing("disk", directory=tmp_path)
    q, J_ref, g_ref, records = reference("incline")
    scene = incline()
    rf = reduced_functional(scene, policy)
    J, g = rf.value_and_gradient(q)
    assert pytest.approx(J_ref, rel=RTOL, abs=0) == J
    assert _relative(g, g_ref) <= RTOL
    # the contact records are those of the first forward (recomputations record nothing);
    # two runs agree to round-off (ipctk's threaded sums), not bit for bit
    got = _records(scene)
    assert [n for n, _ in got] == [n for n, _ in records]
    assert np.allclose([d for _, d in got], [d for _, d in records], rtol=1e-12, atol=0)
    assert all(n > 0 for n, _ in records)
    assert np.abs(g[-1]) > 0  # the friction coefficient acts


def test_states_not_held_and_bad_policies():
    q, _, _, _ = reference("beam")
    rf = reduced_functional(beam(), Checkpointing("memory", snaps=2))
    rf.forward(q)
    traj = rf.trajectory
    assert traj.num_steps == BEAM_STEPS and len(traj.records) == BEAM_STEPS
    assert np.array_equal(traj.u[0], rf.simulation.u0)
    assert traj.u[BEAM_STEPS].shape == traj.u[0].shape
    with pytest.raises(CheckpointingError, match="state 5 is not held"):
        traj.u[5]
    for bad, match in [
        (dict(policy="bogus"), "unknown checkpointing policy"),
        (dict(policy="memory"), "needs a number of snaps"),
        (dict(policy="memory", snaps=0), "positive integer"),
        (dict(policy="memory", snaps=2, schedule="hrevolve?"), "unknown checkpointing schedule"),
        (dict(policy="all", snaps=3), "takes no snaps"),
    ]:
        with pytest.raises(ParameterError, match=match):
            Checkpointing(**bad)
    with pytest.raises(ParameterError, match="must be a Checkpointing"):
        ReducedFunctional(rf.simulation, rf.objective, rf.controls.controls, checkpointing="disk")
    run = CheckpointedRun(rf.simulation, Checkpointing("memory", snaps=2))
    with pytest.raises(CheckpointingError, match="no checkpointed forward"):
        run.reverse(lambda i, view: None)


def test_auto_keeps_a_small_run_in_memory_on_a_busy_node(monkeypatch):
    """A run whose states take <= 1% of the available memory is never checkpointed, even when
    the factor store claims all the spare memory (a busy node: available < its reserve)."""
    import diffsolids.solvers.factor_store as fs

    sim = beam()[0]
    state_mb = MPI.COMM_WORLD.allreduce(16 * len(sim.u0) / 2**20, op=MPI.MAX)
    node = MPI.COMM_WORLD.Split_type(MPI.COMM_TYPE_SHARED)
    ranks = node.size
    node.Free()
    run_mb = (BEAM_STEPS + 1) * state_mb * ranks
    with sim.solver.keeping_factors_in(fs.FactorStore()):
        for share, expected in ((0.009, "all"), (0.02, "memory")):
            available = run_mb / share
            monkeypatch.setattr(ckpt, "node_memory_mb", lambda a=available: (a, 5 * a))
            assert Checkpointing().resolve(sim).policy == expected, share


@pytest.mark.parametrize(("states", "expected"), [(1000, "all"), (10, "memory"), (3, "disk")])
def test_auto_policy_follows_available_memory(monkeypatch, states, expected):
    """The rule of Checkpointing: the states take half of what the factor store leaves."""
    import diffsolids.solvers.factor_store as fs

    sim = beam()[0]
    node = MPI.COMM_WORLD.Split_type(MPI.COMM_TYPE_SHARED)
    ranks = node.size
    node.Free()
    state_mb = MPI.COMM_WORLD.allreduce(16 * len(sim.u0) / 2**20, op=MPI.MAX)
    # room for `states` states (and a bit) per rank: half of the available memory
    available = 2 * ranks * state_mb * (states + 0.5)
    monkeypatch.setattr(ckpt, "node_memory_mb", lambda: (available, 4 * available))
    with sim.solver.keeping_factors_in(None):  # no store: nothing reserved for factorisations
        policy = Checkpointing().resolve(sim)
        assert policy.policy == expected
        if expected == "memory":
            assert policy.snaps == states // 2  # checkpoints of d = 2 states
    # a store keeping factors by spare memory leaves a quarter of the total to them: 0 spare
    # (4 x available total), so the states get the 1% of the available memory of any run
    with sim.solver.keeping_factors_in(fs.FactorStore()):
        floor = int(ckpt._SMALL_RUN_SHARE * available / ranks // state_mb)
        busy = "all" if floor >= BEAM_STEPS + 1 else "memory" if floor // 2 >= 2 else "disk"
        assert Checkpointing().resolve(sim).policy == busy
    monkeypatch.undo()
    assert ckpt.Checkpointing("auto").resolve(sim).policy == "all"  # this machine: tiny run
