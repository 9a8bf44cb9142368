"""Physics of the time-dependent model: damping dissipates, the oscillation period is right."""

import numpy as np
import pytest
import ufl
from dolfinx import fem
from mpi4py import MPI

import diffsolids as ds
from diffsolids.mesh import create_rectangle


# -- energy of a swinging cantilever --------------------------------------------------------------
@pytest.fixture(scope="module")
def cantilever():
    """A clamped Neo-Hookean cantilever whose damping can be switched by its parameter fields."""
    dom = create_rectangle(
        MPI.COMM_WORLD, [[0, 0], [2, 0.4]], [10, 2], facets={1: lambda x: np.isclose(x[0], 0)}
    )
    model = ds.Model(dom, ds.NeoHookean(E=1000.0, nu=0.3, density=1.0), damping=True)
    model.add_dirichlet(1, 0.0)
    f = model.fields
    lmbda, mu = model.lame()
    elastic = fem.form(ds.forms.neo_hookean_energy(f.u, lmbda, mu) * f.dx)
    kinetic = fem.form(0.5 * model.coefficients["density"] * ufl.dot(f.v, f.v) * f.dx)

    def energy(u: np.ndarray, v: np.ndarray) -> tuple[float, float]:
        f.u.x.array[:] = u
        f.v.x.array[:] = v
        comm = dom.comm
        return (
            comm.allreduce(fem.assemble_scalar(kinetic), op=MPI.SUM),
            comm.allreduce(fem.assemble_scalar(elastic), op=MPI.SUM),
        )

    return model, energy


_SWINGS: dict = {}


def _swing(cantilever, psi: float, order: int):
    """Energies (kinetic, elastic) per step of a cantilever swinging from an upward velocity."""
    if (psi, order) in _SWINGS:
        return _SWINGS[psi, order]
    model, energy = cantilever
    model.coefficients["damping_psi"].x.array[:] = psi
    model.coefficients["damping_phi"].x.array[:] = psi
    # the first bending mode has a period of about 2: simulate about one period
    sim = ds.Simulation(
        model,
        ds.BDF(order, 0.02, 100),
        v0=lambda x: np.stack([np.zeros_like(x[0]), 0.3 * x[0] ** 2 / 4]),
        progress=False,
    )
    traj = sim.run()
    parts = np.array([energy(u, v) for u, v in zip(traj.u, traj.v, strict=True)])
    assert parts[0, 1] == 0.0 and parts[0, 0] > 0.0  # starts as pure kinetic energy
    _SWINGS[psi, order] = parts
    return parts


DAMPING = 30.0


@pytest.mark.parametrize("order", [1, 2])
def test_damping_removes_energy(cantilever, order):
    damped = _swing(cantilever, DAMPING, order)
    undamped = _swing(cantilever, 0.0, order)
    total, reference = damped.sum(axis=1), undamped.sum(axis=1)
    assert damped[:, 1].max() > 0.3 * total[0]  # the beam really deforms
    if order == 1:
        # implicit Euler dissipates at every step (the more with damping)
        assert np.all(np.diff(total) < 0.0)
        assert np.all(np.diff(reference) < 0.0)
    else:
        # BDF2 is not energy-monotone step by step, but over a few steps it is
        assert np.all(total[5:] < total[:-5])
    # damping, not the integrator's numerical dissipation, removes most of the energy
    assert total[-1] < 0.1 * total[0]
    assert total[-1] < 0.2 * reference[-1]
    assert np.all(total[1:] < reference[1:])


def test_without_damping_bdf2_nearly_conserves_energy(cantilever):
    parts = _swing(cantilever, 0.0, 2)
    total = parts.sum(axis=1)
    assert parts[:, 1].max() > 0.5 * total[0]  # a quarter swing turns it into strain energy
    # BDF2's numerical dissipation over one period at omega dt ~ 0.06 is a few percent
    assert 0.95 * total[0] < total[-1] < total[0]
    assert np.all(total[5:] < total[:-5])


# -- period of a 1D-like bar ------------------------------------------------------------------
def test_axial_bar_period():
    """Axial vibration of a clamped-free bar with nu = 0 (an exact 1D wave in 2D).

    With lambda = 0 the field u = (f(x, t), 0) has sigma_xx = E f' and no lateral stress, so the
    fundamental mode sin(pi x / 2L) cos(omega t) has omega = pi c / (2 L), c = sqrt(E / rho).
    """
    length, E, rho, amplitude = 1.0, 4.0, 1.0, 1e-3
    dom = create_rectangle(
        MPI.COMM_SELF,
        [[0, 0], [length, 0.1]],
        [16, 1],
        facets={1: lambda x: np.isclose(x[0], 0.0)},
    )
    model = ds.Model(dom, ds.LinearElastic(E=E, nu=0.0, density=rho), degree=2)
    model.add_dirichlet(1, 0.0)
    omega = np.pi * np.sqrt(E / rho) / (2 * length)
    period = 2 * np.pi / omega
    steps_per_period = 200
    dt = period / steps_per_period

    def u0(x):
        return np.stack([amplitude * np.sin(np.pi * x[0] / (2 * length)), np.zeros_like(x[0])])

    traj = ds.Simulation(model, ds.BDF(2, dt, 2 * steps_per_period), u0=u0, progress=False).run()
    x = model.V.tabulate_dof_coordinates()
    tip = np.flatnonzero(np.isclose(x[:, 0], length))[0]
    ux = np.array([u[2 * tip] for u in traj.u])
    uy = np.array([u[1::2] for u in traj.u])
    assert np.abs(uy).max() < 1e-4 * amplitude  # lateral motion: discretisation error only
    t = np.array(traj.times)
    i = np.flatnonzero(np.sign(ux[:-1]) != np.sign(ux[1:]))
    crossings = t[i] - ux[i] * (t[i + 1] - t[i]) / (ux[i + 1] - ux[i])
    assert len(crossings) == 4  # two periods
    measured = 2 * (crossings[-1] - crossings[0]) / (len(crossings) - 1)
    # BDF2 lengthens the period: its principal root r of (3/2 - z) r^2 - 2 r + 1/2 = 0 at
    # z = i omega dt advances the phase by arg(r) < omega dt per step (~ (omega dt)^2 / 3)
    roots = np.roots([1.5 - 1j * omega * dt, -2.0, 0.5])
    bdf2_error = omega * dt / np.angle(roots[np.argmax(np.abs(roots))]) - 1.0
    relative_error = measured / period - 1.0
    print(f"bar period: measured {measured}, analytic {period}, BDF2 prediction {bdf2_error}")
    assert 2e-4 < bdf2_error < 5e-4
    assert relative_error == pytest.approx(bdf2_error, rel=0.05)
    assert crossings[0] == pytest.approx(period / 4 * (1 + bdf2_error), rel=1e-4)
