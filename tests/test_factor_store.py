"""The forward factorisations kept for the adjoint: capped count, evenly thinned, exact gradients.

Every MUMPS instance holds MPI communicators; MPICH has 2048 per process and MUMPS corrupts memory
when they run out (after about 400 live instances: a 400-step trajectory whose every step kept
its factors crashed). The store keeps at most ``max_factors`` per store and ``max_live`` per
process; the adjoint stays exact with the factors of other steps as preconditioners.
"""

import gc
import weakref

import numpy as np
import pytest
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import ParameterControl
from diffsolids.mesh import create_rectangle
from diffsolids.objectives import target_displacement, time_integral
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.solvers.factor_store import FactorStore, factor_memory_mb
from diffsolids.verification import finite_difference_check

FD_TOLERANCE = 1e-6


def _reduced_functional(steps: int, nx: int = 4, comm=MPI.COMM_SELF) -> ReducedFunctional:
    """Neo-Hookean strip clamped on the left, swinging under gravity; control: log E per cell."""
    dom = create_rectangle(
        comm, [[0, 0], [2, 0.4]], [nx, 1], facets={1: lambda x: np.isclose(x[0], 0)}
    )
    model = ds.Model(dom, ds.NeoHookean(E=2e3, nu=0.3, density=10.0))
    model.add_dirichlet(1, 0.0)
    model.add_gravity(9.81)
    sim = ds.Simulation(model, ds.BDF(2, 0.02, steps), ds.SolverOptions(rtol=1e-12), progress=False)
    objective = time_integral(target_displacement(model, [0.0, -0.05]), "uniform")
    return ReducedFunctional(sim, objective, [ParameterControl(model, "E", "field", log=True)])


def _fd_errors(rf) -> list[float]:
    """Relative FD errors in a random direction and along the gradient."""
    q0 = rf.initial_parameters()
    g = rf.gradient(q0)
    d = np.random.default_rng(3).standard_normal(q0.size)
    steps = np.array([1e-3, 1e-4])
    errors = [
        finite_difference_check(rf, q0, 0.1 * d / np.linalg.norm(d), steps, gradient=g),
        finite_difference_check(rf, q0, 0.1 * g / np.linalg.norm(g), steps, gradient=g),
    ]
    rf.controls.assign(q0)
    return [e.relative_error for e in errors]


def test_store_thins_to_evenly_spaced_steps_and_gradient_stays_exact():
    rf = _reduced_functional(steps=13)
    store = rf.factor_store
    store.max_factors = 4
    rf.forward(rf.initial_parameters())
    kept = sorted(store.factors)
    assert 1 <= len(kept) <= 4
    assert store.stride == 4  # 13 steps through a cap of 4: strides 1 -> 2 -> 4
    assert all(step % store.stride == 0 for step in kept)
    for error in _fd_errors(rf):
        assert error <= FD_TOLERANCE


def test_the_sweep_reports_where_its_time_went():
    rf = _reduced_functional(steps=3)
    rf.gradient(rf.initial_parameters())
    stats = rf.adjoint_stats
    phases = stats["phase_seconds"]
    assert set(phases) == {"objective_state", "linear_solves", "history", "parameters", "other"}
    assert all(t >= 0.0 for t in phases.values())
    assert sum(phases.values()) == pytest.approx(stats["seconds"], rel=1e-12)
    assert stats["krylov_iterations"] == sum(stats["krylov_per_step"]) > 0


def test_process_wide_cap_holds_over_several_stores(monkeypatch):
    gc.collect()  # stores of earlier tests free their factors
    monkeypatch.setattr(FactorStore, "max_live", FactorStore._live + 3)
    rfs = [_reduced_functional(steps=8), _reduced_functional(steps=8, nx=5)]
    for rf in rfs:
        rf.forward(rf.initial_parameters())
        assert FactorStore._live <= FactorStore.max_live
    stores = [rf.factor_store for rf in rfs]
    assert sum(len(s.factors) for s in stores) <= 3
    for error in _fd_errors(rfs[1]):
        assert error <= FD_TOLERANCE


def test_a_long_trajectory_keeps_few_factorisations():
    # before the cap: 450 live MUMPS instances ran out of MPI communicators and crashed
    rf = _reduced_functional(steps=450, nx=2)
    rf.forward(rf.initial_parameters())
    store = rf.factor_store
    assert len(store.factors) <= store.max_factors
    assert FactorStore._live <= FactorStore.max_live
    g = rf.gradient(rf.initial_parameters())
    assert np.all(np.isfinite(g)) and np.linalg.norm(g) > 0


