"""The objective library a ported paper scene needs (issue 13): target trajectories, node
targets, soft minima over steps, signed-distance targets, compliance and barriers. Values by
hand on known states, gradients against central differences of the whole simulation along a
random direction per control block and along the gradient, errors naming the offending step."""

import numpy as np
import pytest
import ufl
from diffsolids.forms.objectives import log_barrier
from dolfinx import fem
from gradient_scenes import CONTROLS, simulation

from diffsolids.adjoint import Checkpointing, CheckpointingError
from diffsolids.objectives import (
    DeformedCollisionBarrier,
    Integral,
    ObjectiveError,
    RestCollisionBarrier,
    StepValues,
    TimeGrid,
    center_target,
    compliance,
    final_value,
    height_objective,
    inversion_barrier,
    min_distance_target,
    node_target,
    scalar_log_barrier,
    sdf_barrier,
    sdf_target,
    series_barrier,
    series_values,
    soft_min,
    step_selector,
    step_values,
    step_weights,
    target_positions,
    target_trajectory,
    time_integral,
)
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.verification import finite_difference_check

FD_TOLERANCE = 1e-6
SCENE = "2d-p1-nh-damped"  # [0, 2] x [0, 0.5], 4 x 2 cells, clamped at x = 0 (facet 1)
SIZES = {"shape-all": 0.02, "initial-v0": 0.1}  # absolute; parameters: 5 % of |q|
STEPS = np.array([1e-2, 1e-3, 1e-4])


def _fd_check(sim, objective, keys, seed=0):
    """FD of each control block along a random direction and of all along the gradient."""
    rf = ReducedFunctional(sim, objective, [CONTROLS[k](sim) for k in keys])
    q0 = rf.initial_parameters()
    try:
        J0, g = rf.value_and_gradient(q0)
        assert np.isfinite(J0)
        rng = np.random.default_rng(seed)
        offsets = rf.controls.offsets
        blocks = []
        for key, a, b in zip(keys, offsets[:-1], offsets[1:], strict=True):
            size = SIZES.get(key, 0.05 * max(np.linalg.norm(q0[a:b]), 1e-3 * np.sqrt(b - a)))
            blocks.append((size, a, b))
            d = np.zeros_like(q0)
            r = rng.standard_normal(b - a)
            d[a:b] = size * r / np.linalg.norm(r)
            res = finite_difference_check(rf, q0, d, STEPS, gradient=g)
            assert abs(res.adjoint) > 1e-12, (key, res)
            assert res.relative_error <= FD_TOLERANCE, (key, res)
        h = min(size / max(np.linalg.norm(g[a:b]), 1e-300) for size, a, b in blocks)
        res = finite_difference_check(rf, q0, h * g, STEPS, gradient=g)
        assert res.relative_error <= FD_TOLERANCE, res
        return J0, g
    finally:
        rf.controls.assign(q0)


def _copy(traj):
    """A trajectory's states as plain lists (the simulation reuses nothing of them)."""
    return type(traj)(list(traj.times), [u.copy() for u in traj.u], [v.copy() for v in traj.v])


def _run(sim):
    return _copy(sim.run())


def _target_run(sim, factor):
    """A run of the scene with E scaled by ``factor`` (the target of the puzzle and kangaroo)."""
    E = sim.model.coefficients["E"]
    saved = E.x.array.copy()
    E.x.array[:] *= factor
    try:
        return _run(sim)
    finally:
        E.x.array[:] = saved


# -- per-step data by time --------------------------------------------------------------------
def test_step_selector_picks_one_state_per_time():
    model = simulation(SCENE, "bdf2").model
    times = [0.0, 0.05, 0.1, 0.15]
    chi = step_selector(model.fields.t, times)
    one = fem.form(sum(c * (i + 1) for i, c in enumerate(chi)) * model.fields.dx)
    area = 1.0
    for i, t in enumerate(times):
        model.fields.t.value = t
        assert fem.assemble_scalar(one) == pytest.approx((i + 1) * area, rel=1e-13)
    model.fields.t.value = 1.0  # no state there
    assert fem.assemble_scalar(one) == 0.0
    model.fields.t.value = 0.0


