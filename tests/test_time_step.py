"""The time discretisation of a step in one object (integrators.TimeStep).

Coefficients with start-up orders, the predictor and the velocity against their formulas (paper
eq. 4), their transposes (the backward sweep's pushes) against central differences of the
linear maps in random directions and along the gradient, the static step as the same object
without predictor history, and the forward run, the objective evaluation and the sweep reading
the same step object.
"""

import numpy as np
import pytest
from mpi4py import MPI

import diffsolids as ds
from diffsolids.integrators import TimeStep

N_DOFS = 7


def _states(num: int, seed: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    rng = np.random.default_rng(seed)
    return (
        [rng.standard_normal(N_DOFS) for _ in range(num)],
        [rng.standard_normal(N_DOFS) for _ in range(num)],
    )


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5, 6])
def test_start_up_orders_and_formulas(order):
    integ = ds.BDF(order, 0.05, 8)
    assert integ.history_depth == order
    u, v = _states(9, order)
    for i in range(1, 9):
        step = integ.step(i)
        m = min(i, order)
        alpha, beta = ds.bdf_coefficients(m)
        assert (step.order, step.alpha, step.beta, step.dt) == (m, tuple(alpha), beta, 0.05)
        assert step.index == i and step.time == pytest.approx(0.05 * i) and step.inertial
        assert list(step.lags) == list(range(1, m + 1))
        assert integ.coefficients(i) == step
        tilde = -sum(a * (u[i - j] + beta * 0.05 * v[i - j]) for j, a in enumerate(alpha, 1))
        assert np.allclose(step.predictor(u, v), tilde, rtol=1e-14, atol=1e-14)
        vel = (u[i] + sum(a * u[i - j] for j, a in enumerate(alpha, 1))) / (beta * 0.05)
        assert np.allclose(step.velocity(u[i], u), vel, rtol=1e-14, atol=1e-13)
    # BDF_m is exact for polynomials of degree m: u = t^m, v = m t^(m-1) at t_i
    t = 0.05 * np.arange(9)
    poly = [np.full(N_DOFS, tk**order) for tk in t]
    step = integ.step(8)
    exact = np.full(N_DOFS, order * t[8] ** (order - 1))
    assert np.allclose(step.velocity(poly[8], poly), exact, rtol=1e-9)


def test_static_step_has_no_predictor_history():
    integ = ds.Static(3, dt=0.5)
    assert integ.history_depth == 1
    u, v = _states(4, 0)
    step = integ.step(2)
    assert not step.inertial and step.order == 1 and step.time == 1.0
    assert np.array_equal(step.predictor(u, v), np.zeros(N_DOFS))
    # the rate of lagged terms: the first-order difference over the load step, bit for bit
    assert np.array_equal(step.velocity(u[2], u), (u[2] - u[1]) / 0.5)
    ubar, vbar = {k: np.zeros(N_DOFS) for k in range(4)}, {k: np.zeros(N_DOFS) for k in range(4)}
    step.add_predictor_transpose(np.ones(N_DOFS), ubar, vbar)
    assert not any(np.any(a) for a in (*ubar.values(), *vbar.values()))


