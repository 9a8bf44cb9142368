"""Run under ``mpiexec -n 2``: GMRES + multigrid steps (``pc_type`` ``gamg``) give serial results.

The incline scene of test_krylov_steps.py on COMM_WORLD and on COMM_SELF in the same process:
the multigrid hierarchy depends on the partition, the solution of each Newton step and adjoint
system does not (both are solved to 1e-12), so values and gradients agree to 1e-8.
"""

import pytest
import test_gradients_contact as scenes
from mpi4py import MPI
from parallel_checks import assert_world_equals_self, value_and_gradient
from test_krylov_steps import GAMG

import diffsolids as ds
from diffsolids.controls import FrictionControl, ParameterControl, ShapeControl
from diffsolids.reduced_functional import ReducedFunctional

RTOL = 1e-8


def _value_and_gradient(comm):
    model, contact, sim, objective = scenes.incline_scene(1, 2, num_steps=4, comm=comm)
    controls = [
        ShapeControl(model, "all"),
        ParameterControl(model, "E", "field", log=True),
        FrictionControl(contact, pairs=[("slab", "block")]),
    ]
    rf = ReducedFunctional(sim, objective, controls)
    result = value_and_gradient(rf)
    assert rf.adjoint_stats["factorisations"] == 0 and rf.adjoint_stats["krylov_iterations"] > 0
    return result, [r.num_collisions for r in contact.records]


def test_gamg_world_equals_self(monkeypatch):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    monkeypatch.setattr(scenes, "NEWTON", ds.SolverOptions(rtol=1e-12, petsc_options=GAMG))
    world, counts_par = _value_and_gradient(comm)
    serial, counts_ser = _value_and_gradient(MPI.COMM_SELF)
    assert counts_par == counts_ser and min(counts_ser) > 0
    assert_world_equals_self(world, serial, RTOL, "largest relative world-vs-self difference")
    with pytest.raises(AssertionError):  # the comparison can fail: a gradient off by 1e-6
        assert_world_equals_self(world, (serial[0], serial[1], serial[2] * (1 + 1e-6)), RTOL)