# -- target trajectory ---------------------------------------------------------------------------
def test_target_trajectory_values():
    """Own trajectory: zero at every state; shifted by c: |c|^2 times the area / facet length."""
    sim = simulation(SCENE, "bdf2")
    own = _run(sim)
    for match in ("positions", "displacement"):
        s = target_trajectory(sim, own, match=match)
        assert np.abs(series_values(sim, s, own)).max() < 1e-24
    c = np.array([0.03, -0.02])
    shifted = _copy(own)
    for u in shifted.u:
        u.reshape(-1, 2)[:] += c
    volume = series_values(sim, target_trajectory(sim, shifted), own)
    assert volume == pytest.approx(np.full(4, c @ c * 1.0), rel=1e-12)
    body = series_values(sim, target_trajectory(sim, shifted, bodies=[2], weight=3.0), own)
    assert body == pytest.approx(np.full(4, 3.0 * c @ c * 0.5), rel=1e-12)
    surface = series_values(sim, target_trajectory(sim, shifted, facets=[2, 3]), own)
    assert surface == pytest.approx(np.full(4, c @ c * (0.5 + 2.0)), rel=1e-12)
    # the right state at each step: the own trajectory against the target run, step by step
    other = _target_run(sim, 1.3)
    values = series_values(sim, target_trajectory(sim, other, match="displacement"), own)
    V = sim.model.V
    for i in range(4):
        e = fem.Function(V)
        e.x.array[:] = own.u[i] - other.u[i]
        by_hand = fem.assemble_scalar(fem.form(ufl.dot(e, e) * sim.model.fields.dx))
        assert values[i] == pytest.approx(by_hand, rel=1e-12, abs=1e-30)
    assert values[-1] > 1e-8


def test_target_trajectory_gradient():
    """PolyFEM's target objective of the puzzle/kangaroo (the run of other parameters), on a
    surface selection, plus a volume selection of body 2 reduced over two steps."""
    sim = simulation(SCENE, "bdf2")
    target = _target_run(sim, 1.4)
    surface = time_integral(target_trajectory(sim, target, facets=[2, 3]), "uniform")
    volume = time_integral(target_trajectory(sim, target, bodies=[2]), [1, 3])
    _fd_check(sim, 10.0 * surface + volume, ["young-field-log", "shape-all"])


def test_target_trajectory_subset_of_steps_initial_velocity():
    sim = simulation(SCENE, "bdf2")
    target = _target_run(sim, 0.8)
    s = target_trajectory(sim, target, facets=2, match="displacement")
    _fd_check(sim, time_integral(s, [1, 3]), ["initial-v0"])


def test_target_trajectory_errors_name_the_state():
    sim = simulation(SCENE, "bdf2")
    own = _run(sim)
    with pytest.raises(ObjectiveError, match=r"3 states but the simulation has 4"):
        target_trajectory(sim, own.u[:3])
    bad = _copy(own)
    bad.u[2][5] = np.nan
    with pytest.raises(ObjectiveError, match="state 2: non-finite"):
        target_trajectory(sim, bad)
    bad = _copy(own)
    bad.times[3] = 0.2
    with pytest.raises(ObjectiveError, match=r"state 3: time 0.2 but the simulation's step 3"):
        target_trajectory(sim, bad)
    with pytest.raises(ObjectiveError, match=r"state 0: .* values, expected"):
        target_trajectory(sim, [u[:-2] for u in own.u])
    with pytest.raises(ObjectiveError, match=r"target must be a Trajectory .* got float"):
        target_trajectory(sim, 1.0)
    s = target_trajectory(sim, own)
    with pytest.raises(ObjectiveError, match="the target has 4 states but the run has 3"):
        s.values({s: np.zeros(3)})


def test_center_target_of_the_sliding_bunny():
    """PolyFEM's center-target (fig21): zero on the own run, gradient against the E x 0.7 run."""
    sim = simulation(SCENE, "bdf2")
    own = _run(sim)
    assert np.abs(series_values(sim, center_target(sim, own, bodies=[2]), own)).max() < 1e-28
    s = center_target(sim, _target_run(sim, 0.7), bodies=[2])
    _fd_check(sim, 100.0 * final_value(s), ["initial-v0", "young-field-log"])


# -- node target -----------------------------------------------------------------------------
def _right_end(x):
    return np.isclose(x[0], 2.0)


