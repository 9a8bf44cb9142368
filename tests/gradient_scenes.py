"""Scenes, controls, objectives and the checks of the gradient test matrix.

Not collected by pytest (no ``test_`` prefix): test_gradients_*.py import it. Scenes (a Model
on a tiny two-body mesh) and their Simulations are cached per process, so every distinct form
is compiled once and parametrised cases share them; each check restores the parameters it
changed.
"""

import functools
from dataclasses import dataclass

import numpy as np
import pytest
import scipy.sparse as sp
import ufl
from dolfinx import fem
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import (
    DirichletControl,
    InitialCondition,
    ParameterControl,
    RigidVelocity,
    ShapeControl,
)
from diffsolids.controls.maps import Affine, Compose, Log, Power, Simp
from diffsolids.mesh import create_box, create_rectangle
from diffsolids.objectives import (
    Integral,
    center_of_mass_trajectory,
    final_value,
    height_objective,
    stress_lp_norm,
    target_displacement,
    target_positions,
    time_integral,
)
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.verification import finite_difference_check, taylor_test

FD_TOLERANCE = 1e-6
TAYLOR_MIN_RATE = 1.9
NEWTON = ds.SolverOptions(rtol=1e-13)
LENGTH = 2.0


@dataclass(frozen=True)
class Scene:
    """Physics of a scene: law, dimension, degree, damping and parametrisation."""

    dim: int
    degree: int
    law: str  # "linear" or "neo_hookean"
    damping: bool
    lame: bool = False  # (lmbda, mu) instead of (E, nu)
    young_cg1: bool = False  # E as a CG1 field (E/nu scenes)
    plane_stress: bool = False
    ramped_load: bool = False  # a traction growing with t on the top (load steps differ)


SCENES = {
    # BDF1
    "2d-p1-nh-damped": Scene(2, 1, "neo_hookean", True),
    "2d-p2-lin-damped-lame-ps": Scene(2, 2, "linear", True, lame=True, plane_stress=True),
    "3d-p1-lin-cg1": Scene(3, 1, "linear", False, young_cg1=True),
    "3d-p2-nh-lame": Scene(3, 2, "neo_hookean", False, lame=True),
    # BDF2
    "2d-p1-lin-cg1-ps": Scene(2, 1, "linear", False, young_cg1=True, plane_stress=True),
    "2d-p2-nh": Scene(2, 2, "neo_hookean", False),
    "3d-p1-nh-damped-lame": Scene(3, 1, "neo_hookean", True, lame=True),
    "3d-p2-lin-damped": Scene(3, 2, "linear", True),
    # BDF3
    "2d-p1-lin-damped-lame": Scene(2, 1, "linear", True, lame=True),
    "2d-p1-nh-cg1-ps": Scene(2, 1, "neo_hookean", False, young_cg1=True, plane_stress=True),
    "3d-p2-nh-damped": Scene(3, 2, "neo_hookean", True),
    "3d-p2-lin-lame": Scene(3, 2, "linear", False, lame=True),
    # BDF6
    "2d-p2-lin-cg1": Scene(2, 2, "linear", False, young_cg1=True),
    "2d-p2-nh-damped-lame-ps": Scene(2, 2, "neo_hookean", True, lame=True, plane_stress=True),
    "3d-p1-lin-damped": Scene(3, 1, "linear", True),
    "3d-p1-nh-lame": Scene(3, 1, "neo_hookean", False, lame=True),
    # history-field objectives in load steps
    "2d-p1-nh-damped-ramp": Scene(2, 1, "neo_hookean", True, ramped_load=True),
}

INTEGRATORS = {
    "static": lambda: ds.Static(),
    "static2": lambda: ds.Static(num_steps=2, dt=0.5),
    "bdf1": lambda: ds.BDF(1, 0.05, 2),
    "bdf2": lambda: ds.BDF(2, 0.05, 3),
    "bdf3": lambda: ds.BDF(3, 0.05, 4),
    "bdf6": lambda: ds.BDF(6, 0.04, 7),
}