def _flat(u: list[np.ndarray], v: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(u + v)


def _unflat(x: np.ndarray, num: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    parts = np.split(x, 2 * num)
    return parts[:num], parts[num:]


def _check_linear_map(apply, transpose, num: int, seed: int) -> None:
    """Central differences of J(x) = w . F(x) vs the transpose, random directions and gradient."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(2 * num * N_DOFS)
    w = rng.standard_normal(N_DOFS)

    def J(y: np.ndarray) -> float:
        return float(w @ apply(*_unflat(y, num)))

    grad = transpose(w)
    assert np.abs(grad).max() > 0.1
    for d in (rng.standard_normal(x.size), rng.standard_normal(x.size), grad):
        h = 1e-3
        fd = (J(x + h * d) - J(x - h * d)) / (2 * h)
        assert fd == pytest.approx(grad @ d, rel=1e-10, abs=1e-10 * np.abs(grad).sum())


@pytest.mark.parametrize("integ", [ds.BDF(1, 0.1, 4), ds.BDF(3, 0.1, 4), ds.Static(4, 0.3)])
@pytest.mark.parametrize("i", [1, 2, 4])
def test_transposes_are_the_vector_jacobian_products(integ, i):
    step = integ.step(i)
    num = i + 1  # states 0..i

    def velocity(u, v):
        return step.velocity(u[i], u)

    def velocity_t(w):
        ubar, vbar = _zeros(num), _zeros(num)
        step.add_velocity_transpose(w, ubar)
        return _flat([ubar[k] for k in range(num)], [vbar[k] for k in range(num)])

    _check_linear_map(velocity, velocity_t, num, seed=i)
    if not step.inertial:
        return

    def predictor(u, v):
        return step.predictor(u, v)

    def predictor_t(w):
        ubar, vbar = _zeros(num), _zeros(num)
        step.add_predictor_transpose(w, ubar, vbar)
        return _flat([ubar[k] for k in range(num)], [vbar[k] for k in range(num)])

    _check_linear_map(predictor, predictor_t, num, seed=10 + i)


def _zeros(num: int) -> dict[int, np.ndarray]:
    return {k: np.zeros(N_DOFS) for k in range(num)}


def test_predictor_transpose_on_leading_entries():
    """A partial over the owned dofs only pushes into the leading entries of longer arrays."""
    step = ds.BDF(2, 0.1, 3).step(3)
    ubar, vbar = _zeros(4), _zeros(4)
    g = np.ones(N_DOFS - 2)
    step.add_predictor_transpose(g, ubar, vbar)
    for j, a in enumerate(step.alpha, start=1):
        assert np.array_equal(ubar[3 - j][: N_DOFS - 2], -a * g)
        assert np.array_equal(vbar[3 - j][: N_DOFS - 2], -a * step.beta_dt * g)
        assert not np.any(ubar[3 - j][N_DOFS - 2 :]) and not np.any(vbar[3 - j][N_DOFS - 2 :])


@pytest.fixture(scope="module")
def beam() -> ds.Model:
    dom = ds.mesh.create_rectangle(
        MPI.COMM_WORLD, [[0, 0], [1, 0.2]], [5, 2], facets={1: lambda x: np.isclose(x[0], 0)}
    )
    model = ds.Model(dom, ds.NeoHookean(E=1e3, nu=0.3, density=10.0, damping_psi=0.5))
    model.add_gravity(9.81)
    model.add_dirichlet(1, 0.0)
    return model


@pytest.mark.parametrize("integ", [ds.BDF(3, 0.02, 5), ds.Static(3, 1.0)], ids=["bdf3", "static"])
def test_simulation_uses_the_step_object(beam, integ):
    """The forward's v^i is the step's velocity, load_step sets the step's fields and returns it."""
    sim = ds.Simulation(beam, integ, ds.SolverOptions(rtol=1e-12), progress=False)
    traj = sim.run()
    f = beam.fields
    for i in range(1, integ.num_steps + 1):
        step = integ.step(i)
        assert traj.records[i - 1].order == step.order and traj.times[i] == step.time
        assert np.array_equal(traj.v[i], step.velocity(traj.u[i], traj.u))
        f.u_tilde.x.array[:] = 7.0
        assert sim.load_step(i, traj) == step
        assert float(f.dt.value) == step.dt and float(f.beta_dt.value) == step.beta_dt
        assert np.array_equal(f.u_prev.x.array, traj.u[i - 1])
        expected = step.predictor(traj.u, traj.v) if integ.dynamic else np.full_like(traj.u[0], 7)
        assert np.array_equal(f.u_tilde.x.array, expected)


def test_time_step_is_frozen():
    step = TimeStep(1, (-1.0,), 1.0, 0.1)
    with pytest.raises(AttributeError):
        step.dt = 0.2
    assert step.beta_dt == 0.1 and not step.inertial