def test_node_target_values_exact_sum():
    """At rest: sum over the selected vertices of |X_n + 0 - x_n^trg|^2, by locator or index."""
    sim = simulation(SCENE, "bdf2")
    model = sim.model
    own = _run(sim)
    d = np.array([0.1, -0.2])
    s = node_target(model, _right_end, d, match="displacement")
    assert series_values(sim, s, own, steps=[0]) == pytest.approx([3 * d @ d], rel=1e-12)
    # by input index: the vertices of the right end, targets one per index
    x = model.domain.mesh.geometry.x
    ids = model.domain.mesh.geometry.input_global_indices
    right = np.flatnonzero(np.isclose(x[:, 0], 2.0))
    targets = x[right, :2] + np.array([[0.0, 0.1], [0.2, 0.0], [0.0, -0.3]])
    s = node_target(model, ids[right], targets, weight=2.0)
    assert series_values(sim, s, own, steps=[0]) == pytest.approx([2.0 * 0.14], rel=1e-12)
    # later states: the nodal displacements themselves
    u = own.u[-1].reshape(-1, 2)
    V = model.V
    dof_x = V.tabulate_dof_coordinates()[:, 0]
    by_hand = np.sum((u[np.isclose(dof_x, 2.0)] - d) ** 2)
    s = node_target(model, _right_end, d, match="displacement")
    assert series_values(sim, s, own, steps=[-1]) == pytest.approx([by_hand], rel=1e-12)


def test_node_target_gradient_with_another_quadrature():
    """Shape, E and v0 gradients; combined with a default-quadrature target in one objective."""
    sim = simulation(SCENE, "bdf2")
    model = sim.model
    nodes = node_target(model, _right_end, lambda x: x[:2] + np.array([[0.02], [-0.05]]))
    other = target_positions(model, lambda x: 1.01 * x[:2], facets=3)
    J = time_integral(nodes, [2, 3]) + 0.5 * final_value(other)
    _fd_check(sim, J, ["young-field-log", "shape-all", "initial-v0"])


def test_node_target_errors():
    model = simulation(SCENE, "bdf2").model
    with pytest.raises(Exception, match="selects no mesh vertex"):
        node_target(model, lambda x: x[0] > 5.0, [0.0, 0.0])
    with pytest.raises(Exception, match=r"no mesh vertex has the input index \[1000\]"):
        node_target(model, [0, 1000], [0.0, 0.0])
    with pytest.raises(Exception, match="node target has shape"):
        node_target(model, _right_end, [0.0, 0.0, 0.0])


# -- soft minimum over steps -------------------------------------------------------------------
def _leaf(name):
    return Integral(lambda f: None, name)


GRID = TimeGrid(num_steps=5, dt=0.1, dynamic=True)


@pytest.mark.parametrize("kind", ["logsumexp", "harmonic"])
def test_soft_min_value_bounds_and_chain_rule(kind):
    a = _leaf("a")
    rng = np.random.default_rng(4)
    table = {a: rng.uniform(0.5, 2.0, 6)}
    table[a][0] = np.nan  # not evaluated: not among the steps
    steps = [1, 2, 4, -1]
    J = soft_min(a**2, steps, alpha=8.0, kind=kind)
    s = table[a][[1, 2, 4, 5]] ** 2
    value = J.value(table, {}, GRID)
    if kind == "logsumexp":
        assert s.min() - np.log(4) / 8.0 <= value <= s.min()
        assert value == pytest.approx(-np.log(np.sum(np.exp(-8.0 * s))) / 8.0, rel=1e-13)
    else:
        assert value == pytest.approx(1.0 / np.sum(1.0 / s), rel=1e-13)
    assert J.requirements(GRID) == {a: {1, 2, 4, 5}}
    out = {}
    J.backward(table, {}, GRID, 1.0, out, {})
    assert out[a][0] == 0.0 and out[a][3] == 0.0
    for i in (1, 2, 4, 5):
        h = 1e-6
        plus, minus = dict(table), dict(table)
        plus[a], minus[a] = table[a].copy(), table[a].copy()
        plus[a][i] += h
        minus[a][i] -= h
        fd = (J.value(plus, {}, GRID) - J.value(minus, {}, GRID)) / (2 * h)
        assert out[a][i] == pytest.approx(fd, rel=1e-7, abs=1e-9)


