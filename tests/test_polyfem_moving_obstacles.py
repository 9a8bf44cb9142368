"""Moving obstacles read from a PolyFEM scene: displacement expressions of x, y, z, t.

A small 2D PolyFEM-style scene written to ``tmp_path``: a block thrown down onto a ground
polyline (``is_obstacle``) that slides to the right and sinks with a slight tilt, given as the
expression strings of ``boundary_conditions.obstacle_displacements`` (PolyFEM's lookup rule:
the entry whose id is the obstacle's ``surface_selection``; a ``dirichlet_boundary`` entry
serves too and is overridden). Checked: the obstacle is where the expression puts it at every
step, the run is intersection-free with a positive gap, friction drags the block along; the
expression parser against numpy (TinyExpr's precedence: left-associative ``^``, the sign
binding to the base, one-argument functions without parentheses, ``log`` = log10) and its
refusals; unsupported entries named with their file and entry; the gradient of the block's
final state w.r.t. its initial velocity against central differences along a random direction
and along the gradient.
"""

import json
from pathlib import Path

import meshio
import numpy as np
import pytest
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import RigidVelocity
from diffsolids.io.expressions import ExpressionError, parse_expression
from diffsolids.objectives import Integral, final_value
from diffsolids.optimize.invariants import check_trajectories
from diffsolids.polyfem import read_polyfem_scene
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.verification import finite_difference_check

COMM = MPI.COMM_WORLD
MOTION = ["0.3*t", "-0.05*t*(1 + 0.1*x)"]  # slides right at 0.3 m/s, sinks, tilts


def motion_numpy(X: np.ndarray, t: float) -> np.ndarray:
    """MOTION written with numpy: (n, 2) displacements of the rest vertices X."""
    return np.column_stack([np.full(len(X), 0.3 * t), -0.05 * t * (1 + 0.1 * X[:, 0])])


def write_scene(folder: Path, edit=None, name: str = "scene.json") -> Path:
    """The block (body 1, 4 x 2 squares of 0.3 x 0.15) 2 cm above the ground (obstacle 2)."""
    nx, ny = 4, 2
    xs, ys = np.linspace(0, 0.3, nx + 1), np.linspace(0, 0.15, ny + 1)
    points = np.array([[x, y, 0.0] for y in ys for x in xs])  # VTU: 3D points, z = 0
    cells = []
    for j in range(ny):
        for i in range(nx):
            a = j * (nx + 1) + i
            cells += [[a, a + 1, a + nx + 2], [a, a + nx + 2, a + nx + 1]]
    meshio.write(folder / "block.vtu", meshio.Mesh(points, [("triangle", np.array(cells))]))
    ground = np.column_stack([np.linspace(-1, 2, 7), np.zeros(7), np.zeros(7)])
    segments = np.column_stack([np.arange(6), np.arange(1, 7)])
    meshio.write(folder / "ground.vtu", meshio.Mesh(ground, [("line", segments)]))
    raw = {
        "geometry": [
            {
                "mesh": "block.vtu",
                "transformation": {"translation": [0.2, 0.02]},
                "volume_selection": 1,
                "surface_selection": 1,
            },
            {
                "mesh": "ground.vtu",
                "is_obstacle": True,
                "volume_selection": 2,
                "surface_selection": 2,
            },
        ],
        "space": {"discr_order": 1},
        "time": {"tend": 0.1, "dt": 0.01, "integrator": "BDF1"},
        "contact": {"enabled": True, "dhat": 0.01, "epsv": 0.01, "friction_coefficient": 0.2},
        "boundary_conditions": {
            "rhs": [0, 9.81],
            "dirichlet_boundary": [{"id": 2, "value": [0, 0]}],  # overridden, as in PolyFEM
            "obstacle_displacements": [{"id": 2, "value": list(MOTION)}],
        },
        "initial_conditions": {"velocity": [{"id": 1, "value": [0.2, -1.0]}]},
        "materials": {"type": "NeoHookean", "E": 1e5, "nu": 0.3, "rho": 1000},
    }
    if edit is not None:
        edit(raw)
    path = folder / name
    path.write_text(json.dumps(raw))
    return path