def _domain(dim: int, comm):
    half = LENGTH / 2
    bodies = {2: lambda x: x[0] > half}
    if dim == 2:
        facets = {
            1: lambda x: np.isclose(x[0], 0.0),
            2: lambda x: np.isclose(x[0], LENGTH),
            3: lambda x: np.isclose(x[1], 0.5),
        }
        return create_rectangle(comm, [[0, 0], [LENGTH, 0.5]], [4, 2], facets=facets, bodies=bodies)
    facets = {
        1: lambda x: np.isclose(x[0], 0.0),
        2: lambda x: np.isclose(x[0], LENGTH),
        3: lambda x: np.isclose(x[2], 0.5),
    }
    return create_box(
        comm, [[0, 0, 0], [LENGTH, 0.5, 0.5]], [2, 1, 1], facets=facets, bodies=bodies
    )


def build_model(scene: Scene, comm=MPI.COMM_SELF) -> ds.Model:
    """A clamped two-body bar under gravity and an end traction (bodies with different E)."""
    domain = _domain(scene.dim, comm)
    stiff = 400.0 if scene.law == "linear" else 300.0
    damping = {"damping_psi": 0.4, "damping_phi": 0.2} if scene.damping else {}
    materials = {}
    for body, factor in ((1, 1.0), (2, 1.6)):
        E, nu = stiff * factor, 0.3 + 0.05 * (body - 1)
        if scene.lame:
            elastic = {"lmbda": E * nu / ((1 + nu) * (1 - 2 * nu)), "mu": E / (2 * (1 + nu))}
        else:
            elastic = {"E": E, "nu": nu}
        law = ds.LinearElastic if scene.law == "linear" else ds.NeoHookean
        materials[body] = law(density=1.0 + 0.5 * (body - 1), **elastic, **damping)
    fields = None
    if scene.young_cg1:
        Q = fem.functionspace(domain.mesh, ("Lagrange", 1))
        E = fem.Function(Q, name="E")
        E.interpolate(lambda x: stiff * (1.0 + 0.3 * x[0]))
        fields = {"E": E}
    model = ds.Model(
        domain, materials, degree=scene.degree, plane_stress=scene.plane_stress, fields=fields
    )
    g = np.zeros(scene.dim)
    g[-1] = -4.0
    model.add_body_force(g, name="gravity")
    traction = np.zeros(scene.dim)
    traction[-1], traction[0] = -6.0, 2.0
    model.add_traction(2, traction)
    if scene.ramped_load:
        model.add_traction(3, lambda t: np.eye(scene.dim)[-1] * -3.0 * t, name="ramp")
    model.add_dirichlet(1, 0.0)
    return model


@functools.cache
def scene_model(name: str) -> ds.Model:
    """The cached Model of a scene (serial)."""
    return build_model(SCENES[name])


@functools.cache
def simulation(scene: str, integrator: str) -> ds.Simulation:
    """A cached Simulation of a scene (v0 nonzero for dynamic runs)."""
    return model_simulation(scene_model(scene), INTEGRATORS[integrator]())


def model_simulation(model: ds.Model, integrator: ds.Integrator) -> ds.Simulation:
    """A Simulation of ``model`` at the Newton tolerance of the gradient tests (v0 = 0.3 upward
    for dynamic runs)."""
    v0 = None
    if integrator.dynamic:
        v0 = np.zeros(model.dim)
        v0[-1] = 0.3
    return ds.Simulation(model, integrator, NEWTON, v0=v0, progress=False)


# -- controls ---------------------------------------------------------------------------------
def _vertex_coordinates(model) -> np.ndarray:
    """Rest vertex coordinates in canonical (input) order (serial or gathered)."""
    mesh = model.domain.mesh
    n = mesh.geometry.index_map().size_local
    ids = mesh.geometry.input_global_indices[:n]
    x = mesh.geometry.x[:n, : model.dim]
    out = np.zeros((mesh.geometry.index_map().size_global, model.dim))
    out[ids] = x
    return model.domain.comm.allreduce(out, op=MPI.SUM)