def test_soft_min_sharp_limit_and_errors():
    a = _leaf("a")
    table = {a: np.array([np.nan, 3.0, 1.0, 2.0, 5.0, 4.0])}
    assert soft_min(a, alpha=1e4).value(table, {}, GRID) == pytest.approx(1.0, abs=1e-12)
    table[a][3] = np.inf
    with pytest.raises(ObjectiveError, match=r"'a' is not finite at 1 step\(s\).*step 3: inf"):
        soft_min(a).value(table, {}, GRID)
    table[a][3] = -1.0
    with pytest.raises(ObjectiveError, match=r"step 3 has -1\.0"):
        soft_min(a, kind="harmonic").value(table, {}, GRID)
    with pytest.raises(Exception, match="alpha > 0"):
        soft_min(a, alpha=0.0)
    with pytest.raises(ObjectiveError, match="refers to steps"):
        soft_min(a, [7]).requirements(GRID)


@pytest.mark.parametrize("kind", ["harmonic", "logsumexp"])
def test_min_distance_target_gradient(kind):
    """PolyFEM's min-dist-target: the centre of mass should pass through a point."""
    sim = simulation(SCENE, "bdf2")
    J = min_distance_target(sim.model, [1.3, 0.3], steps=[1, 2, 3], kind=kind, alpha=200.0)
    _fd_check(sim, J, ["initial-v0", "young-field-log", "shape-all"])


# -- signed distance ---------------------------------------------------------------------------
def test_sdf_target_value_and_gradient():
    sim = simulation(SCENE, "bdf2")
    model = sim.model
    own = _run(sim)
    # at rest: int_[0,2]x[0,0.5] (y - 0.25)^2 = 2 * 2 * 0.25^3 / 3
    s = sdf_target(model, lambda x: x[1] - 0.25)
    assert series_values(sim, s, own, steps=[0]) == pytest.approx([0.25**3 * 4 / 3], rel=1e-12)
    c = ufl.as_vector([1.0, 1.5])
    circle = sdf_target(model, lambda x: ufl.sqrt(ufl.dot(x - c, x - c)) - 1.2, facets=[2, 3])
    _fd_check(sim, time_integral(circle, "uniform"), ["young-field-log", "shape-all"])
    with pytest.raises(Exception, match="UFL scalar"):
        sdf_target(model, lambda x: x)


# -- compliance ----------------------------------------------------------------------------------
def test_compliance_is_twice_the_strain_energy_of_a_linear_static_solve():
    """Clapeyron: at a linear static equilibrium f . u = a(u, u) = 2 W."""
    sim = simulation("2d-p1-lin-cg1-ps", "static")
    model = sim.model
    traj = _run(sim)
    elastic = [t for t in model.terms if type(t).__name__ == "ElasticEnergy"]
    energy = Integral(lambda f: sum(t.energy_density(f) * t.measure(f) for t in elastic), "W")
    W, work = series_values(sim, [energy, compliance(model)], traj, steps=[-1])[0]
    assert work > 0 and work == pytest.approx(2 * W, rel=1e-10)
    gravity = series_values(sim, compliance(model, ["gravity"]), traj, steps=[-1])
    traction = series_values(sim, compliance(model, ["traction_2"]), traj, steps=[-1])
    assert gravity + traction == pytest.approx([work], rel=1e-12)
    with pytest.raises(Exception, match=r"no load named \['wind'\]"):
        compliance(model, ["wind"])


def test_compliance_gradient():
    sim = simulation("2d-p1-lin-cg1-ps", "static")
    _fd_check(sim, final_value(compliance(sim.model)), ["young-field-log", "shape-all"])


# -- barriers ------------------------------------------------------------------------------------
def test_log_barrier_matches_the_scalar_one():
    mesh = simulation(SCENE, "bdf2").model.domain.mesh
    for z in (0.01, 0.3, 0.5, 0.7):
        c = fem.Constant(mesh, z)
        expr = fem.Expression(log_barrier(c, 0.5), np.zeros((1, 2)))
        value = expr.eval(mesh, np.array([0], dtype=np.int32)).ravel()[0]
        assert value == pytest.approx(float(scalar_log_barrier(z, 0.5)), rel=1e-13, abs=0.0)
    assert float(scalar_log_barrier(0.5, 0.5)) == 0.0
    assert np.isnan(scalar_log_barrier(-0.1, 0.5))