def build(path: Path, comm: MPI.Comm = COMM):
    return read_polyfem_scene(path).build(comm, ds.SolverOptions(rtol=1e-10))


# -- the expression parser ----------------------------------------------------------------
def _smoothstep(a):
    return np.where(a < 0, 0.0, np.where(a > 1, 1.0, 3 * a**2 - 2 * a**3))


CASES = {
    "0.3*t + 0.01*t*x": lambda x, y, z, t: 0.3 * t + 0.01 * t * x,
    "-x^2": lambda x, y, z, t: x**2,  # TinyExpr: the sign binds to the base
    "-(x^2)": lambda x, y, z, t: -(x**2),
    "2^3^2 + 0*x": lambda x, y, z, t: 64.0 + 0 * x,  # left-associative
    "x^-2": lambda x, y, z, t: x**-2.0,
    "sin x^2": lambda x, y, z, t: np.sin(x) ** 2,  # a one-argument function takes the base
    "sqrt 4 * y": lambda x, y, z, t: 2 * y,
    "sqrt(abs(y)) * exp(-t)": lambda x, y, z, t: np.sqrt(np.abs(y)) * np.exp(-t),
    "log(abs(x) + 1)": lambda x, y, z, t: np.log10(np.abs(x) + 1),  # log is log10
    "ln(abs(x) + 1) + log10(2)": lambda x, y, z, t: np.log(np.abs(x) + 1) + np.log10(2),
    "atan2(y, x) + pow(abs(z), 1.5)": lambda x, y, z, t: np.arctan2(y, x) + np.abs(z) ** 1.5,
    "x % 0.3": lambda x, y, z, t: np.fmod(x, 0.3),
    "if(x - 0.5, y, z)": lambda x, y, z, t: np.where(x >= 0.5, y, z),
    "min(x, y) - max(z, t)": lambda x, y, z, t: np.minimum(x, y) - np.maximum(z, t),
    "smoothstep(x) + half_smoothstep(y)": lambda x, y, z, t: (
        _smoothstep(x) + 2 * _smoothstep((y + 1) / 2) - 1
    ),
    "rotate_2D_x(x, y, pi/6) * rotate_2D_y(x, y, deg2rad(30))": lambda x, y, z, t: (
        (x * np.cos(np.pi / 6) - y * np.sin(np.pi / 6))
        * (x * np.sin(np.pi / 6) + y * np.cos(np.pi / 6))
    ),
    "sign(x - y) + compare(x, y) + smooth_abs(z, 10)": lambda x, y, z, t: (
        np.sign(x - y) + (x < y) + np.tanh(10 * z) * z
    ),
    "1e-3 * cosh(x) / (1 + tanh(y)^2) - .5E+1*sinh(z)": lambda x, y, z, t: (
        1e-3 * np.cosh(x) / (1 + np.tanh(y) ** 2) - 5.0 * np.sinh(z)
    ),
    "e^t + pi() * 2. + acos(0.5*z) + asin(0.5*y) + atan(x) + cos(t) + tan(y)": lambda x, y, z, t: (
        np.exp(t)
        + 2 * np.pi
        + np.arccos(0.5 * z)
        + np.arcsin(0.5 * y)
        + np.arctan(x)
        + np.cos(t)
        + np.tan(y)
    ),
    "floor(3*x) + ceil(2*y) - x*y*z*t / 7": lambda x, y, z, t: (
        np.floor(3 * x) + np.ceil(2 * y) - x * y * z * t / 7
    ),
    "+-+x - -y": lambda x, y, z, t: -x + y,
    "2*-3 + ((x))": lambda x, y, z, t: -6 + x,
}