def shape_linear_map(model) -> sp.csr_matrix:
    """Three smooth shape modes: axial stretch, bending, a thickness bump (clamp end fixed)."""
    X = _vertex_coordinates(model)
    x = X[:, 0] / LENGTH
    modes = np.zeros((len(X), model.dim, 3))
    modes[:, 0, 0] = 0.2 * x
    modes[:, -1, 1] = 0.2 * x**2
    modes[:, 1, 2] = 0.1 * np.sin(np.pi * x) * (X[:, 1] - 0.25)
    return sp.csr_matrix(modes.reshape(len(X) * model.dim, 3))


def _elastic(name_young: str, name_lame: str):
    def make(sim, **kw):
        model = sim.model
        name = name_lame if model.parametrisation == ("lmbda", "mu") else name_young
        return ParameterControl(model, name, **kw)

    return make


CONTROLS = {
    "shape-all": lambda sim: ShapeControl(sim.model, "all"),
    "shape-boundary": lambda sim: ShapeControl(sim.model, "boundary", exclude_facets=[1]),
    "shape-linear-map": lambda sim: ShapeControl(sim.model, linear_map=shape_linear_map(sim.model)),
    "young-field-log": lambda sim: ParameterControl(sim.model, "E", "field", log=True),
    "young-bodies": lambda sim: ParameterControl(sim.model, "E", "bodies", log=True),
    "poisson-field": lambda sim: ParameterControl(sim.model, "nu", "field"),
    "mu-field-log": lambda sim: ParameterControl(sim.model, "mu", "field", log=True),
    "lmbda-bodies": lambda sim: ParameterControl(sim.model, "lmbda", "bodies"),
    "psi-bodies": lambda sim: ParameterControl(sim.model, "damping_psi", "bodies"),
    "phi-field": lambda sim: ParameterControl(sim.model, "damping_phi", "field"),
    "density-field": lambda sim: ParameterControl(sim.model, "density", "field", log=True),
    "traction-scale": lambda sim: ParameterControl(sim.model, "traction_2", "scale"),
    "gravity-uniform": lambda sim: ParameterControl(sim.model, "gravity", "uniform"),
    "initial-u0": lambda sim: InitialCondition(sim, "displacement"),
    "initial-v0": lambda sim: InitialCondition(sim, "velocity"),
    "rigid-velocity": lambda sim: RigidVelocity(sim, 2, angular=True),
    "dirichlet": lambda sim: DirichletControl(sim, sim.model.dirichlet[0]),
    "dirichlet-per-step": lambda sim: DirichletControl(sim, sim.model.dirichlet[0], per_step=True),
    # parameter maps (diffsolids.controls.maps)
    "young-field-simp": lambda sim: ParameterControl(
        sim.model, "E", "field", map=Simp(100.0, 1000.0, 3.0)
    ),
    "mu-bodies-log-affine": lambda sim: ParameterControl(
        sim.model, "mu", "bodies", map=Compose(Affine(0.5, 1.0), Log())
    ),
    "gravity-power": lambda sim: ParameterControl(sim.model, "gravity", "scale", map=Power(2.0)),
}

# norm of a block of the perturbation at unit step (absolute for displacement-like controls,
# relative to |q| for parameters)
_ABSOLUTE_SIZE = {
    "shape-all": 0.02,
    "shape-boundary": 0.02,
    "shape-linear-map": 0.05,
    "initial-u0": 0.02,
    "initial-v0": 0.1,
    "rigid-velocity": 0.1,
    "dirichlet": 0.01,
    "dirichlet-per-step": 0.01,
}
_RELATIVE_SIZE = 0.05


