"""The assembled residual is the gradient of the assembled energy and the Jacobian its Hessian.

For every strain energy and for the inertia and damping terms we check, on the quantities the
Newton solver assembles (``NewtonSolver.energy``, ``assemble_residual``, ``assemble_jacobian``):

* central finite differences of the energy against <R(u), d> and of the residual against J(u) d,
  in random directions and along the residual direction itself;
* Taylor remainders |E(u + h d) - E(u) - h <R, d>| and ||R(u + h d) - R(u) - h J d|| that
  decrease as h^2 (exactly zero up to roundoff for the Jacobian of quadratic energies);
* symmetry of the Jacobian (it is a Hessian).
"""

import contextlib
from collections.abc import Iterator

import numpy as np
import pytest
from mpi4py import MPI

import diffsolids as ds
from diffsolids.mesh import create_box, create_rectangle
from diffsolids.model import Damping

LAWS = ("linear", "st_venant_kirchhoff", "neo_hookean")
STEPS = 0.05 * 0.5 ** np.arange(5)  # step sizes h of the Taylor tests (directions ~0.1)


class Probe:
    """Energy, residual and Jacobian-vector products of a NewtonSolver at given owned states."""

    def __init__(self, model: ds.Model, dynamic: bool):
        self.model = model
        self.solver = ds.NewtonSolver(model, dynamic, ds.SolverOptions(prevent_inversion=False))
        self.u = model.fields.u
        self.n = self.solver.x.getLocalSize()
        self.comm = model.domain.comm

    def set_u(self, owned: np.ndarray) -> None:
        self.u.x.array[: self.n] = owned
        self.u.x.scatter_forward()

    def energy(self, owned: np.ndarray) -> float:
        self.set_u(owned)
        return self.solver.energy()

    def residual(self, owned: np.ndarray) -> np.ndarray:
        self.set_u(owned)
        b = self.solver.b
        self.solver.assemble_residual(b)
        return b.array_r.copy()

    def jacobian_action(self, owned: np.ndarray, direction: np.ndarray) -> np.ndarray:
        self.set_u(owned)
        A = self.solver.A
        self.solver.assemble_jacobian(A)
        x, y = self.solver.x.duplicate(), self.solver.b.duplicate()
        x.array_w[:] = direction
        A.mult(x, y)
        return y.array_r.copy()

    def jacobian_asymmetry(self, owned: np.ndarray) -> float:
        self.set_u(owned)
        A = self.solver.A
        self.solver.assemble_jacobian(A)
        At = A.copy()
        At.transpose()
        At.axpy(-1.0, A)
        return At.norm() / A.norm()

    def dot(self, a: np.ndarray, b: np.ndarray) -> float:
        return self.comm.allreduce(float(a @ b), op=MPI.SUM)

    def norm(self, a: np.ndarray) -> float:
        return np.sqrt(self.dot(a, a))


def _random(probe: Probe, seed: int, scale: float) -> np.ndarray:
    rng = np.random.default_rng(seed + 17 * probe.comm.rank)
    return scale * rng.uniform(-1.0, 1.0, probe.n)


def _set_field(probe: Probe, field, owned: np.ndarray) -> None:
    field.x.array[: probe.n] = owned
    field.x.scatter_forward()


def _domain(dim: int):
    comm = MPI.COMM_WORLD
    facets = {1: lambda x: np.isclose(x[0], 0.0), 2: lambda x: np.isclose(x[0], 1.0)}
    if dim == 2:
        return create_rectangle(comm, [[0, 0], [1, 1]], [3, 3], facets=facets)
    return create_box(comm, [[0, 0, 0], [1, 1, 1]], [2, 2, 2], facets=facets)


def _material(law: str, damping: bool = False):
    extra = {"damping_psi": 0.7, "damping_phi": 0.4} if damping else {}
    return ds.Material(law, E=10.0, nu=0.3, density=3.0, **extra)