@pytest.mark.parametrize("text", list(CASES))
def test_expressions_against_numpy(text):
    rng = np.random.default_rng(7)
    x, y, z = rng.uniform(-1.5, 1.5, (3, 50))
    t = 0.37
    expr = parse_expression(text)
    got = expr(x, y, z, t)
    want = np.broadcast_to(CASES[text](x, y, z, t), got.shape)
    assert got.shape == (50,)
    np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-14)


def test_expression_variables_and_broadcast():
    expr = parse_expression("0.3 * t")
    assert expr.variables == {"t"} and not expr.depends_on_position
    assert expr(t=2.0).shape == () and float(expr(t=2.0)) == pytest.approx(0.6)
    assert parse_expression("x + y").depends_on_position
    assert parse_expression("-2^2")() == 4.0  # TinyExpr: (-2)^2


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty"),
        ("1 +", "expected a number, a name or '\\(' at the end"),
        ("(x", "expected '\\)'"),
        ("2x", "expected an operator or the end at 'x'"),
        ("x y", "expected an operator"),
        ("foo(x)", "unknown name 'foo'"),
        ("__import__('os')", "unexpected character '_'"),
        ("x.real", "unexpected character '.'"),
        ("x == 1", "unexpected character '='"),
        ("max(1)", "max takes 2 arguments"),
        ("max(1, 2, 3)", "max takes 2 arguments"),
        ("atan2 1", "expected '\\(' after atan2"),
        ("pi(1)", "pi takes no argument"),
        ("1, 2", "TinyExpr's list"),
        ("fac(3)", "'fac' is not supported"),
        ("0x10", "hexadecimal"),
        ("T + 1", "unknown name 'T'"),
    ],
)
def test_expression_parser_refuses(text, message):
    with pytest.raises(ExpressionError, match=message):
        parse_expression(text)


# -- the scene ------------------------------------------------------------------------------
def test_scene_obstacle_moves_as_written_and_is_never_intersected(tmp_path):
    path = write_scene(tmp_path)
    scene = read_polyfem_scene(path)
    (ground,) = scene.obstacle_geometry
    assert ground.displacement == tuple(MOTION)
    assert ground.displacement_entry == "boundary_conditions.obstacle_displacements[0]"
    setup = build(path)
    contact, sim = setup.contact, setup.simulation
    (obstacle,) = contact.obstacles
    assert obstacle.moving and obstacle.num_vertices == 7
    X = obstacle.rest_positions
    traj = sim.run()
    nb = contact.surface.num_body_vertices
    for t in traj.times:
        np.testing.assert_allclose(obstacle.displacement(t), motion_numpy(X, t), atol=1e-15)
        U = contact.surface.obstacle_displacement(t)[nb:]
        np.testing.assert_allclose(U, motion_numpy(X, t), atol=1e-15)
    checks = check_trajectories(sim, [traj], contact)
    assert checks.intersecting == 0 and checks.min_distance > 0
    for k, u in enumerate(traj.u):
        assert not contact.intersects(u, step=k)
    gaps = np.array([r.min_distance for r in contact.records])
    assert np.isfinite(gaps).sum() >= 3 and np.nanmin(gaps) > 0  # in contact for some steps
    friction = max(abs(r.friction_force[0][0]) for r in contact.records)
    assert friction > 0  # the sliding ground drags the block


