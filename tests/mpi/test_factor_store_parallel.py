"""Run under ``mpiexec -n 2``: a thinned factor store gives the serial gradient on 2 ranks.

The store's decisions (cap reached, stride doubled) are collective; the adjoint then
preconditions the steps without factors with those of later steps on every rank alike.
"""

import numpy as np
from mpi4py import MPI
from test_factor_store import _reduced_functional

RTOL = 1e-8


def test_thinned_store_world_equals_self():
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    results = []
    for c in (comm, MPI.COMM_SELF):
        rf = _reduced_functional(steps=13, nx=8, comm=c)
        store = rf.factor_store
        store.max_factors = 3
        q = rf.initial_parameters()
        J, g = rf.value_and_gradient(q)
        assert store.stride == 4 and 1 <= len(store.factors) <= 3
        results.append((J, g))
    (J_par, g_par), (J_ser, g_ser) = results
    assert abs(J_par / J_ser - 1) <= RTOL
    assert np.abs(g_par - g_ser).max() <= RTOL * np.abs(g_ser).max()


def test_memory_decision_is_collective(monkeypatch):
    """Ranks that see different spare memory keep the same factors (the smaller count)."""
    import diffsolids.solvers.factor_store as factor_store

    comm = MPI.COMM_WORLD
    rf = _reduced_functional(steps=8, nx=8, comm=comm)
    store = rf.factor_store = factor_store.FactorStore(out_of_core=False)
    room = 3 if comm.rank == 0 else 2  # factorisations each rank's node has room for

    def fake_memory():  # a huge MB per factorisation, far above the real ones
        return 250.0 + 1e6 * (room - len(store.factors)), 1000.0

    monkeypatch.setattr(factor_store, "node_memory_mb", fake_memory)
    J, g = rf.value_and_gradient(rf.initial_parameters())
    # room for 2 on every rank: 1, 2 -> thinned to 2, 4 -> thinned to 4, 8
    assert sorted(store.factors) == [4, 8] and store.stride == 4
    serial = _reduced_functional(steps=8, nx=8, comm=MPI.COMM_SELF)
    J_ser, g_ser = serial.value_and_gradient(serial.initial_parameters())
    assert abs(J / J_ser - 1) <= RTOL
    assert np.abs(g - g_ser).max() <= RTOL * np.abs(g_ser).max()
