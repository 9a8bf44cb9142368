"""Bad input raises a diffsolids error whose message names the problem."""

import math

import dolfinx
import numpy as np
import pytest
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import ControlError
from diffsolids.mesh import Domain, create_box, create_rectangle


@pytest.fixture(scope="module")
def square():
    """Unit square, left edge tagged 1 ("left"), right edge tagged 2; two bodies (x < 1/2: 1)."""
    return create_rectangle(
        MPI.COMM_WORLD,
        [[0, 0], [1, 1]],
        [4, 4],
        facets={1: lambda x: np.isclose(x[0], 0), 2: lambda x: np.isclose(x[0], 1)},
        bodies={1: lambda m: m[0] < 0.5, 2: lambda m: m[0] >= 0.5},
        names={"left": 1, "right": 2, "soft": 1, "hard": 2},
    )


@pytest.fixture(scope="module")
def cube():
    return create_box(
        MPI.COMM_WORLD, [[0, 0, 0], [1, 1, 1]], [2, 2, 2], facets={1: lambda x: np.isclose(x[0], 0)}
    )


# -- integrators ----------------------------------------------------------------------------------
@pytest.mark.parametrize("dt", [0.0, -0.1, math.nan, math.inf])
def test_non_positive_or_non_finite_time_step(dt):
    with pytest.raises(ds.ParameterError, match=r"time step dt = .* must be a positive finite"):
        ds.BDF(2, dt, 10)
    with pytest.raises(ds.ParameterError, match=r"time step dt = .* must be a positive finite"):
        ds.Static(num_steps=2, dt=dt)


def test_time_step_with_t_end():
    with pytest.raises(ds.ParameterError, match=r"time step dt = -0.1 must be a positive"):
        ds.BDF(1, -0.1, t_end=1.0)
    with pytest.raises(ds.ParameterError, match="give num_steps or a positive finite t_end"):
        ds.BDF(1, 0.1)
    with pytest.raises(ds.ParameterError, match="give num_steps or a positive finite t_end"):
        ds.BDF(1, 0.1, t_end=math.nan)
    assert ds.BDF(1, 0.1, t_end=1.0).num_steps == 10


@pytest.mark.parametrize("order", [0, 7, -1, 2.0, "2"])
def test_bdf_order_outside_range(order):
    with pytest.raises(ds.ParameterError, match=r"BDF order .* outside 1..6"):
        ds.BDF(order, 0.1, 10)
    with pytest.raises(ds.ParameterError, match=r"BDF order .* outside 1..6"):
        ds.bdf_coefficients(order)


@pytest.mark.parametrize("num_steps", [0, -3, 2.5])
def test_number_of_steps(num_steps):
    with pytest.raises(ds.ParameterError, match=r"num_steps = .* must be a positive integer"):
        ds.BDF(2, 0.1, num_steps)


def test_bdf_coefficients_are_consistent():
    """Sum of coefficients 1 + sum alpha = 0 (constants) and exactness for t^k, k <= m."""
    for m in range(1, 7):
        alpha, beta = ds.bdf_coefficients(m)
        steps = np.arange(m + 1)  # t_{i-j} = -j dt with dt = 1, t_i = 0
        coefficients = np.concatenate([[1.0], alpha])
        for k in range(m + 1):
            # d/dt t^k at t = 0 is 1 for k = 1 and 0 otherwise
            lhs = coefficients @ (-steps.astype(float)) ** k
            assert lhs == pytest.approx(beta if k == 1 else 0.0, abs=1e-12)


# -- materials ------------------------------------------------------------------------------------
@pytest.mark.parametrize("E", [0.0, -1.0])
def test_non_positive_young_modulus(E):
    with pytest.raises(ds.ParameterError, match=rf"Young's modulus E = {E} must be positive"):
        ds.NeoHookean(E=E, nu=0.3)


@pytest.mark.parametrize(
    ("name", "value"),
    [("E", math.nan), ("nu", math.inf), ("density", math.nan), ("damping_psi", -math.inf)],
)
def test_non_finite_parameters(name, value):
    params = {"E": 1.0, "nu": 0.3, name: value}
    with pytest.raises(ds.ParameterError, match=rf"material parameter {name} = .* is not finite"):
        ds.LinearElastic(**params)


