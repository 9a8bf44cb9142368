"""Objectives: expression-tree algebra and time weights, the objective library (paper sec. 9.2)
against central finite differences of the full simulation, and the discrete regularisers
(sec. 9.3, appendix F) against finite differences of their values."""

import numpy as np
import pytest
import ufl
from gradient_scenes import scene_model, simulation
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import ParameterControl, ShapeControl
from diffsolids.mesh import create_box, create_rectangle
from diffsolids.objectives import (
    BoundarySmoothing,
    Integral,
    MaterialSmoothing,
    ObjectiveError,
    Regulariser,
    StepValues,
    TimeGrid,
    boundary_graph_fit,
    center_of_mass,
    center_of_mass_trajectory,
    final_value,
    height_objective,
    step_weights,
    stress_bound_penalty,
    stress_lp_norm,
    target_displacement,
    target_positions,
    time_integral,
    volume_penalty,
)
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.verification import finite_difference_check, taylor_test

FD_TOLERANCE = 1e-6


# -- algebra of series and objectives (no PDE) ---------------------------------------------
class _Reg(Regulariser):
    """A regulariser with a prescribed value (its value table entry)."""


def _leaf(name):
    return Integral(lambda f: None, name)


def _central(fn, x, h=1e-6):
    return (fn(x + h) - fn(x - h)) / (2 * h)


GRID = TimeGrid(num_steps=4, dt=0.25, dynamic=True)


def _tree():
    a, b = _leaf("a"), _leaf("b")
    reg = _Reg()
    s = a * b / (1.0 + a**2) - 0.5 * b + (2.0 - a) / b
    J = (
        time_integral(s, "trapezoidal") * final_value(b)
        + time_integral(a, [1, -2]) ** 2 / (2.0 + final_value(a.apply(np.sin, np.cos, "sin")))
        - 3.0 * reg
        + reg**2
        + (1.0 - final_value(b)) ** 3
        + time_integral(a, "uniform") / time_integral(b.apply(np.exp, np.exp), np.linspace(0, 1, 5))
    )
    return J, a, b, reg


def _table(a, b, rng):
    return {a: rng.uniform(0.5, 1.5, 5), b: rng.uniform(0.5, 1.5, 5)}


def test_series_values_elementwise():
    a, b = _leaf("a"), _leaf("b")
    rng = np.random.default_rng(1)
    table = _table(a, b, rng)
    x, y = table[a], table[b]
    cases = [
        (a + b, x + y),
        (a - 2.0, x - 2.0),
        (2.0 - a, 2.0 - x),
        (3.0 / a, 3.0 / x),
        (a / b, x / y),
        (a * b * 2.0, 2 * x * y),
        (a**3, x**3),
        (-b, -y),
        (a.apply(np.exp, np.exp), np.exp(x)),
    ]
    for series, expected in cases:
        assert np.allclose(series.values(table), expected, rtol=1e-14)


def test_chain_rule_matches_finite_differences():
    """Backward pass of a tree with sums, products, quotients, powers and mapped nodes."""
    J, a, b, reg = _tree()
    rng = np.random.default_rng(2)
    table = _table(a, b, rng)
    regs = {reg: 0.7}
    assert set(J.leaves()) == {a, b}
    assert J.regularisers() == [reg, reg]
    out, reg_out = {}, {}
    J.backward(table, regs, GRID, 1.0, out, reg_out)
    for leaf in (a, b):
        for i in range(GRID.num_steps + 1):

            def J_of(v, leaf=leaf, i=i):
                t = {k: arr.copy() for k, arr in table.items()}
                t[leaf][i] = v
                return J.value(t, regs, GRID)

            fd = _central(J_of, table[leaf][i])
            assert out[leaf][i] == pytest.approx(fd, rel=1e-7, abs=1e-9)
    fd_reg = _central(lambda v: J.value(table, {reg: v}, GRID), 0.7)
    assert reg_out[reg] == pytest.approx(fd_reg, rel=1e-8)
    # the weights are not all trivial
    assert np.count_nonzero(out[a]) >= 4


