"""A Simulation freezes its model: terms, loads, contact terms and Dirichlet conditions added
afterwards raise ParameterError (the Simulation compiled the forms and collected the step
bounds when it was made, so it would ignore them or miss their collision-free step bound)."""

import numpy as np
import pytest
import ufl
from child_process import assert_child_raises
from mpi4py import MPI

import diffsolids as ds
from diffsolids.mesh import create_rectangle

FROZEN = "the model is already used by a Simulation"

# every public mutator of Model, called as it would be before creating the Simulation
MUTATORS = {
    "add_term": lambda m: m.add_term(lambda f: 1e-3 * ufl.dot(f.u, f.u) * f.dx),
    "add_body_force": lambda m: m.add_body_force([0.0, -1.0], name="late_force"),
    "add_gravity": lambda m: m.add_gravity(9.81),
    "add_traction": lambda m: m.add_traction(2, [0.0, -1.0], name="late_traction"),
    "add_dirichlet": lambda m: m.add_dirichlet(2, 0.0),
    "add_numeric_term": lambda m: m.add_numeric_term(object()),
}


def _domain():
    facets = {1: lambda x: np.isclose(x[0], 0.0), 2: lambda x: np.isclose(x[0], 1.0)}
    return create_rectangle(MPI.COMM_SELF, [[0, 0], [1, 0.2]], [5, 1], facets=facets)


def _contents(model) -> tuple:
    return (
        len(model.terms),
        len(model.numeric_terms),
        len(model.dirichlet),
        sorted(model.coefficients),
    )


@pytest.fixture(scope="module")
def frozen_model():
    model = ds.Model(_domain(), ds.NeoHookean(E=1e3, nu=0.3))
    model.add_dirichlet(1, 0.0)
    model.add_traction(2, [0.0, -1.0])
    ds.Simulation(model, ds.Static(), progress=False)
    return model


def test_simulation_freezes_the_model():
    model = ds.Model(_domain(), ds.NeoHookean(E=1e3, nu=0.3))
    model.add_dirichlet(1, 0.0)
    assert not model.frozen
    ds.Simulation(model, ds.Static(), progress=False)
    assert model.frozen
    ds.Simulation(model, ds.Static(num_steps=2), progress=False)  # more simulations may share it


def test_every_mutator_is_checked():
    public = {name for name in dir(ds.Model) if name.startswith("add_")}
    assert public == set(MUTATORS)


@pytest.mark.parametrize("method", sorted(MUTATORS))
def test_mutator_raises_after_a_simulation(frozen_model, method):
    before = _contents(frozen_model)
    with pytest.raises(ds.ParameterError, match=rf"Model\.{method}: {FROZEN}") as info:
        MUTATORS[method](frozen_model)
    assert "before creating the Simulation" in str(info.value)
    assert _contents(frozen_model) == before  # nothing half-added


def test_a_simulation_that_failed_does_not_freeze():
    model = ds.Model(_domain(), ds.NeoHookean(E=1e3, nu=0.3))
    with pytest.raises(ds.ParameterError, match="initial velocity needs a dynamic"):
        ds.Simulation(model, ds.Static(), v0=[1.0, 0.0])
    for add in MUTATORS.values():
        if add is not MUTATORS["add_numeric_term"]:
            add(model)


_SCRIPT = """
import numpy as np
from mpi4py import MPI
import diffsolids as ds
from diffsolids.mesh import create_rectangle

facets = {1: lambda x: np.isclose(x[0], 0.0), 2: lambda x: np.isclose(x[0], 1.0)}
model = ds.Model(create_rectangle(MPI.COMM_WORLD, [[0, 0], [1, 0.2]], [5, 1], facets=facets),
                 ds.NeoHookean(E=1e3, nu=0.3))
model.add_dirichlet(1, 0.0)
sim = ds.Simulation(model, ds.Static(), progress=False)
model.add_gravity(9.81)
"""


def test_error_reaches_the_user_as_itself(tmp_path):
    error = f"diffsolids.errors.ParameterError: Model.add_gravity: {FROZEN}"
    assert_child_raises(_SCRIPT, error, tmp_path)