def test_sdf_barrier_deformed_gradient_and_rest_gradient():
    sim = simulation(SCENE, "bdf2")
    model = sim.model
    floor = sdf_barrier(model, lambda x: x[1] + 0.5, 0.6, facets=[2])  # below the bar
    rest = sdf_barrier(model, lambda x: 2.3 - x[0], 0.5, bodies=[2], deformed=False)
    rf = ReducedFunctional(sim, rest, [CONTROLS["shape-all"](sim)])
    assert rf(rf.initial_parameters()) > 0  # the right end within 0.5 of the wall at 2.3
    _fd_check(sim, time_integral(floor, "uniform") + rest, ["young-field-log", "shape-all"])


def test_inversion_barriers_gradient_and_the_step_of_an_inverted_state():
    sim = simulation(SCENE, "bdf2")
    model = sim.model
    squash = inversion_barrier(model, 0.3, 0.8)  # det F ~ 1: active
    rest = inversion_barrier(model, 0.5, 0.6, deformed=False)  # ratio 1 at the initial design
    J = time_integral(squash, "uniform") + rest
    _fd_check(sim, J, ["young-field-log", "shape-all"])
    impossible = inversion_barrier(model, 1.5, 0.1)
    rf = ReducedFunctional(sim, time_integral(impossible, [2, 3]), [CONTROLS["initial-v0"](sim)])
    message = r"'inversion barrier' is not finite at 2 step.*step 2"
    with pytest.raises(ObjectiveError, match=message):
        rf(rf.initial_parameters())


def test_series_barrier_on_the_height():
    sim = simulation(SCENE, "bdf2")
    height = -height_objective(sim.model)
    J = time_integral(series_barrier(height, 0.2, 0.1), "uniform")
    value, _ = _fd_check(sim, J, ["initial-v0", "young-field-log"])
    assert value > 0


def test_step_values_missing_states_and_the_step_that_uses_one():
    """NaN marks a state without data: fine where the weight is zero, named where it is not."""
    with pytest.raises(ObjectiveError, match=r"1 are infinite \(state 2: inf\)"):
        StepValues([0.0, 1.0, np.inf], "height")
    a = _leaf("a")
    table = {a: np.array([np.nan, 1.0, 2.0, 3.0, 4.0, 5.0])}
    target = StepValues([np.nan, 1.5, 1.5, np.nan, 1.5, 1.5], "target")
    misfit = (a - target) ** 2
    assert time_integral(misfit, [1, 2, 4, 5]).value(table, {}, GRID) == pytest.approx(
        0.25 + 0.25 + 6.25 + 12.25
    )
    out = {}
    time_integral(misfit, [1, 2, 4, 5]).backward(table, {}, GRID, 1.0, out, {})
    assert np.array_equal(out[a], [0.0, -1.0, 1.0, 0.0, 5.0, 7.0])
    with pytest.raises(ObjectiveError, match=r"not finite at 1 step\(s\) .*\(step 3: nan\)"):
        time_integral(misfit, "uniform").value(table, {}, GRID)
    with pytest.raises(ObjectiveError, match=r"step 3: nan"):
        soft_min(misfit).value(table, {}, GRID)


# -- the IPC barrier of the rest shape -------------------------------------------------------------
def _geometry_fd(model, reg, direction, h=1e-6):
    x = model.domain.mesh.geometry.x
    x0 = x.copy()
    try:
        x[:, :2] = x0[:, :2] + h * direction
        plus = reg.evaluate(model)
        x[:, :2] = x0[:, :2] - h * direction
        minus = reg.evaluate(model)
    finally:
        x[:] = x0
    return (plus - minus) / (2 * h)


def test_rest_collision_barrier_values_and_geometry_derivative():
    """Bar of height 0.5 with boundary edges of 0.25 and 0.5: a corner vertex and the second
    edge along the side are 0.25 apart (not adjacent), the top and bottom sides 0.5."""
    sim = simulation(SCENE, "bdf2")
    model = sim.model
    assert RestCollisionBarrier(model, 0.2).evaluate(model) == 0.0
    assert RestCollisionBarrier(model, 0.2).smallest_distance() == np.inf
    assert RestCollisionBarrier(model, 0.3).smallest_distance() == pytest.approx(0.25, rel=1e-12)
    x = model.domain.mesh.geometry.x
    x0 = x.copy()
    try:  # a jittered design (see the next test)
        x[:, :2] += 0.03 * np.random.default_rng(9).uniform(-1, 1, (len(x), 2))
        _check_rest_barrier_gradient(model)
    finally:
        x[:] = x0