def test_other_material_parameters():
    with pytest.raises(ds.ParameterError, match=r"shear modulus mu = 0.0 must be positive"):
        ds.NeoHookean(lmbda=1.0, mu=0.0)
    with pytest.raises(ds.ParameterError, match=r"density = -1.0 must be positive"):
        ds.NeoHookean(E=1.0, nu=0.3, density=-1.0)
    with pytest.raises(ds.ParameterError, match=r"damping parameters psi = -0.1, phi = 0.0"):
        ds.NeoHookean(E=1.0, nu=0.3, damping_psi=-0.1)
    with pytest.raises(ds.ParameterError, match=r"either as \(E, nu\) or as \(lmbda, mu\)"):
        ds.NeoHookean(E=1.0, mu=0.3)
    with pytest.raises(ds.ParameterError, match=r"either as \(E, nu\) or as \(lmbda, mu\)"):
        ds.NeoHookean(E=1.0)
    with pytest.raises(ds.ParameterError, match=r"unknown constitutive law 'mooney'"):
        ds.Material("mooney", E=1.0, nu=0.3)


@pytest.mark.parametrize(
    ("dim", "plane_stress", "nu", "bad"),
    [
        (3, False, 0.5, True),
        (3, False, -1.0, True),
        (3, False, 0.49, False),
        (2, False, 0.5, True),
        (2, False, 0.7, True),
        (2, True, 0.7, False),  # plane stress allows nu up to 1
        (2, True, 1.0, True),
        (2, True, -1.2, True),
    ],
)
def test_poisson_ratio_range(square, cube, dim, plane_stress, nu, bad):
    dom = square if dim == 2 else cube
    mat = ds.NeoHookean(E=1.0, nu=nu)
    if not bad:
        model = ds.Model(dom, mat, plane_stress=plane_stress)
        assert model.plane_stress == plane_stress
        return
    model_name = "plane stress" if plane_stress else f"{dim}D/plane strain"
    upper = 1.0 if plane_stress else 0.5
    with pytest.raises(
        ds.ParameterError,
        match=rf"nu = {nu} is outside the physical range \(-1, {upper}\) for {model_name}",
    ):
        ds.Model(dom, mat, plane_stress=plane_stress)


def test_negative_bulk_modulus(cube):
    with pytest.raises(ds.ParameterError, match="lmbda \\+ 2 mu / 3"):
        ds.Model(cube, ds.NeoHookean(lmbda=-1.0, mu=1.0))


def test_parameter_fields_are_validated(square):
    Q = dolfinx.fem.functionspace(square.mesh, ("DG", 0))
    E = dolfinx.fem.Function(Q)
    E.x.array[:] = 1.0
    E.x.array[0] = np.nan
    with pytest.raises(ds.ParameterError, match="parameter field E has 1 non-finite values"):
        ds.Model(square, ds.NeoHookean(E=1.0, nu=0.3), fields={"E": E})
    E.x.array[0] = -2.0
    with pytest.raises(ds.ParameterError, match=r"field E has 1 values outside .* \(0, inf\)"):
        ds.Model(square, ds.NeoHookean(E=1.0, nu=0.3), fields={"E": E})
    with pytest.raises(ds.ParameterError, match=r"unknown parameter fields \['youngs'\]"):
        ds.Model(square, ds.NeoHookean(E=1.0, nu=0.3), fields={"youngs": E})


def _sag_problem(square):
    """A clamped square sagging under gravity, J its mean sag, and its parameter fields."""
    model = ds.Model(square, ds.NeoHookean(E=1e5, nu=0.3, density=10.0))
    model.add_gravity(9.81)
    model.add_dirichlet("left", 0.0)
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-10), progress=False)
    sag = ds.final_value(ds.Integral(lambda f: -f.u[1] * f.dx, "sag"))
    return model, sim, sag


def _fields(model) -> dict:
    return {name: f.x.array.copy() for name, f in model.coefficients.items()}