def test_unevaluated_steps_do_not_pollute():
    """NaN at steps of zero weight (never evaluated) leave J and its gradient finite."""
    a = _leaf("a")
    J = time_integral(a**2, "uniform") + final_value(1.0 / a)
    table = {a: np.array([np.nan, 1.0, 2.0, 3.0, 4.0])}
    assert J.requirements(GRID) == {a: {1, 2, 3, 4}}
    value = J.value(table, {}, GRID)
    assert value == pytest.approx(0.25 * (1 + 4 + 9 + 16) + 0.25)
    out = {}
    J.backward(table, {}, GRID, 1.0, out, {})
    assert out[a][0] == 0.0
    assert np.all(np.isfinite(out[a]))


def test_step_weights():
    n, dt = GRID.num_steps, GRID.dt
    assert np.array_equal(step_weights("uniform", GRID), [0, dt, dt, dt, dt])
    assert np.array_equal(step_weights("trapezoidal", GRID), [dt / 2, dt, dt, dt, dt / 2])
    assert np.array_equal(step_weights("final", GRID), [0, 0, 0, 0, 1])
    assert np.array_equal(step_weights([1, -1, 1], GRID), [0, 2, 0, 0, 1])
    w = np.arange(n + 1, dtype=float)
    assert np.array_equal(step_weights(w, GRID), w)
    with pytest.raises(ObjectiveError, match="unknown time weighting 'simpson'"):
        step_weights("simpson", GRID)
    with pytest.raises(ObjectiveError, match=r"refers to steps \[5\] but the run has 0..4"):
        step_weights([5], GRID)
    with pytest.raises(ObjectiveError, match=r"refers to steps \[-6\]"):
        step_weights([-6], GRID)
    with pytest.raises(ObjectiveError, match=r"expected 5 time weights, got shape \(3,\)"):
        step_weights(np.ones(3), GRID)


def test_reduced_series_in_order_and_objective_series_once_each():
    from diffsolids.objectives import objective_series, soft_min

    a, b = _leaf("a"), _leaf("b")
    sa, sb = a * a, a + b
    Ja = time_integral(sa, "uniform")
    J = 2.0 * Ja + soft_min(sb).apply(np.exp, np.exp, "exp") - final_value(b) * Ja + 1.0
    reduced = J.reduced_series()
    assert len(reduced) == 4
    assert all(x is y for x, y in zip(reduced, [sa, sb, b, sa], strict=True))
    found = list(objective_series(J).values())  # each series once, in order
    assert len(found) == 3
    assert all(x is y for x, y in zip(found, [sa, sb, b], strict=True))


def test_step_values_series():
    a = _leaf("a")
    target = StepValues([0.0, 1.0, 2.0, 3.0, 4.0], "target")
    series = (a - target) ** 2
    table = {a: np.full(5, 1.0)}
    assert np.array_equal(series.values(table), [1, 0, 1, 4, 9])
    with pytest.raises(ObjectiveError, match="target has 3 values but the run has 5 states"):
        StepValues([1.0, 2.0, 3.0], "target").values(table)
    with pytest.raises(ObjectiveError, match="finite 1D array"):
        StepValues([[1.0]])


# -- the library against finite differences of the whole simulation ---------------------------
SCENE = "2d-p1-nh-damped"


