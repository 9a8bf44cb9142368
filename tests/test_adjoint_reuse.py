"""What the backward sweep reuses from the forward, and that it never reuses it stale.

The contact term keeps each step's collision set at the converged u^i, its lagged collision
set and TangentialCollisions (by step, checked against what they were built from); the adjoint
forms' emptiness is memoised by UFL signature. A gradient after changing the friction
coefficient, the shape, the initial velocity (also so much that the collision sets change) or
the time step of the same model and contact term must equal the gradient of a fresh simulation
at those values, and the sweep must build no collision sets or lagged friction of its own.
"""

import ipctk
import numpy as np
import pytest
from test_gradients_contact import incline_scene

import diffsolids as ds
from diffsolids.adjoint import forms as adjoint_forms
from diffsolids.controls import FrictionControl, InitialCondition, ShapeControl
from diffsolids.reduced_functional import ReducedFunctional

STEPS = 4
RTOL = 1e-12  # the same arithmetic: equal to round-off


def _problem(order: int = 2, dt: float | None = None):
    model, contact, sim, objective = incline_scene(1, order, num_steps=STEPS)
    if dt is not None:
        integ = ds.BDF(order, dt, STEPS)
        sim = ds.Simulation(model, integ, ds.SolverOptions(rtol=1e-12), progress=False)
    controls = [
        FrictionControl(contact, pairs=[("slab", "block")]),
        ShapeControl(model, "all"),
        InitialCondition(sim, "velocity"),
    ]
    return model, contact, sim, ReducedFunctional(sim, objective, controls)


def _fresh(q: np.ndarray, dt: float | None = None, sets: list | None = None):
    """(J, gradient) at q of a new scene (a new model, contact term and simulation).

    ``sets``: a list to append the fresh run's collision sets to.
    """
    _, contact, _, rf = _problem(dt=dt)
    J, g = rf(q), rf.gradient(q)
    if sets is not None:
        sets.append(_collision_sets(contact))
    return J, g


def _close(a, b) -> bool:
    return np.allclose(a, b, rtol=RTOL, atol=RTOL * np.abs(b).max())


def _count_lagged_builds(contact) -> list[int]:
    """Count the builds of the step's own TangentialCollisions (patched on the instance).

    Those with the current coefficients and without weight gradients: the friction and shape
    kernels build their own (unit coefficients, shape derivatives).
    """
    lagging = contact.lagging
    calls = [0]
    original = lagging.tangential_collisions

    def counted(mu_table, barrier, shape_derivatives=False):
        if not shape_derivatives and np.array_equal(mu_table, lagging.mu_table(lagging.mu)):
            calls[0] += 1
        return original(mu_table, barrier, shape_derivatives)

    lagging.tangential_collisions = counted
    return calls


def _collision_sets(contact) -> list[list]:
    """The vertex ids of the collisions the forward kept at the end of each step."""
    mesh = contact.surface.mesh
    return [
        sorted(tuple(C[k].vertex_ids(mesh.edges, mesh.faces)) for k in range(len(C)))
        for *_, C in (contact.adjoint._kept[i] for i in sorted(contact.adjoint._kept))
    ]


def _count_collision_builds(contact) -> list[int]:
    """Count the builds of collision sets without weight gradients (patched on the instance)."""
    builder = contact.builder
    calls = [0]
    original = builder.build

    def counted(x, shape_derivatives=False):
        if not shape_derivatives:
            calls[0] += 1
        return original(x, shape_derivatives)

    builder.build = counted
    return calls


def test_sweep_reuses_the_forward_friction_and_collisions():
    _, contact, _, rf = _problem()
    q = rf.initial_parameters()
    rf(q)
    calls = _count_lagged_builds(contact)
    builds = _count_collision_builds(contact)
    g = rf.gradient(q)  # no new forward: the sweep of the run above
    assert contact.lagging.active
    assert calls[0] == 0, f"the sweep built {calls[0]} lagged TangentialCollisions"
    # the collision sets at u^i (kept at the forward's end of step) and at u^{i-1} (lagged)
    assert builds[0] == 0, f"the sweep built {builds[0]} collision sets"
    step = contact._step  # the last step: its kept set is for its U^N only
    U = contact.adjoint._kept[step.index][1]
    assert contact.adjoint.kept_collisions(step, U) is not None
    assert contact.adjoint.kept_collisions(step, U + 1e-12) is None
    assert _close(g, _fresh(q)[1])


