"""Misuse of controls, objectives and reduced functionals raises a diffsolids error naming it."""

import numpy as np
import pytest
import ufl
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import (
    ControlError,
    DirichletControl,
    InitialCondition,
    ParameterControl,
    RigidVelocity,
    ShapeControl,
)
from diffsolids.mesh import create_rectangle
from diffsolids.objectives import (
    Integral,
    ObjectiveError,
    StepValues,
    boundary_graph_fit,
    center_of_mass_trajectory,
    final_value,
    height_objective,
    stress_lp_norm,
    target_displacement,
    time_integral,
    volume_penalty,
)
from diffsolids.reduced_functional import AdjointError, ReducedFunctional


def _scene():
    dom = create_rectangle(
        MPI.COMM_SELF,
        [[0, 0], [2, 0.5]],
        [4, 2],
        facets={1: lambda x: np.isclose(x[0], 0), 2: lambda x: np.isclose(x[0], 2)},
        bodies={2: lambda m: m[0] > 1},
        names={"clamp": 1, "tip": 2},
    )
    model = ds.Model(dom, ds.NeoHookean(E=100.0, nu=0.3))
    model.add_gravity(1.0)
    bc = model.add_dirichlet("clamp", 0.0)
    sim = ds.Simulation(model, ds.BDF(2, 0.05, 3), ds.SolverOptions(rtol=1e-12), progress=False)
    return model, sim, bc


@pytest.fixture(scope="module")
def scene():
    return _scene()


@pytest.fixture(scope="module")
def other():
    return _scene()


def _objective(model):
    return time_integral(Integral(lambda f: ufl.dot(f.u, f.u) * f.dx, "u2"))


# -- controls ----------------------------------------------------------------------------------
def test_controls_of_another_simulation(scene, other):
    model, sim, _ = scene
    other_model, other_sim, other_bc = other
    J = _objective(model)
    foreign = [
        (ParameterControl(other_model, "E", "field"), "belongs to a different model"),
        (ShapeControl(other_model, "all"), "shape control belongs to a different model"),
        (InitialCondition(other_sim, "velocity"), "belongs to a different simulation"),
        (RigidVelocity(other_sim, 1), "belongs to a different simulation"),
        (DirichletControl(other_sim, other_bc), "belongs to a different simulation"),
    ]
    for control, message in foreign:
        with pytest.raises(ControlError, match=message):
            ReducedFunctional(sim, J, [ParameterControl(model, "E", "uniform"), control])
    with pytest.raises(ControlError, match="does not belong to the simulation's model"):
        DirichletControl(sim, other_bc)


def test_conflicting_controls(scene):
    model, sim, bc = scene
    J = _objective(model)
    pairs = [
        (ShapeControl(model, "all"), ShapeControl(model, "boundary"), "both set shape"),
        (
            ParameterControl(model, "E", "field"),
            ParameterControl(model, "E", "bodies", bodies=[2]),
            "both set coefficient 'E'",
        ),
        (InitialCondition(sim), RigidVelocity(sim, 1), "both set the initial velocity"),
        (DirichletControl(sim, bc), DirichletControl(sim, bc, per_step=True), "both set Dirichlet"),
    ]
    for a, b, message in pairs:
        with pytest.raises(ControlError, match=message):
            ReducedFunctional(sim, J, [a, b])
    # disjoint parts of one quantity are fine
    rf = ReducedFunctional(
        sim,
        J,
        [
            ParameterControl(model, "E", "bodies", bodies=[1]),
            ParameterControl(model, "E", "bodies", bodies=[2]),
            RigidVelocity(sim, 1),
            RigidVelocity(sim, 2),
        ],
    )
    assert rf.size == 2 + 2 * 3