def control_kind(key: str, scene: Scene) -> str:
    """What a control key exercises in a scene (for the coverage check)."""
    if key == "young-field-log" and scene.young_cg1:
        return "young-cg1"
    return key


# -- objectives ----------------------------------------------------------------------------
def _kinetic(model) -> Integral:
    rho = model.coefficients["density"]
    return Integral(lambda f: 0.5 * rho * ufl.dot(f.v, f.v) * f.dx, "kinetic")


def _history_integral(kind: str, model) -> Integral:
    """Integrals reading a history field of the step: u^{i-1} or the BDF predictor."""
    rho = model.coefficients["density"]
    integrands = {
        "u_prev": lambda f: (ufl.dot(f.u_prev, f.u_prev) + 0.1 * f.u_prev[1]) * f.dx,
        "u_tilde": lambda f: ufl.dot(f.u_tilde, f.u_tilde + f.u) * f.dx,
        # a user-written velocity next to the integrator's
        "rate": lambda f: rho * ufl.dot((f.u - f.u_prev) / f.dt, f.v + f.u) * f.dx,
    }
    return Integral(integrands[kind], kind)


HISTORY_OBJECTIVES = ("u_prev", "u_tilde", "rate")


def objective(kind: str, model, dynamic: bool):
    """Representative objectives (products, quotients and powers included).

    The kinds of HISTORY_OBJECTIVES read u_prev or u_tilde (all steps but step 0, which has no
    history, and the last one squared).
    """
    if kind in HISTORY_OBJECTIVES:
        leaf = _history_integral(kind, model)
        return time_integral(leaf, "uniform") + final_value(leaf) ** 2
    dim = model.dim
    down = np.zeros(dim)
    down[-1] = -0.05
    if kind == "stress":
        lp = stress_lp_norm(model, 4)
        return time_integral(lp, "uniform") if dynamic else final_value(lp)
    if kind == "target":
        disp = target_displacement(model, down, facets=2)
        if not dynamic:
            return final_value(disp) * (1.0 + final_value(height_objective(model)) ** 2)
        return time_integral(disp, "trapezoidal") + 0.1 * final_value(_kinetic(model))
    if kind == "com":
        target = np.full(dim, 0.25)
        target[0] = 1.05
        com = center_of_mass_trajectory(model, target)
        shape = target_positions(model, lambda x: 1.01 * x[:dim], weight=lambda x: 1.0 + x[0])
        if not dynamic:
            return final_value(com) / final_value(shape)
        return time_integral(com, "uniform") / time_integral(shape, [1, -1]) ** 0.5
    raise ValueError(kind)


# -- cases ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Case:
    """One row of the test matrix: a simulation, its controls and an objective."""

    scene: str
    integrator: str
    controls: tuple[str, ...]
    objective: str

    @property
    def id(self) -> str:
        return f"{self.integrator}-{self.scene}-{self.objective}-{'+'.join(self.controls)}"


@dataclass
class CaseResult:
    """Finite-difference and Taylor results of a case."""

    blocks: dict
    along_gradient: object
    taylor: object
    num_parameters: int


def _block_sizes(rf, keys) -> list[float]:
    """Norm of the perturbation of each control block at unit step."""
    q = rf.initial_parameters()
    offsets = rf.controls.offsets
    out = []
    for key, a, b in zip(keys, offsets[:-1], offsets[1:], strict=True):
        if key in _ABSOLUTE_SIZE:
            out.append(_ABSOLUTE_SIZE[key])
        else:
            out.append(_RELATIVE_SIZE * max(np.linalg.norm(q[a:b]), 1e-3 * np.sqrt(b - a)))
    return out


def fd_steps() -> np.ndarray:
    """Central-difference steps (relative to a unit-size perturbation)."""
    return np.array([1e-2, 1e-3, 1e-4])