@pytest.mark.parametrize(
    "change", ["friction", "shape", "friction_and_shape", "velocity", "faster"]
)
def test_changed_parameters_match_a_fresh_simulation(change):
    model, contact, _, rf = _problem()
    q0 = rf.initial_parameters()
    rf(q0)
    rf.gradient(q0)
    q = q0.copy()
    if change in ("friction", "friction_and_shape"):
        q[0] = 0.3  # mu 0.2 -> 0.3: the kept collision sets hold, the friction does not
    if change in ("shape", "friction_and_shape"):
        q[1:-2] += 1e-4 * np.random.default_rng(1).standard_normal(len(q) - 3)
    if change == "velocity":
        q[-2:] += [0.05, -0.02]  # the states from step 1 on change, x^0 does not
    if change == "faster":  # the block slides past slab vertices: other collision sets
        a, b = rf.controls.offsets[2:4]
        nodes = np.unique(model.V.dofmap.list[model.domain.cells_of("block")])
        q[a:b].reshape(-1, 2)[nodes, 0] += 3.0
    sets = [_collision_sets(contact)]
    J, g = rf(q), rf.gradient(q)
    J_fresh, g_fresh = _fresh(q, sets=sets)
    if change == "faster":  # what was kept at q0 would be wrong at q
        assert sets[0] != sets[1]
    assert abs(J - J_fresh) <= RTOL * abs(J_fresh)
    assert _close(g, g_fresh)
    # and back: what q kept does not leak into q0
    assert _close(rf.gradient(q0), _fresh(q0)[1])


def test_kept_friction_needs_the_same_barrier_and_coefficients():
    """kappa is fixed for the life of a contact term; the kept friction still checks it."""
    _, contact, _, rf = _problem()
    rf(rf.initial_parameters())
    lagging = contact.lagging  # at the last step of the run
    kept = lagging._step_tangential(contact.barrier)
    assert lagging._step_tangential(contact.barrier) is kept
    other = ipctk.BarrierPotential(contact.dhat, 2.0 * contact.stiffness)
    rebuilt = lagging._step_tangential(other)
    assert rebuilt is not kept
    forces = [rebuilt[k].normal_force_magnitude for k in range(len(rebuilt))]
    expected = [2.0 * kept[k].normal_force_magnitude for k in range(len(kept))]
    assert np.allclose(forces, expected, rtol=1e-12)
    mu = lagging.mu.copy()
    lagging.set_coefficients(2.0 * mu)
    assert lagging._step_tangential(other) is not rebuilt
    lagging.set_coefficients(mu)


def test_changed_time_step_matches_a_fresh_simulation():
    model, contact, _, rf = _problem()
    q = rf.initial_parameters()
    rf(q)
    rf.gradient(q)
    # another simulation of the same model and contact term, with another time step
    integ = ds.BDF(2, 0.012, STEPS)
    sim2 = ds.Simulation(model, integ, ds.SolverOptions(rtol=1e-12), progress=False)
    controls = [
        FrictionControl(contact, pairs=[("slab", "block")]),
        ShapeControl(model, "all"),
        InitialCondition(sim2, "velocity"),
    ]
    rf2 = ReducedFunctional(sim2, rf.objective, controls)
    J, g = rf2(q), rf2.gradient(q)
    J_fresh, g_fresh = _fresh(q, dt=0.012)
    assert abs(J - J_fresh) <= RTOL * abs(J_fresh)
    assert _close(g, g_fresh)


def test_form_emptiness_memo_is_by_signature():
    """An empty derivative and a nonempty one: the memo answers each from its own signature."""
    import ufl
    from dolfinx import fem

    model, _, _, _ = _problem()
    f = model.fields
    w = ufl.TestFunction(model.V)
    J = ufl.inner(f.u, f.u) * ufl.dx(domain=model.V.mesh)
    nonempty = ufl.derivative(J, f.u, w)
    empty = ufl.derivative(J, f.v, w)  # J does not read v
    for _ in range(2):  # the second time from the memo
        assert adjoint_forms._nonempty(nonempty) is nonempty
        assert adjoint_forms._nonempty(empty) is None
    assert adjoint_forms._EMPTY_BY_SIGNATURE[nonempty.signature()] is False
    assert adjoint_forms._EMPTY_BY_SIGNATURE[empty.signature()] is True
    # another model's form of the same structure has the same signature, and the same answer
    other, _, _, _ = _problem()
    g = other.fields
    same = ufl.derivative(
        ufl.inner(g.u, g.u) * ufl.dx(domain=other.V.mesh), g.u, ufl.TestFunction(other.V)
    )
    assert same.signature() == nonempty.signature()
    assert adjoint_forms._nonempty(same) is same
    assert isinstance(fem.form(nonempty), fem.Form)