def test_bad_control_construction(scene):
    model, sim, _ = scene
    with pytest.raises(ControlError, match="no coefficient 'young'"):
        ParameterControl(model, "young")
    with pytest.raises(ControlError, match="unknown parameter mode 'cells'"):
        ParameterControl(model, "E", "cells")
    with pytest.raises(
        ControlError, match="'gravity' cannot be parametrised: log parametrisation needs positive"
    ):
        ParameterControl(model, "gravity", "uniform", log=True)
    with pytest.raises(ds.TagError, match="unknown body"):
        ParameterControl(model, "E", "bodies", bodies=[7])
    with pytest.raises(ControlError, match="unknown vertex selection 'surface'"):
        ShapeControl(model, "surface")
    with pytest.raises(ControlError, match="vertex indices out of range"):
        ShapeControl(model, np.array([0, 10**6]))
    with pytest.raises(ControlError, match="linear_map has 3 rows, expected"):
        ShapeControl(model, linear_map=np.ones((3, 2)))
    static = ds.Simulation(model, ds.Static(), progress=False)
    with pytest.raises(ControlError, match="initial-velocity control needs a dynamic"):
        InitialCondition(static, "velocity")
    with pytest.raises(ControlError, match="rigid initial-velocity control needs a dynamic"):
        RigidVelocity(static, 1)
    with pytest.raises(ControlError, match="'displacement' or 'velocity'"):
        InitialCondition(sim, "acceleration")
    with pytest.raises(ControlError, match="at least one control"):
        ReducedFunctional(sim, _objective(model), [])


def test_parameter_vector_of_wrong_length(scene):
    model, sim, _ = scene
    rf = ReducedFunctional(
        sim, _objective(model), [ParameterControl(model, "E", "bodies"), RigidVelocity(sim, 2)]
    )
    q = rf.initial_parameters()
    assert q.size == 5
    for bad in (q[:-1], np.append(q, 1.0), q.reshape(1, -1)):
        with pytest.raises(ControlError, match=r"the controls expect 5 \(E\[bodies\]: 2, rigid"):
            rf(bad)
        with pytest.raises(ControlError, match="the controls expect 5"):
            rf.gradient(bad)
    q_nan = q.copy()
    q_nan[0] = np.nan
    with pytest.raises(ControlError, match="non-finite"):
        rf(q_nan)


def test_non_physical_parameters(scene):
    model, sim, _ = scene
    rf = ReducedFunctional(sim, _objective(model), [ParameterControl(model, "nu", "uniform")])
    with pytest.raises(ds.ParameterError, match=r"nu has \d+ values outside the physical range"):
        rf(np.array([0.5]))
    rf.controls.assign(np.array([0.3]))


def test_shape_update_inverting_elements(scene):
    model, sim, _ = scene
    control = ShapeControl(model, "all")
    rf = ReducedFunctional(sim, _objective(model), [control])
    q0 = rf.initial_parameters()
    x_before = model.domain.mesh.geometry.x.copy()
    q = q0.copy().reshape(-1, 2)
    q[:, 0] = -2.0 * control.X0[np.argsort(control.input_index)][:, 0]  # mirror in x: all flip
    with pytest.raises(
        ds.InvertedElementError, match=r"inverts 16 cells \(input cell indices"
    ) as e:
        rf(q.ravel())
    assert len(e.value.cells) == 16
    assert np.array_equal(model.domain.mesh.geometry.x, x_before)  # the mesh is left unchanged
    one = q0.copy().reshape(-1, 2)
    corner = int(np.flatnonzero(np.all(np.isclose(control.X0, [2.0, 0.5]), axis=1))[0])
    one[control.input_index[corner]] = [-1.9, -0.45]  # pull a corner across its cell
    with pytest.raises(ds.InvertedElementError) as e:
        rf(one.ravel())
    assert 1 <= len(e.value.cells) < 16
    assert np.array_equal(model.domain.mesh.geometry.x, x_before)
    assert rf(q0) > 0.0  # still usable


