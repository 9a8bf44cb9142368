"""Temporal orders of the BDF integrators and exact free fall.

Order test: undamped linear elastodynamics M u'' + K u = 0 of a clamped P2 cantilever started in
its lowest discrete eigenmode phi (K phi = omega^2 M phi, from the assembled matrices). The exact
semi-discrete solution is u(t) = phi cos(omega t), so the error at a fixed final time measures
the time discretisation alone. The final time is half a period and the step counts are modest:
BDF3+ are not A-stable, and the roundoff in the stiff modes of the imaginary axis grows by up to
~1.2 per step for BDF4, which must stay far below the measured errors.
"""

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse
from mpi4py import MPI

import diffsolids as ds
from diffsolids.mesh import create_rectangle

STEP_COUNTS = (16, 32, 64)
GRAVITY = 9.81


def _dense(A) -> np.ndarray:
    indptr, indices, values = A.getValuesCSR()
    return scipy.sparse.csr_matrix((values, indices, indptr), shape=A.getSize()).toarray()


@pytest.fixture(scope="module")
def cantilever():
    """Model, lowest eigenmode phi (max norm 1) and its angular frequency omega."""
    dom = create_rectangle(
        MPI.COMM_SELF, [[0, 0], [2, 0.5]], [8, 2], facets={1: lambda x: np.isclose(x[0], 0)}
    )
    model = ds.Model(dom, ds.LinearElastic(E=1.0, nu=0.3, density=1.0), degree=2)
    model.add_dirichlet(1, 0.0)
    # the step Jacobian is M / (beta dt)^2 + K: two values of beta dt give M and K
    solver = ds.NewtonSolver(model, dynamic=True)
    jacobians = []
    for beta_dt in (1.0, 0.5):
        model.fields.beta_dt.value = beta_dt
        solver.assemble_jacobian(solver.A)
        jacobians.append(_dense(solver.A))
    M = (jacobians[1] - jacobians[0]) / 3.0
    K = jacobians[0] - M
    free = np.setdiff1d(np.arange(len(M)), model.dirichlet_dofs())
    eigvals, eigvecs = scipy.linalg.eigh(
        K[np.ix_(free, free)], M[np.ix_(free, free)], subset_by_index=[0, 0]
    )
    phi = np.zeros(len(M))
    phi[free] = eigvecs[:, 0]
    phi /= np.abs(phi).max()
    omega = float(np.sqrt(eigvals[0]))
    assert 0.05 < omega < 0.5  # a bending mode of this slender beam
    return model, phi, omega


def _final_error(cantilever, order: int, steps: int, exact_start: bool) -> float:
    model, phi, omega = cantilever
    t_end = np.pi / omega
    dt = t_end / steps

    def exact(t):
        return phi * np.cos(omega * t), -omega * phi * np.sin(omega * t)

    startup = [exact(j * dt) for j in range(1, order)] if exact_start else None
    sim = ds.Simulation(model, ds.BDF(order, dt, steps), u0=phi, startup=startup, progress=False)
    traj = sim.run()
    orders = [r.order for r in traj.records]
    expected = [0] * (order - 1) if exact_start else list(range(1, order))
    assert orders[: order - 1] == expected and set(orders[order - 1 :]) == {order}
    u_exact, v_exact = exact(traj.times[-1])
    return max(np.abs(traj.u[-1] - u_exact).max(), np.abs(traj.v[-1] - v_exact).max() / omega)


def _measured_orders(errors) -> np.ndarray:
    errors = np.asarray(errors)
    return np.log2(errors[:-1] / errors[1:])


@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_order_from_exact_history(cantilever, order):
    errors = [_final_error(cantilever, order, n, exact_start=True) for n in STEP_COUNTS]
    rates = _measured_orders(errors)
    print(f"BDF{order} exact start: errors {errors}, orders {rates}")
    assert abs(rates[-1] - order) < 0.15, rates
    assert abs(rates[0] - order) < 0.3, rates


