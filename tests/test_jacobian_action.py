"""The matrix-free step Jacobian of the adjoint solves: K x equals the assembled exact Jacobian
times x, also when the coefficients are packed once per solve and only the direction changes."""

from contextlib import nullcontext

import numpy as np
import pytest
from mpi4py import MPI

import diffsolids as ds
from diffsolids.mesh import create_rectangle
from diffsolids.solvers.action import JacobianAction


def damped_newton(comm=MPI.COMM_SELF, degree: int = 1):
    """NewtonSolver of a damped Neo-Hookean strip at a smooth deformed state."""
    dom = create_rectangle(
        comm, [[0, 0], [2, 0.4]], [6, 2], facets={1: lambda x: np.isclose(x[0], 0)}
    )
    law = ds.NeoHookean(E=2e3, nu=0.3, density=10.0, damping_psi=5.0, damping_phi=2.0)
    model = ds.Model(dom, law, degree=degree)
    model.add_dirichlet(1, 0.0)
    model.add_gravity(9.81)
    sim = ds.Simulation(model, ds.BDF(2, 0.02, 2), progress=False)
    f = model.fields
    f.u.interpolate(lambda x: 0.05 * np.array([x[0] * np.sin(3 * x[1]), x[0] ** 2]))
    f.u_prev.interpolate(lambda x: 0.04 * np.array([x[0] * x[1], x[0] ** 2 + x[1]]))
    f.beta_dt.value = 0.02
    return sim.solver


def actions(newton, directions, fixed: bool, action=None):
    """(owned entries of K x per direction, the JacobianAction); one Krylov solve's worth of
    actions under a fixed state if ``fixed``."""
    action = action or JacobianAction(newton)
    x, y = action.mat.createVecs()
    out = []
    with action.fixed_state() if fixed else nullcontext():
        for d in directions:
            x.array_w[:] = d
            action.mult(action.mat, x, y)
            out.append(y.array_r.copy())
    return out, action


def exact_products(newton, directions) -> list[np.ndarray]:
    """Owned entries of K x with K the assembled exact Jacobian at the current state."""
    A = newton.create_matrix()
    newton.assemble_jacobian(A, exact=True)
    x, y = A.createVecs()
    out = []
    for d in directions:
        x.array_w[:] = d
        A.mult(x, y)
        out.append(y.array_r.copy())
    return out


@pytest.mark.parametrize("degree", [1, 2])
def test_action_is_the_exact_jacobian_with_coefficients_packed_once(degree):
    newton = damped_newton(degree=degree)
    n = newton.create_matrix().getLocalSize()[0]
    rng = np.random.default_rng(degree)
    directions = [rng.standard_normal(n) for _ in range(3)]
    fixed, action = actions(newton, directions, fixed=True)
    assert action._direction_columns is not None  # the packed-once path is the one tested
    plain, _ = actions(newton, directions, fixed=False)
    exact = exact_products(newton, directions)
    for yf, yp, ye in zip(fixed, plain, exact, strict=True):
        assert np.linalg.norm(yf - ye) <= 1e-12 * np.linalg.norm(ye)
        assert np.array_equal(yf, yp)


def test_state_changes_between_solves_are_seen():
    """A new state packs anew: the second solve's action uses the new u."""
    newton = damped_newton()
    n = newton.create_matrix().getLocalSize()[0]
    d = [np.random.default_rng(5).standard_normal(n)]
    (first,), action = actions(newton, d, fixed=True)
    newton.model.fields.u.x.array[:] *= 2.0
    (second,), _ = actions(newton, d, fixed=True, action=action)
    (exact,) = exact_products(newton, d)
    assert np.linalg.norm(second - exact) <= 1e-12 * np.linalg.norm(exact)
    assert not np.allclose(first, exact)