def _dynamic_probe(model: ds.Model) -> Probe:
    """A dynamic Probe with a non-trivial history: u_prev, u_tilde, dt and beta dt of BDF2."""
    probe = Probe(model, dynamic=True)
    f = probe.model.fields
    _set_field(probe, f.u_prev, _random(probe, 101, 0.05))
    _set_field(probe, f.u_tilde, _random(probe, 102, 0.05))
    f.dt.value = 0.3
    f.beta_dt.value = 0.2
    return probe


def _check_consistency(probe: Probe, u: np.ndarray, direction: np.ndarray, quadratic: bool):
    """FD and Taylor checks of energy -> residual -> Jacobian at u along direction."""
    E0, R0 = probe.energy(u), probe.residual(u)
    Jd = probe.jacobian_action(u, direction)
    slope = probe.dot(R0, direction)
    curvature = probe.dot(Jd, direction)
    # the direction must probe the energy to first and second order, or the checks are vacuous
    assert abs(slope) > 1e-8 * probe.norm(R0) * probe.norm(direction)
    assert curvature > 0.0

    # central differences: error O(h^2) relative to the derivative
    h = 1e-4
    fd_slope = (probe.energy(u + h * direction) - probe.energy(u - h * direction)) / (2 * h)
    assert fd_slope == pytest.approx(slope, rel=1e-6)
    fd_Jd = (probe.residual(u + h * direction) - probe.residual(u - h * direction)) / (2 * h)
    assert probe.norm(fd_Jd - Jd) <= 1e-6 * probe.norm(Jd)

    # Taylor remainders: second order in h
    r_energy = np.array(
        [abs(probe.energy(u + s * direction) - E0 - s * slope) for s in STEPS],
    )
    rates = np.log2(r_energy[:-1] / r_energy[1:])
    assert np.all(np.abs(rates - 2.0) < 0.1), rates
    # the remainder is the quadratic term: |r(h) - h^2/2 d.J.d| = O(h^3)
    assert r_energy[-1] == pytest.approx(0.5 * STEPS[-1] ** 2 * abs(curvature), rel=0.05)

    r_residual = np.array(
        [probe.norm(probe.residual(u + s * direction) - R0 - s * Jd) for s in STEPS],
    )
    if quadratic:  # the residual is affine: the first-order expansion is exact
        assert np.all(r_residual <= 1e-10 * STEPS * probe.norm(Jd)), r_residual
    else:
        rates = np.log2(r_residual[:-1] / r_residual[1:])
        assert np.all(np.abs(rates - 2.0) < 0.1), rates


def _directions(probe: Probe, u: np.ndarray, seed: int):
    """A random direction and the (scaled) residual direction at u."""
    d_random = _random(probe, seed, 0.1)
    R = probe.residual(u)
    d_residual = 0.1 * R / probe.comm.allreduce(np.max(np.abs(R), initial=0.0), op=MPI.MAX)
    return {"random": d_random, "residual": d_residual}


@pytest.fixture(scope="module")
def static_probes():
    cache = {}

    def get(law: str, dim: int) -> Probe:
        if (law, dim) not in cache:
            cache[law, dim] = Probe(ds.Model(_domain(dim), _material(law)), dynamic=False)
        return cache[law, dim]

    return get


@pytest.mark.parametrize("direction", ["random", "residual"])
@pytest.mark.parametrize("law", LAWS)
def test_strain_energy_2d(static_probes, law, direction):
    probe = static_probes(law, 2)
    u = _random(probe, 1, 0.1)
    d = _directions(probe, u, seed=2)[direction]
    _check_consistency(probe, u, d, quadratic=law == "linear")
    assert probe.jacobian_asymmetry(u) < 1e-13


@pytest.mark.parametrize("direction", ["random", "residual"])
def test_neo_hookean_3d(static_probes, direction):
    probe = static_probes("neo_hookean", 3)
    u = _random(probe, 3, 0.08)
    d = _directions(probe, u, seed=4)[direction]
    _check_consistency(probe, u, d, quadratic=False)
    assert probe.jacobian_asymmetry(u) < 1e-13


@pytest.fixture(scope="module")
def inertia_probe():
    """A BDF step with inertia only (the elastic terms removed)."""
    model = ds.Model(_domain(2), _material("linear"))
    model.terms = []
    return _dynamic_probe(model)


