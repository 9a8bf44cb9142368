"""Run under ``mpiexec -n 2``: gradients through contact and friction on 2 ranks equal serial ones.

The scenes of test_gradients_contact.py and test_contact_indenter.py are built on COMM_WORLD and
on COMM_SELF in the same process; collision counts, continuation substeps, values and gradients
(parameters in canonical order) must agree.
"""

import pytest
from mpi4py import MPI
from parallel_checks import assert_world_equals_self, value_and_gradient
from test_contact_indenter import _indenter_scene
from test_gradients_contact import incline_scene, static_scene

from diffsolids.controls import FrictionControl, InitialCondition, ParameterControl, ShapeControl
from diffsolids.reduced_functional import ReducedFunctional

RTOL = 1e-8


def _incline(comm):
    model, contact, sim, objective = incline_scene(1, 2, comm=comm)
    controls = [
        ShapeControl(model, "all"),
        ParameterControl(model, "E", "field", log=True),
        FrictionControl(contact),
        ParameterControl(model, "damping_psi", "bodies"),
        InitialCondition(sim, "velocity"),
    ]
    return ReducedFunctional(sim, objective, controls), contact


def _static_3d(comm):
    model, contact, sim, objective = static_scene(3, comm=comm)
    return ReducedFunctional(sim, objective, ShapeControl(model, "all")), contact


def _static_3d_convergent(comm):
    """The convergent formulation: merged and negative weights read, the others in bulk."""
    model, contact, sim, objective = static_scene(3, comm=comm, formulation="convergent")
    return ReducedFunctional(sim, objective, ShapeControl(model, "all")), contact


def _indenter(comm):
    """Obstacle driven by Dirichlet values: steps reached by continuation (substeps)."""
    model, contact, sim, objective = _indenter_scene(True, 0.3, comm=comm)
    controls = [
        ParameterControl(model, "E", "bodies", bodies=["block"], log=True),
        ShapeControl(model, "all"),
    ]
    return ReducedFunctional(sim, objective, controls), contact


def _value_and_gradient(build, comm):
    rf, contact = build(comm)
    result = value_and_gradient(rf)
    counts = [r.num_collisions for r in contact.records]
    counts.append(dict(rf.simulation.substeps))
    return result, counts


@pytest.mark.parametrize(
    "build",
    [_incline, _static_3d, _static_3d_convergent, _indenter],
    ids=["incline-friction", "static-3d", "static-3d-convergent", "indenter"],
)
def test_contact_gradient_world_equals_self(build):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    world, counts_par = _value_and_gradient(build, comm)
    serial, counts_ser = _value_and_gradient(build, MPI.COMM_SELF)
    assert counts_par == counts_ser and min(counts_ser[:-1]) > 0
    assert_world_equals_self(world, serial, RTOL, "largest relative world-vs-self difference")