def test_3d_scene_obstacle_moves_as_written(tmp_path):
    """3D: a placed .obj plane moved by a dirichlet_boundary entry using x, y, z (PolyFEM: the
    transformed rest vertices), under a falling tetrahedral cube: intersection-free."""
    corners = np.array([[i, j, k] for k in (0, 1) for j in (0, 1) for i in (0, 1)], float)
    tets = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7]])
    tets = np.vstack([tets, [[0, 4, 6, 7]]])
    meshio.write(tmp_path / "cube.vtu", meshio.Mesh(corners, [("tetra", tets)]))
    plane = np.array([[-1, -1, 0], [2, -1, 0], [2, 2, 0], [-1, 2, 0], [0.5, 0.5, 0]], float)
    tris = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    meshio.write(tmp_path / "plane.obj", meshio.Mesh(plane, [("triangle", tris)]))
    value = ["0.2*t", "0", "-0.05*t*(1 + 0.1*x + 0.2*y) + 0.3*t*(z + 0.01)"]
    raw = {
        "geometry": [
            {
                "mesh": "cube.vtu",
                "transformation": {"scale": 0.2, "translation": [0.1, 0.1, 0.03]},
                "volume_selection": 1,
                "surface_selection": 1,
            },
            {
                "mesh": "plane.obj",
                "is_obstacle": True,
                "volume_selection": 2,
                "surface_selection": 2,
                "transformation": {"translation": [0, 0, -0.01]},
            },
        ],
        "time": {"tend": 0.05, "dt": 0.01},
        "contact": {"enabled": True, "dhat": 0.01, "epsv": 0.01, "friction_coefficient": 0.0},
        "boundary_conditions": {
            "rhs": [0, 0, 9.81],
            "dirichlet_boundary": [{"id": 2, "value": value, "dimension": [True, False, True]}],
        },
        "initial_conditions": {"velocity": [{"id": 1, "value": [0, 0, -1.0]}]},
        "materials": {"type": "NeoHookean", "E": 1e5, "nu": 0.3, "rho": 1000},
    }
    (tmp_path / "scene.json").write_text(json.dumps(raw))
    setup = build(tmp_path / "scene.json")
    contact, sim = setup.contact, setup.simulation
    (o,) = contact.obstacles
    X = o.rest_positions
    assert np.allclose(X, plane + np.array([0, 0, -0.01]))  # placed by its transformation
    traj = sim.run()
    for t in traj.times:
        x, y, z = X.T
        want = np.column_stack(
            [
                np.full(5, 0.2 * t),
                np.zeros(5),
                -0.05 * t * (1 + 0.1 * x + 0.2 * y) + 0.3 * t * (z + 0.01),
            ]
        )
        np.testing.assert_allclose(o.displacement(t), want, atol=1e-15)
    checks = check_trajectories(sim, [traj], contact)
    assert checks.intersecting == 0 and checks.min_distance > 0
    assert np.isfinite([r.min_distance for r in contact.records]).sum() >= 2


def test_constant_dirichlet_displacement_and_interpolation(tmp_path):
    """A dirichlet_boundary value on the obstacle's id moves it (numbers: a translation)."""

    def constant(raw):
        del raw["boundary_conditions"]["obstacle_displacements"]
        raw["boundary_conditions"]["dirichlet_boundary"] = [
            {"id": 2, "value": [0.0, -0.01], "dimension": [False, True]}
        ]

    (o,) = read_polyfem_scene(write_scene(tmp_path, constant)).obstacles(2)
    assert o.moving and o.motion(0.0).shape == (2,)  # uniform: a translation
    np.testing.assert_array_equal(o.displacement(0.0), np.tile([0.0, -0.01], (7, 1)))

    def ramp(raw):
        raw["boundary_conditions"]["obstacle_displacements"] = [
            {
                "id": [5, 2],
                "value": ["2", "x", 0],  # PolyFEM's 3-component default form in 2D
                "interpolation": [
                    {"type": "linear_ramp", "from": 0.02, "to": 0.05},
                    {"type": "linear"},
                ],
            }
        ]

    (o,) = read_polyfem_scene(write_scene(tmp_path, ramp)).obstacles(2)
    X = o.rest_positions
    for t, r in [(0.0, 0.0), (0.03, 0.01), (0.2, 0.03)]:
        np.testing.assert_allclose(
            o.displacement(t), np.column_stack([2 * r + 0 * X[:, 0], X[:, 0] * t])
        )

    def fixed(raw):
        raw["boundary_conditions"]["obstacle_displacements"] = [{"id": "all", "value": ["0", 0]}]

    (o,) = read_polyfem_scene(write_scene(tmp_path, fixed)).obstacles(2)
    assert not o.moving


def _edit(**changes):
    def edit(raw):
        entry = raw["boundary_conditions"]["obstacle_displacements"][0]
        entry.update(changes)

    return edit