def _library(model, dynamic: bool):
    """Objectives of the library, each reduced with time weights ({name: Objective})."""
    dim = model.dim
    down = np.zeros(dim)
    down[-1] = -0.05

    def reduce(series, weights="uniform"):
        return time_integral(series, weights) if dynamic else final_value(series)

    com_target = np.column_stack([np.linspace(1.0, 1.05, 4)] + [np.full(4, 0.2)] * (dim - 1))
    return {
        "lp2": reduce(stress_lp_norm(model, 2)),
        "lp6-piola": reduce(stress_lp_norm(model, 6, "piola")),
        "lp4-von-mises-body2": reduce(stress_lp_norm(model, 4, "von_mises", bodies=[2])),
        "stress-bound": reduce(stress_bound_penalty(model, 8.0)),
        "target-displacement-boundary": reduce(
            target_displacement(model, down, weight=lambda x: 1 + x[0], facets=2), "trapezoidal"
        ),
        "target-displacement-volume": reduce(
            target_displacement(model, lambda x: 0.02 * x[:dim] ** 2, bodies=[1])
        ),
        "target-positions": reduce(
            target_positions(model, lambda x: 1.02 * x[:dim], weight=lambda x: 1 + x[1])
        ),
        "target-positions-boundary": reduce(
            target_positions(model, lambda x: x[:dim] + 0.01, facets=[2, 3])
        ),
        "com-fixed": reduce(center_of_mass_trajectory(model, np.full(dim, 0.3)), "trapezoidal"),
        "com-per-step": time_integral(center_of_mass_trajectory(model, com_target), "uniform")
        if dynamic
        else final_value(center_of_mass_trajectory(model, com_target[-1])),
        "com-of-time": reduce(
            center_of_mass_trajectory(model, lambda t: ufl.as_vector([1.0 + t] + [0.2] * (dim - 1)))
        ),
        "height": reduce(height_objective(model)),
        "com-x-body": final_value(center_of_mass(model, bodies=[2])[0]) ** 2,
        "volume-upper": volume_penalty(model, 0.9, "upper"),
        "volume-lower-deformed": volume_penalty(model, 1.1, "lower", deformed=True),
        "graph-fit": reduce(boundary_graph_fit(model, 3, lambda x: 0.5 + 0.05 * ufl.sin(x))),
    }


LIBRARY = [
    "lp2",
    "lp6-piola",
    "lp4-von-mises-body2",
    "stress-bound",
    "target-displacement-boundary",
    "target-displacement-volume",
    "target-positions",
    "target-positions-boundary",
    "com-fixed",
    "com-per-step",
    "com-of-time",
    "height",
    "com-x-body",
    "volume-upper",
    "volume-lower-deformed",
    "graph-fit",
]


def test_library_list_is_complete():
    assert list(_library(scene_model(SCENE), True)) == LIBRARY


@pytest.mark.parametrize("integrator", ["static", "bdf2"])
@pytest.mark.parametrize("name", LIBRARY)
def test_library_objective_gradient(name, integrator):
    """dJ.dq of each objective vs central differences (E field and shape), random and along g."""
    sim = simulation(SCENE, integrator)
    model = sim.model
    objective = _library(model, sim.integrator.dynamic)[name]
    controls = [ParameterControl(model, "E", "field", log=True), ShapeControl(model, "all")]
    rf = ReducedFunctional(sim, objective, controls)
    q0 = rf.initial_parameters()
    try:
        J0, g = rf.value_and_gradient(q0)
        assert np.isfinite(J0)
        rng = np.random.default_rng(3)
        n_e = controls[0].size
        d = np.concatenate(
            [0.05 * rng.standard_normal(n_e), 0.005 * rng.standard_normal(q0.size - n_e)]
        )
        steps = np.array([1e-1, 1e-2, 1e-3])
        res = finite_difference_check(rf, q0, d, steps, gradient=g)
        assert abs(res.adjoint) > 1e-12, res
        assert res.relative_error <= FD_TOLERANCE, res
        # along the gradient (shape part scaled to a small vertex motion)
        h = min(0.05 / max(np.linalg.norm(g[:n_e]), 1e-300), 0.02 / np.linalg.norm(g[n_e:]))
        res = finite_difference_check(rf, q0, h * g, steps, gradient=g)
        assert res.relative_error <= FD_TOLERANCE, res
    finally:
        rf.controls.assign(q0)


def test_objective_values():
    """Values computed by hand on the rest configuration u^0 = 0."""
    model = scene_model(SCENE)  # [0, 2] x [0, 0.5], density 1 (x < 1) and 1.5 (x > 1)
    sim = simulation(SCENE, "static")

    def value(objective):
        rf = ReducedFunctional(sim, objective, [ParameterControl(model, "gravity", "uniform")])
        return rf(rf.initial_parameters())

    # masses 0.5 at x = 0.5 and 0.75 at x = 1.5, both at y = 0.25
    com = center_of_mass(model)
    assert value(time_integral(com[0] + com[1], [0])) == pytest.approx(1.1 + 0.25, rel=1e-12)
    assert value(time_integral(height_objective(model), [0])) == pytest.approx(-0.25, rel=1e-12)
    # rest volume 1.0
    assert value(volume_penalty(model, 0.9, "upper")) == pytest.approx(0.01, rel=1e-10)
    assert value(volume_penalty(model, 0.9, "lower")) == 0.0
    assert value(volume_penalty(model, 1.2, "lower")) == pytest.approx(0.04, rel=1e-10)
    disp = target_displacement(model, [0.0, -0.1], weight=2.0, facets=2)
    assert value(time_integral(disp, [0])) == pytest.approx(2.0 * 0.01 * 0.5, rel=1e-12)