def run_case(case: Case, seed: int = 0) -> CaseResult:
    """FD per control block in a random direction, FD along the gradient, a Taylor test."""
    sim = simulation(case.scene, case.integrator)
    controls = [CONTROLS[k](sim) for k in case.controls]
    obj = objective(case.objective, sim.model, sim.integrator.dynamic)
    rf = ReducedFunctional(sim, obj, controls)
    q0 = rf.initial_parameters()
    try:
        rng = np.random.default_rng(seed)
        g = rf.gradient(q0)
        sizes = _block_sizes(rf, case.controls)
        offsets = rf.controls.offsets
        blocks = list(zip(case.controls, sizes, offsets[:-1], offsets[1:], strict=True))
        block_errors = {}
        directions = []
        for key, size, a, b in blocks:
            d = np.zeros_like(q0)
            r = rng.standard_normal(b - a)
            d[a:b] = size * r / np.linalg.norm(r)
            directions.append(d)
            block_errors[key] = finite_difference_check(rf, q0, d, fd_steps(), gradient=g)
        # along the gradient, scaled so that no block moves further than its size
        h = min(size / max(np.linalg.norm(g[a:b]), 1e-300) for _, size, a, b in blocks)
        along = finite_difference_check(rf, q0, h * g, fd_steps(), gradient=g)
        taylor = taylor_test(rf, q0, sum(directions), h0=0.02, num=3)
        return CaseResult(block_errors, along, taylor, len(q0))
    finally:
        rf.controls.assign(q0)


def _cases(integrator: str, rows) -> list[Case]:
    return [Case(scene, integrator, tuple(controls.split()), obj) for scene, obj, controls in rows]


# Covering design: every control kind with every integrator, every (law, damping, dim, degree)
# in a dynamic run, every (law, dim, degree) in a static one; test_design_covers checks it.
STATIC_CASES = _cases(
    "static",
    [
        ("2d-p1-nh-damped", "stress", "young-field-log shape-all traction-scale"),
        ("2d-p2-lin-damped-lame-ps", "target", "mu-field-log shape-boundary"),
        ("3d-p1-lin-cg1", "com", "young-field-log poisson-field gravity-uniform"),
        ("3d-p2-nh-lame", "target", "lmbda-bodies shape-linear-map"),
        ("2d-p2-nh", "com", "young-bodies density-field dirichlet"),
        ("3d-p1-nh-damped-lame", "stress", "mu-field-log shape-all"),
        ("3d-p2-lin-damped", "target", "young-field-log traction-scale shape-boundary"),
    ],
) + _cases(
    "static2",
    [("2d-p1-lin-cg1-ps", "target", "dirichlet-per-step shape-linear-map gravity-uniform")],
)