# -- objectives ------------------------------------------------------------------------------------
def test_objectives_with_unknown_tags(scene):
    model, *_ = scene
    with pytest.raises(ds.TagError, match="unknown facet tag 9"):
        target_displacement(model, [0.0, 0.0], facets=9)
    with pytest.raises(ds.TagError, match="unknown facet tag name 'top'"):
        target_displacement(model, [0.0, 0.0], facets=["tip", "top"])
    with pytest.raises(ds.TagError, match=r"unknown body \(cell tag\) 3"):
        target_displacement(model, [0.0, 0.0], bodies=[3])
    with pytest.raises(ds.TagError, match="unknown facet tag 5"):
        boundary_graph_fit(model, 5, ufl.sin)
    with pytest.raises(ds.TagError, match="unknown body"):
        center_of_mass_trajectory(model, [0.0, 0.0], bodies=4)
    with pytest.raises(ds.TagError, match="unknown body"):
        stress_lp_norm(model, 2, bodies=["stiff"]).a.form(model.fields)
    with pytest.raises(ds.TagError, match="unknown body"):
        volume_penalty(model, 1.0, bodies=[8])


def test_objectives_with_bad_arguments(scene):
    model, *_ = scene
    with pytest.raises(ds.ParameterError, match="p >= 2"):
        stress_lp_norm(model, 1.5)
    with pytest.raises(ds.ParameterError, match="unknown stress 'tresca'"):
        stress_lp_norm(model, 2, "tresca")
    with pytest.raises(ds.ParameterError, match=r"target has shape \(3,\), expected \(2,\)"):
        target_displacement(model, [0.0, 0.0, 0.0])
    with pytest.raises(ds.ParameterError, match=r"bodies \(volume target\), not both"):
        target_displacement(model, [0.0, 0.0], facets=2, bodies=[1])
    with pytest.raises(ds.ParameterError, match="volume bound must be 'upper' or 'lower'"):
        volume_penalty(model, 1.0, "both")
    with pytest.raises(ds.ParameterError, match=r"expected \(2,\) or \(N \+ 1, 2\)"):
        center_of_mass_trajectory(model, np.zeros((4, 3)))
    with pytest.raises(ds.ParameterError, match="axis 2 out of range"):
        height_objective(model, axis=2)


def test_objectives_referring_to_unknown_steps(scene):
    model, sim, _ = scene  # steps 0..3
    control = [ParameterControl(model, "E", "uniform")]
    u2 = Integral(lambda f: ufl.dot(f.u, f.u) * f.dx, "u2")
    bad = [
        (time_integral(u2, [1, 4]), r"refers to steps \[1, 4\] but the run has 0..3"),
        (time_integral(u2, np.ones(7)), r"expected 4 time weights, got shape \(7,\)"),
        (time_integral(u2, "midpoint"), "unknown time weighting 'midpoint'"),
        (
            time_integral(center_of_mass_trajectory(model, np.zeros((6, 2))), "uniform"),
            "centre-of-mass target has 6 values but the run has 4 states",
        ),
        (final_value(u2 - StepValues([0.0, 1.0], "data")), "data has 2 values"),
    ]
    for objective, message in bad:
        rf = ReducedFunctional(sim, objective, control)
        with pytest.raises(ObjectiveError, match=message):
            rf(rf.initial_parameters())
    with pytest.raises(ObjectiveError, match="time_integral expects a Series"):
        time_integral(final_value(u2))
    with pytest.raises(ObjectiveError, match="objective must be an Objective"):
        ReducedFunctional(sim, u2, control)


def test_gradient_before_forward(scene):
    model, sim, _ = scene
    rf = ReducedFunctional(sim, _objective(model), [ParameterControl(model, "E", "uniform")])
    with pytest.raises(AdjointError, match=r"no forward solve yet: call rf\(q\)"):
        rf.derivative()
    assert isinstance(AdjointError("x"), ds.DiffsolidsError)
    g = rf.gradient(rf.initial_parameters())  # the documented way works
    assert g.shape == (1,) and np.isfinite(g).all()


def test_non_finite_objective(scene):
    model, sim, _ = scene
    log_of_zero = Integral(lambda f: ufl.ln(ufl.dot(f.u, f.u)) * f.dx, "log")
    rf = ReducedFunctional(
        sim, time_integral(log_of_zero, [0]), [ParameterControl(model, "E", "uniform")]
    )
    with pytest.raises(ObjectiveError, match="not finite"):
        rf(rf.initial_parameters())