def test_a_refused_parameter_point_leaves_the_model_as_it_was(square):
    """A trial point with a non-physical value is refused as a whole: every parameter field
    and every control's value stay those of the last accepted point, also when another field
    of the same point was valid, and another control's problem runs on after it."""
    model, sim, sag = _sag_problem(square)
    controls = [
        ds.ParameterControl(model, "E", "uniform", log=True),
        ds.ParameterControl(model, "nu", "uniform"),
        ds.ParameterControl(model, "density", "scale"),
    ]
    rf = ds.ReducedFunctional(sim, sag, controls)
    q0 = np.array([np.log(2e5), 0.25, 2.0])
    J0 = rf(q0)
    before = _fields(model)
    for bad in ([np.log(3e5), 0.5, 2.0], [np.log(3e5), 0.3, -1.0], [np.nan, 0.3, 2.0]):
        with pytest.raises((ds.ParameterError, ControlError)):
            rf(np.array(bad))
        after = _fields(model)
        assert all(np.array_equal(after[k], before[k]) for k in before), bad
        assert np.array_equal(rf.controls.value(), q0), bad
    assert rf(q0) == J0
    # a single control assigned directly, then a problem of another control
    E_control = ds.ParameterControl(model, "E", "uniform")
    with pytest.raises(ds.ParameterError, match="field E has"):
        E_control.assign(np.array([-5.0]))
    assert np.array_equal(model.coefficients["E"].x.array, before["E"])
    other = ds.ReducedFunctional(sim, sag, ds.ParameterControl(model, "nu", "uniform"))
    assert np.isfinite(other(np.array([0.3])))


def test_a_refused_point_puts_every_control_back(square):
    """Shape, initial velocity, a Dirichlet value and an affine map over E change before E's
    field is refused: all of them, and the geometry and initial state, return to the last
    accepted point (before, the shape stayed moved and a later run used it silently)."""
    from diffsolids.controls import AffineControl, DirichletControl, InitialCondition, ShapeControl

    model = ds.Model(square, ds.NeoHookean(E=1e5, nu=0.3, density=10.0))
    model.add_gravity(9.81)
    pull = model.add_dirichlet("right", np.array([0.0, 0.0]))
    model.add_dirichlet("left", 0.0)
    sim = ds.Simulation(model, ds.BDF(1, 0.01, 2), progress=False)
    sag = ds.final_value(ds.Integral(lambda f: -f.u[1] * f.dx, "sag"))
    E = ds.ParameterControl(model, "E", "uniform")
    controls = [
        ShapeControl(model, "all"),
        InitialCondition(sim, "velocity"),
        DirichletControl(sim, pull),
        AffineControl(E, np.array([[2.0]]), np.array([1e4])),
    ]
    rf = ds.ReducedFunctional(sim, sag, controls)
    q0 = rf.initial_parameters() + 1e-4  # an accepted point away from the start
    q0[-1] = 5e4
    J0 = rf(q0)
    X0, v0 = square.mesh.geometry.x.copy(), sim.v0.copy()
    bad = q0 + 1e-3
    bad[-1] = -1e5  # E = 2 q + 1e4 < 0
    with pytest.raises(ds.ParameterError, match="field E has"):
        rf(bad)
    assert np.array_equal(rf.controls.value(), q0)
    assert np.array_equal(square.mesh.geometry.x, X0) and np.array_equal(sim.v0, v0)
    assert np.all(model.coefficients["E"].x.array == 1.1e5)
    assert rf(q0) == J0


def test_displacement_degree(square):
    with pytest.raises(ds.ParameterError, match="displacement degree 4 not supported"):
        ds.Model(square, ds.LinearElastic(E=1.0, nu=0.3), degree=4)


# -- tags -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def model(square):
    return ds.Model(square, ds.NeoHookean(E=1.0, nu=0.3))


def test_unknown_facet_tags(model):
    with pytest.raises(ds.TagError, match=r"unknown facet tag 7; the mesh has facet tags \[1, 2\]"):
        model.add_dirichlet(7, 0.0)
    with pytest.raises(ds.TagError, match=r"unknown facet tag 9; the mesh has facet tags"):
        model.add_traction(9, [1.0, 0.0])
    with pytest.raises(ds.TagError, match=r"unknown facet tag name 'top'; known names: \["):
        model.add_traction("top", [1.0, 0.0])
    with pytest.raises(ds.TagError, match=r"unknown body \(cell tag\) 5"):
        model.add_body_force([0.0, -1.0], bodies=[5])


def test_named_tags_resolve(square):
    assert square.facet_id("right") == 2
    assert square.body_id("hard") == 2
    assert len(square.cells_of("soft")) == len(square.cells_of(1)) > 0