DYNAMIC_CASES = (
    _cases(
        "bdf1",
        [
            ("2d-p1-nh-damped", "target", "young-field-log psi-bodies traction-scale initial-v0"),
            ("2d-p1-nh-damped", "com", "young-bodies shape-linear-map rigid-velocity"),
            (
                "2d-p2-lin-damped-lame-ps",
                "stress",
                "mu-field-log phi-field shape-boundary initial-u0",
            ),
            ("3d-p1-lin-cg1", "com", "young-field-log poisson-field density-field dirichlet"),
            (
                "3d-p2-nh-lame",
                "target",
                "lmbda-bodies shape-all gravity-uniform dirichlet-per-step",
            ),
        ],
    )
    + _cases(
        "bdf2",
        [
            (
                "2d-p1-lin-cg1-ps",
                "stress",
                "young-field-log poisson-field shape-all initial-u0 dirichlet-per-step",
            ),
            (
                "2d-p2-nh",
                "target",
                "young-field-log shape-linear-map gravity-uniform rigid-velocity",
            ),
            (
                "3d-p1-nh-damped-lame",
                "com",
                "mu-field-log lmbda-bodies psi-bodies traction-scale initial-v0",
            ),
            (
                "3d-p2-lin-damped",
                "target",
                "young-bodies phi-field shape-boundary density-field dirichlet",
            ),
        ],
    )
    + _cases(
        "bdf3",
        [
            ("2d-p1-lin-damped-lame", "target", "mu-field-log phi-field shape-all dirichlet"),
            ("2d-p1-nh-cg1-ps", "stress", "young-field-log poisson-field density-field initial-v0"),
            ("3d-p2-nh-damped", "com", "young-bodies psi-bodies shape-boundary dirichlet-per-step"),
            ("3d-p2-nh-damped", "target", "young-field-log gravity-uniform rigid-velocity"),
            ("3d-p2-lin-lame", "com", "lmbda-bodies shape-linear-map traction-scale initial-u0"),
        ],
    )
    + _cases(
        "bdf6",
        [
            (
                "2d-p2-lin-cg1",
                "com",
                "young-field-log poisson-field shape-boundary gravity-uniform",
            ),
            (
                "2d-p2-nh-damped-lame-ps",
                "stress",
                "lmbda-bodies psi-bodies shape-all rigid-velocity",
            ),
            (
                "3d-p1-lin-damped",
                "target",
                "young-field-log phi-field traction-scale dirichlet-per-step",
            ),
            ("3d-p1-lin-damped", "stress", "young-bodies shape-linear-map initial-u0"),
            ("3d-p1-nh-lame", "com", "mu-field-log density-field initial-v0 dirichlet"),
        ],
    )
)


# Objectives reading the history fields (u_prev in static and BDF runs, u_tilde in BDF runs),
# not part of the covering design above.
HISTORY_CASES = [
    Case("2d-p1-nh-damped", "bdf2", ("young-field-log", "initial-v0", "initial-u0"), "u_prev"),
    Case("2d-p1-nh-damped", "bdf3", ("young-field-log", "initial-v0", "initial-u0"), "u_tilde"),
    Case("2d-p1-nh-damped", "bdf2", ("psi-bodies", "initial-v0"), "rate"),
    Case("2d-p1-nh-damped-ramp", "static2", ("young-field-log", "initial-u0"), "u_prev"),
    Case("2d-p1-nh-damped-ramp", "static2", ("young-bodies", "traction-scale"), "rate"),
]


def check_case(case: Case) -> CaseResult:
    """Run a case and assert: FD error <= FD_TOLERANCE per block and along the gradient, Taylor
    second-order rate >= TAYLOR_MIN_RATE, and nonzero directional derivatives."""
    result = run_case(case)
    for key, res in result.blocks.items():
        assert abs(res.adjoint) > 1e-12, f"{key}: zero directional derivative\n{res}"
        assert res.relative_error <= FD_TOLERANCE, f"{key}\n{res}"
    assert result.along_gradient.relative_error <= FD_TOLERANCE, str(result.along_gradient)
    assert result.taylor.min_rate >= TAYLOR_MIN_RATE, str(result.taylor)
    return result


def assert_world_equals_self(
    comm: MPI.Comm, parallel: tuple, serial: tuple, rtol: float = 1e-8
) -> None:
    """(q, J, gradient) of a distributed run against the serial run of the same problem.

    The parameters are in canonical order: a wrong order moves values by O(1), while a field
    interpolated at dof coordinates (pushed forward from a different cell on each partition)
    differs by rounding. Every rank must hold the same value and gradient.
    """
    (q_par, J_par, g_par), (q_ser, J_ser, g_ser) = parallel, serial
    np.testing.assert_allclose(q_par, q_ser, rtol=4 * np.finfo(float).eps, atol=0)
    assert J_par == pytest.approx(J_ser, rel=rtol)
    assert np.abs(g_ser).max() > 0
    assert np.abs(g_par - g_ser).max() <= rtol * np.abs(g_ser).max()
    for value in comm.allgather(J_par):
        assert value == J_par
    for gradient in comm.allgather(g_par):
        assert np.array_equal(gradient, g_par)