@pytest.mark.parametrize("order", [2, 3, 4])
def test_order_with_lower_order_startup(cantilever, order):
    """The first BDF1 step (local error O(dt^2)) caps the global order at 2."""
    errors = [_final_error(cantilever, order, n, exact_start=False) for n in STEP_COUNTS]
    rates = _measured_orders(errors)
    print(f"BDF{order} default start-up: errors {errors}, orders {rates}")
    assert abs(rates[-1] - 2) < 0.15, rates
    assert abs(rates[0] - 2) < 0.3, rates


def test_startup_states_are_validated(cantilever):
    model, phi, _ = cantilever
    with pytest.raises(ds.ParameterError, match="leave no step of 2 to solve"):
        ds.Simulation(model, ds.BDF(3, 0.1, 2), startup=[(phi, phi), (phi, phi)])
    with pytest.raises(ds.ParameterError, match="start-up states need a dynamic"):
        ds.Simulation(model, ds.Static(2), startup=[(phi, phi)])
    with pytest.raises(ds.ParameterError, match=r"start-up state v\^1 has non-finite"):
        ds.Simulation(model, ds.BDF(2, 0.1, 3), startup=[(phi, np.full_like(phi, np.nan))])


@pytest.fixture(scope="module")
def falling_body():
    """An unconstrained Neo-Hookean body under gravity (no Dirichlet condition)."""
    dom = create_rectangle(MPI.COMM_SELF, [[0, 0], [1, 0.5]], [2, 1])
    model = ds.Model(dom, ds.NeoHookean(E=100.0, nu=0.3, density=2.0))
    model.add_gravity(GRAVITY)
    return model


def _fall(model, order: int, dt: float, steps: int):
    """Vertical position errors u - (-g t^2 / 2) per step (one value: the fall is rigid)."""
    traj = ds.Simulation(model, ds.BDF(order, dt, steps), progress=False).run()
    t = np.array(traj.times)
    u = np.array(traj.u).reshape(steps + 1, -1, 2)
    v = np.array(traj.v).reshape(steps + 1, -1, 2)
    # velocity exact at every step (BDF of any order is exact for v linear in t)
    assert np.abs(v[:, :, 1] + GRAVITY * t[:, None]).max() <= 1e-11 * GRAVITY * t[-1]
    assert np.abs(v[:, :, 0]).max() <= 1e-12 * GRAVITY * t[-1]
    assert np.abs(u[:, :, 0]).max() <= 1e-12 * GRAVITY * t[-1] ** 2
    error = u[:, :, 1] + 0.5 * GRAVITY * t[:, None] ** 2
    assert np.ptp(error, axis=1).max() <= 1e-12 * GRAVITY * t[-1] ** 2  # no deformation
    assert all(r.iterations == 1 for r in traj.records)
    return error[:, 0]


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5, 6])
def test_free_fall(falling_body, order):
    dt, steps = 0.01, 60
    error = _fall(falling_body, order, dt, steps)
    scaled = error / (GRAVITY * dt**2)
    assert scaled[1] == pytest.approx(-0.5, rel=1e-9)  # the first (BDF1) step
    if order == 1:
        # every BDF1 step adds -g dt^2 / 2: the error grows as -g dt t / 2
        assert np.allclose(scaled, -0.5 * np.arange(steps + 1), rtol=1e-9, atol=1e-9)
        return
    # the start-up error O(g dt^2) is carried along but does not grow: after the transients of
    # the parasitic roots (modulus <= 0.87 for BDF6) it is constant
    assert np.all(np.abs(scaled) <= 0.8)
    first, second = np.abs(scaled[: steps // 2]), np.abs(scaled[steps // 2 :])
    assert second.max() <= first.max() * (1 + 1e-6)
    tail = scaled[2 * steps // 3 :]
    assert np.ptp(tail) <= 2e-3 * np.abs(tail).max()
    # halving dt over the same time interval leaves the scaled error unchanged: O(dt^2)
    finer = _fall(falling_body, order, dt / 2, 2 * steps) / (GRAVITY * (dt / 2) ** 2)
    assert finer[-1] == pytest.approx(scaled[-1], rel=2e-3)