@pytest.fixture(scope="module")
def damping_probe():
    """A BDF step with inertia and damping only (the elastic terms removed)."""
    model = ds.Model(_domain(2), _material("linear", damping=True))
    model.terms = [t for t in model.terms if isinstance(t, Damping)]
    assert model.terms, "the damped material must add a damping term"
    return _dynamic_probe(model)


@pytest.mark.parametrize("direction", ["random", "residual"])
def test_inertia(inertia_probe, direction):
    probe = inertia_probe
    u = _random(probe, 5, 0.1)
    d = _directions(probe, u, seed=6)[direction]
    _check_consistency(probe, u, d, quadratic=True)
    assert probe.jacobian_asymmetry(u) < 1e-13


@pytest.mark.parametrize("direction", ["random", "residual"])
def test_damping(damping_probe, direction):
    probe = damping_probe
    u = _random(probe, 7, 0.1)
    _check_consistency(probe, u, _directions(probe, u, seed=8)[direction], quadratic=False)
    assert probe.jacobian_asymmetry(u) < 1e-13


@contextlib.contextmanager
def _damping_off(probe: Probe) -> Iterator[None]:
    """Sets the damping coefficients to zero inside the block and restores them after it."""
    fields = [probe.model.coefficients[k] for k in ("damping_psi", "damping_phi")]
    saved = [c.x.array.copy() for c in fields]
    for c in fields:
        c.x.array[:] = 0.0
    try:
        yield
    finally:
        for c, values in zip(fields, saved, strict=True):
            c.x.array[:] = values


def test_damping_is_a_sizeable_nonlinear_term(damping_probe):
    """Guard for test_damping: the damping term changes energy, residual and Jacobian."""
    probe = damping_probe
    u = _random(probe, 7, 0.1)
    f = probe.model.fields
    with_damping = (probe.energy(u), probe.residual(u))
    with _damping_off(probe):
        without = (probe.energy(u), probe.residual(u))
    assert abs(with_damping[0] - without[0]) > 0.1 * abs(without[0])
    assert probe.norm(with_damping[1] - without[1]) > 0.1 * probe.norm(without[1])
    # damping vanishes with the strain rate: at u = u_prev it is zero with zero force
    u_prev = f.u_prev.x.array[: probe.n].copy()
    E_at_prev = probe.energy(u_prev)
    with _damping_off(probe):
        assert probe.energy(u_prev) == pytest.approx(E_at_prev, rel=1e-13)


@pytest.fixture(scope="module")
def full_dynamic_probe():
    """A damped Neo-Hookean BDF step with gravity, a traction and a Dirichlet condition."""
    model = ds.Model(_domain(3), _material("neo_hookean", damping=True))
    model.add_gravity(9.81)
    model.add_traction(2, [0.3, -0.2, 0.1])
    model.add_dirichlet(1, 0.0)
    return _dynamic_probe(model)


@pytest.mark.parametrize("direction", ["random", "residual"])
def test_full_dynamic_step_with_dirichlet(full_dynamic_probe, direction):
    probe = full_dynamic_probe
    fixed = probe.model.dirichlet_dofs()
    fixed = fixed[fixed < probe.n]
    u = _random(probe, 9, 0.06)
    u[fixed] = 0.0  # admissible state
    d = _directions(probe, u, seed=10)[direction]
    d[fixed] = 0.0  # admissible direction
    _check_consistency(probe, u, d, quadratic=False)
    # Dirichlet rows: residual u - g (g = 0 here), Jacobian rows and columns of the identity
    off = u.copy()
    off[fixed] = 0.01
    R = probe.residual(off)
    assert np.allclose(R[fixed], 0.01, rtol=1e-14, atol=0)
    e = np.zeros(probe.n)
    e[fixed[:1]] = 1.0
    if probe.comm.allreduce(len(fixed), op=MPI.SUM):
        Je = probe.jacobian_action(u, e)
        assert np.allclose(Je[fixed], e[fixed], rtol=0, atol=1e-14)
    assert probe.jacobian_asymmetry(u) < 1e-13