# -- regularisers ----------------------------------------------------------------------------
def _unit_square_two_cells():
    return ds.Model(
        create_rectangle(
            MPI.COMM_SELF, [[0, 0], [1, 1]], [1, 1], bodies={2: lambda m: m[0] > m[1]}
        ),
        ds.LinearElastic(E=1.0, nu=0.3),
    )


def test_boundary_smoothing_hand_values():
    """Unit square: s_i = (-1/2, -1/2) at every corner, so J = 4 (1/2)^(p/2)."""
    model = _unit_square_two_cells()
    assert BoundarySmoothing(model, 2.0).evaluate(model) == pytest.approx(2.0, rel=1e-14)
    assert BoundarySmoothing(model, 3.0).evaluate(model) == pytest.approx(4 * 0.5**1.5, rel=1e-14)


def test_laplacian_boundary_smoothing_hand_value_and_scaling():
    """Unit square: each corner is (1/2, 1/2) from the mean of its two neighbours: J = 4/2."""
    model = _unit_square_two_cells()
    reg = BoundarySmoothing(model, scale_invariant=False)
    assert reg.evaluate(model) == pytest.approx(2.0, rel=1e-14)
    x = model.domain.mesh.geometry.x
    x0 = x.copy()
    x[:, :2] *= 3.0  # PolyFEM's non-scale-invariant form grows with the size squared
    assert reg.evaluate(model) == pytest.approx(18.0, rel=1e-14)
    x[:] = x0


def test_boundary_smoothing_scale_invariant_and_zero_when_even():
    dom = create_rectangle(MPI.COMM_SELF, [[0, 0], [2, 1]], [6, 3])
    model = ds.Model(dom, ds.LinearElastic(E=1.0, nu=0.3))
    reg = BoundarySmoothing(model, 2.0)
    value = reg.evaluate(model)
    assert value == pytest.approx(2.0, rel=1e-13)  # straight evenly sampled edges: corners only
    x = dom.mesh.geometry.x
    x0 = x.copy()
    x[:, :2] = 3.7 * x[:, :2] + np.array([1.0, -2.0])
    assert reg.evaluate(model) == pytest.approx(value, rel=1e-13)
    x[:] = x0


def _perturbed_geometry_fd(model, reg, direction, h):
    x = model.domain.mesh.geometry.x
    d = model.dim
    x0 = x.copy()
    x[:, :d] = x0[:, :d] + h * direction
    jp = reg.evaluate(model)
    x[:, :d] = x0[:, :d] - h * direction
    jm = reg.evaluate(model)
    x[:] = x0
    return (jp - jm) / (2 * h)


def _shape_gradient_per_node(model, grad):
    """Regulariser gradient on the shape space -> per geometry node (serial)."""
    S = model.shape_space
    mesh = model.domain.mesh
    node = np.empty(len(mesh.geometry.x), dtype=np.int64)
    node[S.dofmap.list.ravel()] = mesh.geometry.dofmaps[0].ravel()
    out = np.zeros((len(mesh.geometry.x), model.dim))
    out[node] = grad.reshape(-1, model.dim)
    return out