def _check_rest_barrier_gradient(model):
    reg = RestCollisionBarrier(model, 0.6, stiffness=2.0)
    value = reg.evaluate(model)
    assert value > 0
    # the geometry nodes are the P1 shape dofs (serial): compare along random motions
    g = reg.gradient(model)["shape"].reshape(-1, 2)
    S = model.shape_space
    node_of = np.empty(len(g), dtype=np.int64)
    node_of[S.dofmap.list.ravel()] = model.domain.mesh.geometry.dofmaps[0].ravel()
    rng = np.random.default_rng(2)
    for _ in range(2):
        d = 0.01 * rng.standard_normal((len(g), 2))
        direction = np.zeros((len(g), 2))
        direction[node_of] = d
        assert np.sum(g * d) == pytest.approx(_geometry_fd(model, reg, direction), rel=1e-6)
    direction = np.zeros((len(g), 2))
    direction[node_of] = 0.01 * g / np.linalg.norm(g)
    assert np.sum(g * 0.01 * g / np.linalg.norm(g)) == pytest.approx(
        _geometry_fd(model, reg, direction), rel=1e-6
    )


def test_rest_collision_barrier_in_a_shape_gradient_and_touching_designs():
    """On a jittered design: on the structured grid every closest point is an edge's end, where
    the distance changes type (C^1 only), which central differences resolve at O(h) only."""
    sim = simulation(SCENE, "bdf2")
    model = sim.model
    x = model.domain.mesh.geometry.x
    x0 = x.copy()
    free = ~np.isclose(x0[:, 0], 0.0)  # the clamped end stays
    try:
        x[free, :2] += 0.03 * np.random.default_rng(8).uniform(-1, 1, (free.sum(), 2))
        J = final_value(target_positions(model, lambda x: 1.01 * x[:2], facets=3))
        J = J + 1e-2 * RestCollisionBarrier(model, 0.6)
        _fd_check(sim, J, ["shape-all", "young-field-log"])
    finally:
        x[:] = x0
    x0 = x.copy()
    top = np.isclose(x0[:, 1], 0.5) & np.isclose(x0[:, 0], 1.0)
    try:
        x[top, 1] = 0.0  # the middle of the top side pushed down onto the bottom side
        with pytest.raises(ObjectiveError, match="rest collision barrier"):
            RestCollisionBarrier(model, 0.6).evaluate(model)
    finally:
        x[:] = x0


# -- per-step values of an objective -------------------------------------------------------------
def test_step_values_of_an_objective_are_public_and_finite_at_every_state():
    sim = simulation(SCENE, "bdf2")
    model = sim.model
    target = target_trajectory(sim, _target_run(sim, 1.2), facets=[2])
    rate = Integral(lambda f: ufl.dot(f.u - f.u_prev, f.u - f.u_prev) * f.dx, "rate")
    J = 10.0 * time_integral(target, "uniform") + time_integral(rate, "sum")
    J = J + soft_min(-height_objective(model), alpha=50.0)
    rf = ReducedFunctional(sim, J, [CONTROLS["initial-v0"](sim)])
    with pytest.raises(ObjectiveError, match="no forward run yet"):
        step_values(rf)
    value = rf(rf.initial_parameters())
    per_step = step_values(rf)
    labels = list(per_step)
    assert labels[:2] == ["target trajectory", "rate"] and len(labels) == 3
    for values in per_step.values():
        assert values.shape == (4,) and np.all(np.isfinite(values))
    assert per_step["rate"][0] == 0.0  # state 0: no motion before the start
    grid = rf.grid
    by_steps = 10.0 * step_weights("uniform", grid) @ per_step["target trajectory"]
    by_steps += step_weights("sum", grid) @ per_step["rate"]
    height = per_step[labels[2]][1:]
    by_steps += -np.log(np.sum(np.exp(-50.0 * height))) / 50.0
    assert by_steps == pytest.approx(value, rel=1e-12)
    terms = rf.term_values()
    assert any(label.startswith("softmin(") for label in terms)
    # a checkpointed run keeps u^0 and u^N only: refused, not evaluated on the wrong states
    rf = ReducedFunctional(
        sim, J, [CONTROLS["initial-v0"](sim)], checkpointing=Checkpointing("memory", snaps=2)
    )
    assert rf(rf.initial_parameters()) == pytest.approx(value, rel=1e-12)
    with pytest.raises(CheckpointingError, match=r"state 1 is not held"):
        step_values(rf)