def test_dirichlet_that_constrains_nothing(model):
    with pytest.raises(ds.TagError, match="constrains no dof"):
        model.add_dirichlet(lambda x: x[0] > 5.0, 0.0)
    with pytest.raises(ds.ParameterError, match=r"Dirichlet components \[2\] invalid"):
        model.add_dirichlet(1, 0.0, components=[2])
    with pytest.raises(ds.ParameterError, match=r"takes \(t\) or \(x, t\)"):
        model.add_dirichlet(1, lambda x, t, s: 0.0)


def test_body_without_material(square):
    with pytest.raises(ds.TagError, match=r"bodies \[2\] have no material"):
        ds.Model(square, {1: ds.NeoHookean(E=1.0, nu=0.3)})


def test_material_for_missing_body(square):
    mat = ds.NeoHookean(E=1.0, nu=0.3)
    with pytest.raises(ds.TagError, match=r"unknown body \(cell tag\) 3; the mesh has .* \[1, 2\]"):
        ds.Model(square, {1: mat, 2: mat, 3: mat})
    with pytest.raises(ds.TagError, match=r"unknown body \(cell tag\) name 'steel'"):
        ds.Model(square, {"soft": mat, "steel": mat})


def test_materials_per_body(square):
    soft, hard = ds.NeoHookean(E=1.0, nu=0.3), ds.NeoHookean(E=7.0, nu=0.2)
    model = ds.Model(square, {"soft": soft, "hard": hard})
    E = model.coefficients["E"].x.array
    assert np.all(E[square.cells_of("soft")] == 1.0)
    assert np.all(E[square.cells_of("hard")] == 7.0)
    with pytest.raises(ds.ParameterError, match="same way"):
        ds.Model(square, {"soft": soft, "hard": ds.NeoHookean(lmbda=1.0, mu=1.0)})


def test_non_finite_loads_and_initial_values(model):
    with pytest.raises(ds.ParameterError, match=r"is not finite"):
        model.add_body_force([np.nan, 0.0], name="bad_force")
    with pytest.raises(ds.ParameterError, match=r"initial displacement u0 has non-finite"):
        ds.Simulation(model, ds.Static(), u0=[np.inf, 0.0])
    with pytest.raises(ds.ParameterError, match=r"initial velocity v0 has non-finite"):
        ds.Simulation(model, ds.BDF(1, 0.1, 1), v0=[np.nan, 0.0])
    with pytest.raises(ds.ParameterError, match=r"expected a vector of length 2"):
        ds.Simulation(model, ds.Static(), u0=[1.0, 0.0, 0.0])
    with pytest.raises(ds.ParameterError, match="initial velocity needs a dynamic"):
        ds.Simulation(model, ds.Static(), v0=[1.0, 0.0])


def test_gravity_is_a_magnitude_along_an_axis(model):
    with pytest.raises(ds.ParameterError, match="use add_body_force for a vector"):
        model.add_gravity([0.0, -9.81])
    with pytest.raises(ds.ParameterError, match="finite number"):
        model.add_gravity(np.inf)
    with pytest.raises(ds.ParameterError, match="axis 2 is not an axis of a 2D mesh"):
        model.add_gravity(9.81, axis=2)
    model.add_gravity(9.81, axis=0)
    assert np.allclose(model.coefficients["gravity"].x.array.reshape(-1, 2)[0], [-9.81, 0.0])


# -- inverted input meshes -----------------------------------------------------------------------
def _moved_vertex_mesh(target):
    """A 2x2 square mesh whose centre vertex (1/2, 1/2) is moved to ``target``."""
    mesh = dolfinx.mesh.create_unit_square(MPI.COMM_SELF, 2, 2)
    x = mesh.geometry.x
    centre = np.flatnonzero(np.isclose(x[:, 0], 0.5) & np.isclose(x[:, 1], 0.5))
    assert len(centre) == 1
    x[centre[0], :2] = target
    return Domain.from_mesh(mesh)


def test_folded_input_mesh():
    # the centre vertex moved beyond the right edge: cells fold over their neighbours
    dom = _moved_vertex_mesh([1.3, 0.6])
    with pytest.raises(ds.InvertedElementError, match="inverted input mesh") as info:
        ds.Model(dom, ds.NeoHookean(E=1.0, nu=0.3))
    assert len(info.value.cells) > 0