@pytest.mark.parametrize(
    ("dim", "p", "exclude", "scale_invariant"),
    [
        (2, 2.0, (), True),
        (2, 3.5, (1,), True),
        (3, 2.0, (), True),
        (3, 1.5, (1,), True),
        (2, 2.0, (1,), False),
        (3, 2.0, (), False),
    ],
)
def test_boundary_smoothing_gradient(dim, p, exclude, scale_invariant):
    facets = {1: lambda x: np.isclose(x[0], 0.0)}
    if dim == 2:
        dom = create_rectangle(MPI.COMM_SELF, [[0, 0], [2, 1]], [5, 3], facets=facets)
    else:
        dom = create_box(MPI.COMM_SELF, [[0, 0, 0], [2, 1, 1]], [3, 2, 2], facets=facets)
    model = ds.Model(dom, ds.LinearElastic(E=1.0, nu=0.3))
    x = dom.mesh.geometry.x
    rng = np.random.default_rng(4)
    x[:, :dim] += 0.03 * rng.standard_normal((len(x), dim))  # a rough surface: s_i != 0
    reg = BoundarySmoothing(model, p, exclude_facets=exclude, scale_invariant=scale_invariant)
    G = _shape_gradient_per_node(model, reg.gradient(model)["shape"])
    assert np.abs(G).max() > 0
    if exclude:
        fixed = np.unique(_facet_nodes(dom, 1))
        assert np.all(G[fixed] == 0.0)
    for direction in (rng.standard_normal((len(x), dim)), G):
        fd = _perturbed_geometry_fd(model, reg, direction, 1e-6 / np.abs(direction).max())
        assert np.sum(G * direction) == pytest.approx(fd, rel=1e-7)


def _facet_nodes(dom, tag):
    import dolfinx.mesh

    mesh = dom.mesh
    return dolfinx.mesh.entities_to_geometry(mesh, mesh.topology.dim - 1, dom.facets_of(tag))


def test_material_smoothing_hand_value_and_uniform():
    model = _unit_square_two_cells()
    reg = MaterialSmoothing(model, ["E"])
    assert reg.evaluate(model) == 0.0
    assert np.all(reg.gradient(model)["E"] == 0.0)
    E = model.coefficients["E"]
    E.x.array[:] = [2.0, 5.0]
    assert reg.evaluate(model) == pytest.approx((1 - 5 / 2) ** 2 + (1 - 2 / 5) ** 2, rel=1e-14)
    assert reg.pairs.shape == (1, 2)


@pytest.mark.parametrize("dim", [2, 3])
def test_material_smoothing_gradient(dim):
    if dim == 2:
        dom = create_rectangle(MPI.COMM_SELF, [[0, 0], [2, 1]], [4, 3])
    else:
        dom = create_box(MPI.COMM_SELF, [[0, 0, 0], [1, 1, 1]], [2, 2, 2])
    model = ds.Model(dom, ds.NeoHookean(lmbda=2.0, mu=1.0))
    rng = np.random.default_rng(5)
    for name in ("lmbda", "mu"):
        model.coefficients[name].x.array[:] *= rng.uniform(
            0.5, 2.0, model.coefficients[name].x.array.size
        )
    reg = MaterialSmoothing(model)
    assert reg.names == ("lmbda", "mu")
    grads = reg.gradient(model)
    for name in reg.names:
        arr = model.coefficients[name].x.array
        for direction in (rng.standard_normal(arr.size), grads[name]):
            h = 1e-6 / np.abs(direction).max()
            arr += h * direction
            jp = reg.evaluate(model)
            arr -= 2 * h * direction
            jm = reg.evaluate(model)
            arr += h * direction
            assert np.dot(grads[name], direction) == pytest.approx((jp - jm) / (2 * h), rel=1e-7)


def test_regulariser_errors():
    model = _unit_square_two_cells()
    with pytest.raises(ds.ParameterError, match="p > 1"):
        BoundarySmoothing(model, 1.0)
    with pytest.raises(ds.ParameterError, match="no coefficient 'lmbda'"):
        MaterialSmoothing(model, ["lmbda"])
    with pytest.raises(ds.ParameterError, match="'gravity' needs a scalar DG0 field"):
        model.add_gravity(1.0)
        MaterialSmoothing(model, ["gravity"])
    other = _unit_square_two_cells()
    with pytest.raises(ObjectiveError, match="built for a different model"):
        MaterialSmoothing(model, ["E"]).evaluate(other)
    model.coefficients["E"].x.array[0] = 0.0
    with pytest.raises(ObjectiveError, match="finite nonzero values"):
        MaterialSmoothing(model, ["E"]).evaluate(model)