@pytest.mark.parametrize(
    "edit, message",
    [
        (_edit(value=["0.3*t +", "0"]), r"obstacle_displacements\[0\]\.value\[0\]: expression"),
        (_edit(value=["sinh(t", "0"]), r"value\[0\]: expression 'sinh\(t': expected '\)'"),
        (_edit(value=["open(t)", "0"]), r"value\[0\]: .*unknown name 'open'"),
        (_edit(value=[[0.1] * 7, 0]), r"value\[0\] = .*per-vertex or per-time array"),
        (_edit(value=[{"value": 1, "unit": "mm"}, 0]), r"value\[0\] = .*an object is not"),
        (_edit(value=["block.vtu", 0]), r"values read from a file"),
        (_edit(value="0.1*t"), r"obstacle_displacements\[0\]\.value = '0.1\*t': a list"),
        (_edit(time_reference=[0, 1]), r"time_reference: per-time"),
        (_edit(interpolation={"type": "piecewise_linear"}), r"supported interpolation types"),
        (_edit(interpolation={"type": "linear_ramp"}), r"linear_ramp needs 'to'"),
        (_edit(id=7), r"id 7 is not the surface_selection of an obstacle"),
        (_edit(extra=1), r"unsupported key\(s\) \['extra'\]"),
    ],
)
def test_unsupported_entries_are_named(tmp_path, edit, message):
    path = write_scene(tmp_path, edit)
    with pytest.raises(ds.ParameterError, match=message) as info:
        read_polyfem_scene(path)
    assert str(path) in str(info.value)


def test_wrong_component_count_is_named(tmp_path):
    path = write_scene(tmp_path, _edit(value=["0.1*t", "0", "t"]))
    scene = read_polyfem_scene(path)
    with pytest.raises(
        ds.ParameterError, match=r"obstacle_displacements\[0\].*3 components for a 2D"
    ):
        scene.obstacles(2)

    with (
        pytest.warns(UserWarning, match="is an obstacle"),
        pytest.raises(ds.ParameterError, match="need kinematic obstacles"),
    ):
        read_polyfem_scene(write_scene(tmp_path), obstacles="clamp")


def test_motion_that_is_not_finite_is_named(tmp_path):
    path = write_scene(tmp_path, _edit(value=["1 / (t - 0.05)", "0"]))
    (o,) = read_polyfem_scene(path).obstacles(2)
    with pytest.raises(
        ds.ParameterError, match=r"obstacle_displacements\[0\].*t = 0.05 is not finite"
    ):
        o.displacement(0.05)


# -- a gradient through the moving obstacle --------------------------------------------------
def velocity_functional(
    folder: Path, comm: MPI.Comm = COMM
) -> tuple[ReducedFunctional, np.ndarray]:
    """The block's final height and spread against its initial velocity (ground moving).

    Uses ``folder/scene.json`` when it exists (written by :func:`write_scene`).
    """
    path = folder / "scene.json"
    sim = build(path if path.is_file() else write_scene(folder), comm).simulation

    def objective(f):
        return (f.X[1] + f.u[1]) * f.dx(1) + 10.0 * f.u[0] ** 2 * f.dx(1)

    rf = ReducedFunctional(
        sim, final_value(Integral(objective)), RigidVelocity(sim, 1, angular=False)
    )
    return rf, np.array([0.2, -1.0])


@pytest.mark.parametrize("direction", ["random", "gradient"])
def test_velocity_gradient_through_a_moving_obstacle(tmp_path, direction):
    rf, q = velocity_functional(tmp_path)
    J, g = rf.value_and_gradient(q)
    assert np.isfinite(J) and np.linalg.norm(g) > 1e-8
    d = np.random.default_rng(13).standard_normal(2) if direction == "random" else g
    fd = finite_difference_check(rf, q, d / np.linalg.norm(d), [1e-3, 1e-4, 1e-5], gradient=g)
    assert fd.relative_error < 1e-6, str(fd)