def test_solvers_are_freed_with_their_communicators():
    # PETSc callbacks held the solver (a cycle through C): MUMPS instances and MPI
    # communicators leaked with every solver until MPICH had none left
    def free_communicators() -> int:
        comms = []
        try:
            while len(comms) < 4096:
                comms.append(MPI.COMM_SELF.Dup())
        except MPI.Exception:
            pass
        for c in comms:
            c.Free()
        return len(comms)

    def solve_and_drop() -> None:
        rf = _reduced_functional(steps=4)
        rf.gradient(rf.initial_parameters())
        solver = weakref.ref(rf.simulation.solver)
        del rf
        gc.collect()
        assert solver() is None

    solve_and_drop()  # once-per-process communicators (e.g. collective_comm's) made here
    before = free_communicators()
    for _ in range(3):
        solve_and_drop()
    assert free_communicators() == before


def test_max_factors_must_be_positive():
    with pytest.raises(ValueError, match="max_factors"):
        FactorStore(max_factors=0)


@pytest.mark.parametrize(
    "kwargs", [{"budget_mb": -1.0}, {"reserve": 1.0}, {"reserve": -0.1}, {"node_share": 0.0}]
)
def test_memory_settings_are_checked(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        FactorStore(**kwargs)


def _fake_node(monkeypatch, rf, memory):
    """Replace the node's memory by ``memory(per_factor, store) -> (available, total)``."""
    import diffsolids.solvers.factor_store as factor_store

    store = rf.factor_store
    state = {"per_factor": None}

    def fake_memory():
        # at the first call (the first kept step) the SNES holds the factors of step 1
        if state["per_factor"] is None:
            ksp = rf.simulation.solver.snes.getKSP()
            state["per_factor"] = factor_memory_mb(ksp.getPC().getFactorMatrix())
        return memory(state["per_factor"], store)

    monkeypatch.setattr(factor_store, "node_memory_mb", fake_memory)
    return state


def test_default_store_keeps_the_factors_on_disk(tmp_path):
    """The default store writes MUMPS' factors out of core and the gradient stays exact."""
    rf = _reduced_functional(steps=6)
    default = rf.factor_store
    assert default.out_of_core and default.budget_mb is None
    store = rf.factor_store = FactorStore(directory=tmp_path)
    rf.forward(rf.initial_parameters())
    assert sorted(store.factors) == list(range(1, 7))
    files = list(tmp_path.iterdir())
    assert files  # each kept factorisation's files
    assert store.node_claim_mb(1000.0, 2000.0, 1) == 0.0  # no memory claimed
    assert 0 < store.used_mb <= store.run_budget_mb
    for error in _fd_errors(rf):
        assert error <= FD_TOLERANCE
    store.clear()
    gc.collect()
    assert len(list(tmp_path.iterdir())) < len(files)


def test_out_of_core_directory_must_be_writable(tmp_path):
    with pytest.raises(ValueError, match="not writable"):
        FactorStore(directory=tmp_path / "missing")


def test_default_budget_is_a_share_of_the_available_memory(monkeypatch):
    """Without a budget, factors in memory take at most node_share of the available memory."""
    rf = _reduced_functional(steps=10)
    store = rf.factor_store = FactorStore(out_of_core=False)
    assert store.budget_mb is None and store.node_share == 0.1
    # a node with 35 factorisations available: 3.5 of them are the store's share
    state = _fake_node(monkeypatch, rf, lambda pf, store: (35.0 * pf, 40.0 * pf))
    rf.forward(rf.initial_parameters())
    per_factor = state["per_factor"]
    assert store.run_budget_mb == pytest.approx(3.5 * per_factor)
    assert store.used_mb <= store.run_budget_mb
    kept = sorted(store.factors)
    # 10 steps into room for 3: thinned to stride 4, not the first three steps
    assert store.stride == 4 and kept == [4, 8]
    for error in _fd_errors(rf):
        assert error <= FD_TOLERANCE


def test_default_budget_keeps_the_reserve_available(monkeypatch):
    """Memory taken by others lowers what the store keeps: never below the node's reserve."""
    rf = _reduced_functional(steps=10)
    store = rf.factor_store = FactorStore(out_of_core=False)
    # the node's available memory shrinks by what the store keeps, starting 1.5 factorisations
    # above the reserve (25 % of the total); the share (10 % of 1000 MB) is no limit
    _fake_node(monkeypatch, rf, lambda pf, store: (250.0 + 1.5 * pf - store.used_mb, 1000.0))
    rf.forward(rf.initial_parameters())
    # each new factorisation leaves room for one: thinned down to the last multiple of 8
    assert sorted(store.factors) == [8] and store.stride == 8
    for error in _fd_errors(rf):
        assert error <= FD_TOLERANCE


def test_a_container_limit_lowers_the_node_memory(tmp_path):
    """Inside a container /proc/meminfo shows the host: the cgroup's limit must win."""
    from diffsolids.solvers.factor_store import node_memory_mb

    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:       65536000 kB\nMemAvailable:   60000000 kB\n")
    host = node_memory_mb(meminfo, tmp_path / "no-cgroup")
    assert host == pytest.approx((60000000 / 1024, 65536000 / 1024))
    v2 = tmp_path / "v2"
    v2.mkdir()
    (v2 / "memory.max").write_text(f"{4 * 2**30}\n")
    (v2 / "memory.current").write_text(f"{3 * 2**30}\n")
    (v2 / "memory.stat").write_text(f"anon 1\ninactive_file {2**29}\n")
    assert node_memory_mb(meminfo, v2) == pytest.approx((1536.0, 4096.0))
    (v2 / "memory.max").write_text("max\n")
    assert node_memory_mb(meminfo, v2) == pytest.approx(host)
    v1 = tmp_path / "v1" / "memory"
    v1.mkdir(parents=True)
    (v1 / "memory.limit_in_bytes").write_text(f"{2 * 2**30}\n")
    (v1 / "memory.usage_in_bytes").write_text(f"{2**30}\n")
    (v1 / "memory.stat").write_text("total_inactive_file 0\n")
    assert node_memory_mb(meminfo, v1.parent) == pytest.approx((1024.0, 2048.0))
    (v1 / "memory.limit_in_bytes").write_text("9223372036854771712\n")  # v1's "no limit"
    assert node_memory_mb(meminfo, v1.parent) == pytest.approx(host)


def test_a_functional_keeps_its_factor_store_to_itself(tmp_path):
    """Creating a ReducedFunctional leaves the solver alone; its store is the solver's only
    while it runs, so two functionals of one simulation keep their own factorisations."""
    first = _reduced_functional(steps=4)
    sim = first.simulation
    assert sim.solver.factor_store is None and first.factor_store is not None
    second = ReducedFunctional(
        sim, first.objective, first.controls.controls, factor_store=FactorStore(directory=tmp_path)
    )
    q = first.initial_parameters()
    g_first = first.gradient(q)
    assert sim.solver.factor_store is None
    assert sorted(first.factor_store.factors) == [1, 2, 3, 4]
    second.forward(q)
    assert sorted(second.factor_store.factors) == [1, 2, 3, 4]
    assert sorted(first.factor_store.factors) == [1, 2, 3, 4]  # untouched by the other's run
    kept = dict(second.factor_store.factors)
    sim.run()  # a plain run keeps nothing
    assert second.factor_store.factors == kept
    np.testing.assert_allclose(second.derivative(), g_first, rtol=1e-8)
    for error in _fd_errors(second):
        assert error <= FD_TOLERANCE


def test_factor_store_argument_is_checked():
    rf = _reduced_functional(steps=2)
    for bad in ({"factor_store": "disk"}, {"factor_store": FactorStore(), "factor_memory_mb": 10}):
        with pytest.raises(ds.ParameterError, match="factor_store must be a FactorStore"):
            ReducedFunctional(rf.simulation, rf.objective, rf.controls.controls, **bad)


def test_keeping_factors_in_puts_the_previous_store_back(tmp_path):
    """The solver's factor store is set for a block only; the block's end (also by an error)
    restores the previous one, and assigning it directly warns that it is deprecated."""
    rf = _reduced_functional(steps=2)
    solver = rf.simulation.solver
    store = FactorStore(directory=tmp_path)
    with solver.keeping_factors_in(store) as kept:
        assert kept is store and solver.factor_store is store
        with pytest.raises(RuntimeError, match="inner"), solver.keeping_factors_in(None):
            assert solver.factor_store is None
            raise RuntimeError("inner")
        assert solver.factor_store is store
    assert solver.factor_store is None
    with pytest.warns(DeprecationWarning, match="keeping_factors_in"):
        solver.factor_store = store
    assert solver.factor_store is store