def test_degenerate_input_mesh():
    # the centre vertex on the line through two neighbours: zero-area cells
    dom = _moved_vertex_mesh([1.0, 0.5])
    with pytest.raises(ds.InvertedElementError, match="degenerate"):
        ds.Model(dom, ds.NeoHookean(E=1.0, nu=0.3))


def test_valid_moved_vertex_mesh():
    # a small move keeps every cell valid: no error (the check is not trivially failing)
    ds.Model(_moved_vertex_mesh([0.55, 0.45]), ds.NeoHookean(E=1.0, nu=0.3))


# -- Newton failure -------------------------------------------------------------------------------
def test_newton_failure_names_step_iterations_and_residual(square):
    model = ds.Model(square, ds.NeoHookean(E=1.0, nu=0.3))
    model.add_dirichlet("left", 0.0)
    model.add_traction("right", lambda t: [0.3 * t, 0.0])
    options = ds.SolverOptions(max_iterations=1)
    sim = ds.Simulation(model, ds.Static(num_steps=3, dt=1.0), options, progress=False)
    with pytest.raises(
        ds.NewtonConvergenceError,
        match=r"Newton solve of step 1 failed after 1 iterations: residual \d\.\d{3}e[-+]\d+ "
        r"\(tolerance \d\.\d{3}e[-+]\d+\)",
    ) as info:
        sim.run()
    err = info.value
    assert (err.step, err.iterations) == (1, 1)
    assert err.residual > 0 and np.isfinite(err.residual)
    assert isinstance(err, ds.ConvergenceError)
    # the same problem solves with the default options
    traj = ds.Simulation(model, ds.Static(num_steps=3, dt=1.0), progress=False).run()
    assert all(r.iterations > 1 for r in traj.records)


class _NoStep:
    """A step bound (like the inversion guard or contact CCD) that admits no step at all."""

    def max_step(self, x, dx) -> float:
        return 0.0


def test_blocked_newton_step_is_not_success(square):
    model = ds.Model(square, ds.LinearElastic(E=10.0, nu=0.3))
    model.add_dirichlet("left", 0.0)
    model.add_traction("right", [1.0, 0.0])
    solver = ds.NewtonSolver(model, dynamic=False)
    solver.step_bounds.append(_NoStep())
    # a non-zero admissible start (from u = 0 PETSc reports DIVERGED_LINE_SEARCH instead)
    model.fields.u.interpolate(lambda x: np.stack([0.1 * x[0] * x[1], np.zeros_like(x[0])]))
    initial_residual = solver.residual_norm()
    # regression: PETSc stopped on the zero step (CONVERGED_SNORM_RELATIVE) and solve()
    # returned "converged" at the initial residual
    with pytest.raises(ds.NewtonConvergenceError, match=r"step 1 failed after \d+ iterations"):
        solver.solve(1)
    assert solver.residual_norm() == pytest.approx(initial_residual)  # no progress was possible
    assert initial_residual > 0.1


def test_static_and_bdf_argument_orders_are_named_in_the_error():
    """Static(dt, num_steps) (the BDF order of dt first) is refused with both signatures."""
    with pytest.raises(ds.ParameterError, match=r"Static\(num_steps, dt\) and BDF\(order, dt"):
        ds.Static(0.1, 10)


def test_a_refused_point_puts_the_friction_coefficients_back():
    """FrictionControl's coefficients are state of the contact term: a point whose E is
    refused leaves them (and the control's value) at the last accepted point."""
    from test_gradients_contact import incline_scene

    from diffsolids.controls import FrictionControl

    model, contact, sim, objective = incline_scene(1, 1, num_steps=2)
    controls = [
        FrictionControl(contact, pairs=[("slab", "block")]),
        ds.ParameterControl(model, "E", "bodies"),
    ]
    rf = ds.ReducedFunctional(sim, objective, controls)
    q0 = np.array([0.35, 2e5, 1.5e5])
    rf(q0)
    mu0 = contact.friction_coefficients
    with pytest.raises(ds.ParameterError, match="field E has"):
        rf(np.array([0.6, 2e5, -1.0]))
    assert np.array_equal(contact.friction_coefficients, mu0)
    assert np.array_equal(rf.controls.value(), q0)
