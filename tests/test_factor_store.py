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
    store = rf.simulation.solver.factor_store
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
    stores = [rf.simulation.solver.factor_store for rf in rfs]
    assert sum(len(s.factors) for s in stores) <= 3
    for error in _fd_errors(rfs[1]):
        assert error <= FD_TOLERANCE


def test_a_long_trajectory_keeps_few_factorisations():
    # before the cap: 450 live MUMPS instances ran out of MPI communicators and crashed
    rf = _reduced_functional(steps=450, nx=2)
    rf.forward(rf.initial_parameters())
    store = rf.simulation.solver.factor_store
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

    gc.collect()
    before = free_communicators()
    for _ in range(3):
        rf = _reduced_functional(steps=4)
        rf.gradient(rf.initial_parameters())
        solver = weakref.ref(rf.simulation.solver)
        del rf
        gc.collect()
        assert solver() is None
    assert free_communicators() == before


def test_max_factors_must_be_positive():
    with pytest.raises(ValueError, match="max_factors"):
        FactorStore(max_factors=0)


@pytest.mark.parametrize("kwargs", [{"budget_mb": -1.0}, {"reserve": 1.0}, {"reserve": -0.1}])
def test_memory_settings_are_checked(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        FactorStore(**kwargs)


def test_default_budget_keeps_factors_while_the_node_has_memory_to_spare(monkeypatch):
    """Without a budget, factors are kept until the node's available memory nears the reserve."""
    import diffsolids.solvers.factor_store as factor_store

    rf = _reduced_functional(steps=10)
    store = rf.simulation.solver.factor_store
    assert store.budget_mb is None  # the ReducedFunctional's default
    state = {"per_factor": None}

    def fake_memory():
        # a node of 1000 MB whose available memory shrinks by what the store keeps, starting
        # 3.5 factorisations above the reserve (25 % of the total); at the first call the SNES
        # still holds the factors of step 1
        if state["per_factor"] is None:
            ksp = rf.simulation.solver.snes.getKSP()
            state["per_factor"] = factor_memory_mb(ksp.getPC().getFactorMatrix())
        return 250.0 + 3.5 * state["per_factor"] - store.used_mb, 1000.0

    monkeypatch.setattr(factor_store, "node_memory_mb", fake_memory)
    rf.forward(rf.initial_parameters())
    assert len(store.factors) == 3  # the fourth would leave less than the reserve
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