def test_deformed_collision_barrier_partials():
    """PolyFEM's deformed_collision_barrier at a state of the run: dJ/du and dJ/dX against
    central differences of its value along random directions and along the gradients, the
    series along a trajectory, and an intersecting state refused naming its time."""
    sim = simulation(SCENE, "bdf2")
    model = sim.model
    u = model.fields.u
    x = model.domain.mesh.geometry.x
    x0, u_saved = x.copy(), u.x.array.copy()
    rng = np.random.default_rng(12)
    try:
        x[:, :2] += 0.03 * rng.uniform(-1, 1, (len(x), 2))  # off the grid's degenerate pairs
        own = _run(sim)
        barrier = DeformedCollisionBarrier(model, 0.6, stiffness=3.0)
        values = series_values(sim, barrier, own)
        assert np.all(values > 0) and not np.allclose(values, values[0])
        u.x.array[:] = own.u[-1]
        g = barrier.state_gradient(model)
        owned = model.V.dofmap.index_map.size_local * 2
        assert np.all(g[owned:] == 0.0)

        def along_u(d, h=1e-6):
            u.x.array[:] = own.u[-1] + h * d
            plus = barrier.evaluate(model)
            u.x.array[:] = own.u[-1] - h * d
            minus = barrier.evaluate(model)
            u.x.array[:] = own.u[-1]
            return (plus - minus) / (2 * h)

        for d in (0.01 * rng.standard_normal(len(g)), 0.01 * g / np.linalg.norm(g)):
            assert g @ d == pytest.approx(along_u(d), rel=1e-6)
        # shape: at fixed u, the positions move with X
        G = barrier.shape_gradient(model).reshape(-1, 2)
        S = model.shape_space
        node_of = np.empty(len(G), dtype=np.int64)
        node_of[S.dofmap.list.ravel()] = model.domain.mesh.geometry.dofmaps[0].ravel()
        for d in (0.01 * rng.standard_normal(G.shape), 0.01 * G / np.linalg.norm(G)):
            direction = np.zeros_like(d)
            direction[node_of] = d
            assert np.sum(G * d) == pytest.approx(_geometry_fd(model, barrier, direction), rel=1e-6)
        # the right half folded down (y -> -y beyond x = 1): its top side crosses the bottom
        X = model.V.tabulate_dof_coordinates()
        fold = X[:, 0] > 1.01
        u.x.array.reshape(-1, 2)[fold, 1] = -2.0 * X[fold, 1]
        model.fields.t.value = 0.1
        with pytest.raises(ObjectiveError, match=r"deformed collision barrier at t = 0.1"):
            barrier.evaluate(model)
        with pytest.raises(ObjectiveError, match="numeric code, not a UFL form"):
            barrier.form(model.fields)
    finally:
        x[:] = x0
        u.x.array[:] = u_saved
        model.fields.t.value = 0.0


def _numeric_leaves_supported(sim, objective, controls) -> ReducedFunctional:
    """The ReducedFunctional, or a skip while it cannot evaluate numeric leaves."""
    try:
        return ReducedFunctional(sim, objective, controls)
    except ObjectiveError as e:
        if "numeric code, not a UFL form" not in str(e):
            raise
        pytest.skip("the ReducedFunctional does not evaluate numeric objective leaves yet")


def test_deformed_collision_barrier_gradient():
    """Through the adjoint: E field, shape and v0 against central differences along random
    directions and the gradient, with a UFL target in the same objective and on steps 0, 3."""
    sim = simulation(SCENE, "bdf2")
    model = sim.model
    x = model.domain.mesh.geometry.x
    x0 = x.copy()
    free = ~np.isclose(x0[:, 0], 0.0)
    try:
        x[free, :2] += 0.03 * np.random.default_rng(8).uniform(-1, 1, (free.sum(), 2))
        barrier = DeformedCollisionBarrier(model, 0.6)
        target = final_value(target_positions(model, lambda x: 1.01 * x[:2], facets=3))
        J = time_integral(barrier, "uniform") + target
        _numeric_leaves_supported(sim, J, [CONTROLS["initial-v0"](sim)])
        _fd_check(sim, J, ["young-field-log", "shape-all", "initial-v0"])
        _fd_check(sim, time_integral(barrier, [0, 3]), ["shape-all", "initial-v0"])
    finally:
        x[:] = x0