@pytest.mark.parametrize("integrator", ["static", "bdf1"])
def test_regularisers_in_reduced_functional(integrator):
    """Objective + weighted regularisers through the controls' chain rule (log E per body)."""
    sim = simulation(SCENE, integrator)
    model = sim.model
    objective = (
        final_value(target_displacement(model, [0.0, -0.05], facets=2))
        + 1e-3 * BoundarySmoothing(model, 2.0, exclude_facets=[1])
        + 1e-2 * MaterialSmoothing(model, ["E", "nu"]) ** 2
    )
    controls = [
        ShapeControl(model, "boundary", exclude_facets=[1]),
        ParameterControl(model, "E", "field", log=True),
        ParameterControl(model, "nu", "bodies"),
    ]
    rf = ReducedFunctional(sim, objective, controls)
    q0 = rf.initial_parameters()
    try:
        rng = np.random.default_rng(6)
        g = rf.gradient(q0)
        d = rng.standard_normal(q0.size) * 0.02
        for direction in (d, g * (0.02 / np.abs(g).max())):
            res = finite_difference_check(rf, q0, direction, [1e-1, 1e-2, 1e-3], gradient=g)
            assert res.relative_error <= FD_TOLERANCE, res
        taylor = taylor_test(rf, q0, d, h0=0.5, num=3)
        assert taylor.min_rate >= 1.9, taylor
    finally:
        rf.controls.assign(q0)


@pytest.mark.parametrize("plane_stress", [False, True])
def test_von_mises_objective_is_the_3d_von_mises_stress(plane_stress):
    """L4 norm of the von Mises stress of a uniform state = |area|^(1/4) times the von Mises
    stress of the 3x3 Cauchy stress (plane strain: with its sigma_zz; computed with numpy)."""
    from dolfinx import fem
    from output_checks import expected_von_mises, gradient, model_on

    from diffsolids.solvers.forms import compile_form

    dom = create_rectangle(MPI.COMM_SELF, [[0, 0], [2, 1]], [2, 2])
    model = model_on(dom, 1, plane_stress=plane_stress)
    G = gradient(2)
    model.fields.u.interpolate(lambda x: 1.5 * G @ x[:2])
    (leaf,) = stress_lp_norm(model, 4, "von_mises").leaves()
    integral = fem.assemble_scalar(compile_form(leaf.form(model.fields)))
    expected = expected_von_mises(2, 1.5, plane_stress)
    assert integral**0.25 == pytest.approx(2.0**0.25 * expected, rel=1e-10)


@pytest.mark.parametrize("law", ["neo_hookean", "st_venant_kirchhoff"])
@pytest.mark.parametrize("dim", [2, 3])
def test_written_out_cauchy_stress_is_p_ft_over_j(law, dim):
    """The closed-form Cauchy stress of each finite-strain law equals dpsi/dF F^T / J."""
    from dolfinx import fem

    from diffsolids import forms
    from diffsolids.solvers.forms import compile_form

    dom = (create_rectangle if dim == 2 else create_box)(
        MPI.COMM_SELF, [[0.0] * dim, [1.0] * dim], [2] * dim
    )
    V = fem.functionspace(dom.mesh, ("Lagrange", 2, (dim,)))
    u = fem.Function(V)
    u.interpolate(
        lambda x: 0.2 * np.array([np.sin(2 * x[k] + k) * x[(k + 1) % dim] for k in range(dim)])
    )
    lmbda, mu = 3.0, 1.5
    F = forms.deformation_gradient(u)
    reference = forms.first_piola_kirchhoff(law, u, lmbda, mu) * F.T / ufl.det(F)
    sigma = forms.cauchy_stress(law, u, lmbda, mu)
    diff = sigma - reference
    dx = ufl.dx(domain=dom.mesh)
    err = fem.assemble_scalar(compile_form(ufl.inner(diff, diff) * dx))
    size = fem.assemble_scalar(compile_form(ufl.inner(reference, reference) * dx))
    assert size > 1e-3
    assert err <= 1e-26 * size
