"""Scenes of our own in PolyFEM's files: a block thrown onto a clamped ground, with targets and
opt.json files of each kind the runner maps (tests/test_polyfem_optimization.py and its MPI
twin)."""

import json
from pathlib import Path

import meshio
import numpy as np

__all__ = ["write_experiment", "write_rectangle", "write_shape_experiment"]


def write_rectangle(folder: Path, n: tuple[int, int] = (8, 4)) -> Path:
    """A triangulated [0, 2] x [0, 1] rectangle as gmsh 2.2 (no physical groups)."""
    x, y = np.meshgrid(np.linspace(0, 2, n[0] + 1), np.linspace(0, 1, n[1] + 1), indexing="ij")
    points = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    idx = np.arange(x.size).reshape(x.shape)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    cells = np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    path = folder / "rectangle.msh"
    meshio.write(path, meshio.Mesh(points, [("triangle", cells)]), file_format="gmsh22")
    return path


def _scene(velocity, E: float, friction: float, steps: int) -> dict:
    """A 0.2 x 0.1 block thrown at ``velocity`` onto a 2 x 0.1 ground clamped on its boundary."""
    return {
        "geometry": [
            {
                "mesh": "rectangle.msh",
                "transformation": {"scale": [1.0, 0.1], "translation": [-0.5, -0.1]},
                "volume_selection": 3,
                "surface_selection": 2,
            },
            {
                "mesh": "rectangle.msh",
                "transformation": {"scale": 0.1, "translation": [0.0, 0.002]},
                "volume_selection": 1,
                "surface_selection": 1,
            },
        ],
        "time": {"tend": 0.01 * steps, "dt": 0.01, "integrator": "ImplicitEuler"},
        "contact": {"enabled": True, "dhat": 1e-3, "friction_coefficient": friction, "epsv": 1e-3},
        "boundary_conditions": {
            "rhs": [0, 9.81],
            "dirichlet_boundary": [{"id": 2, "value": [0, 0]}],
        },
        "initial_conditions": {"velocity": [{"id": 1, "value": list(velocity)}]},
        "materials": [
            {"id": 3, "type": "NeoHookean", "E": 1e5, "nu": 0.3, "rho": 100},
            {"id": 1, "type": "NeoHookean", "E": E, "nu": 0.3, "rho": 100},
        ],
    }


VARIABLES = {
    "initial": {
        "type": "initial",
        "composition": [
            {"type": "per-body-to-per-node", "state": 0},
            {"type": "append-const", "start": 0, "size": None, "value": 0},
        ],
    },
    "friction": {"type": "friction", "composition": [{"type": "scale", "value": 1}]},
    "elastic": {
        "type": "elastic",
        "composition": [
            {"type": "exp", "from": -1, "to": -1},
            {"type": "per-body-to-per-elem", "state": 0},
        ],
    },
}
PARAMETERS = {
    "initial": {"number": 4, "initial": [0, 0, 1.0, -0.5]},
    "friction": {"number": 1, "initial": [0.2]},
    "elastic": {"number": 4},
}
TARGET = {
    "type": "transient_integral",
    "state": 0,
    "weight": 10,
    "static_objective": {"type": "target", "state": 0, "target_state": 1, "surface_selection": [1]},
}


def write_experiment(folder: Path, kind: str, steps: int = 12, functionals=None, **opt) -> Path:
    """run.json, target.json and opt.json of a ``kind`` ("initial", "friction", "elastic")."""
    folder.mkdir(parents=True, exist_ok=True)
    write_rectangle(folder)
    run = _scene((1.0, -0.5), 2e4, 0.2, steps)
    target = {
        "initial": _scene((1.5, -1.0), 2e4, 0.2, steps),
        "friction": _scene((1.0, -0.5), 2e4, 0.5, steps),
        "elastic": _scene((1.0, -0.5), 6e4, 0.2, steps),
    }[kind]
    (folder / "run.json").write_text(json.dumps(run))
    (folder / "target.json").write_text(json.dumps(target))
    variable = json.loads(json.dumps(VARIABLES[kind]))
    if kind == "initial":  # u0 of every node: (9 x 5 nodes) x 2 bodies x 2 components
        variable["composition"][1]["size"] = 2 * 45 * 2
    spec = {
        "parameters": [PARAMETERS[kind]],
        "variable_to_simulation": [{"state": 0, **variable}],
        "functionals": functionals or [TARGET],
        "states": [{"path": "run.json"}, {"path": "target.json"}],
        "solver": {"nonlinear": {"solver": "L-BFGS", "max_iterations": 5, "grad_norm": 1e-8}},
        **opt,
    }
    path = folder / "opt.json"
    path.write_text(json.dumps(spec, indent=1))
    return path


def write_shape_experiment(folder: Path) -> Path:
    """A static 2 x 1 plate clamped on its left side (id 1), pulled down on its right (id 3):
    the hook's forms (stress norm, soft volume bound, Laplacian smoothing, min_jacobian stop)
    on the boundary vertices of its top and bottom (ids 2, 4)."""
    folder.mkdir(parents=True, exist_ok=True)
    write_rectangle(folder)
    scene = {
        "geometry": [
            {
                "mesh": "rectangle.msh",
                "volume_selection": 1,
                "surface_selection": {"threshold": 1e-6},
            }
        ],
        "boundary_conditions": {
            "rhs": [0, 0],
            "dirichlet_boundary": [{"id": 1, "value": [0, 0]}],
            "neumann_boundary": [{"id": 3, "value": [0, -2.0]}],
        },
        "materials": {"type": "NeoHookean", "E": 200, "nu": 0.35},
    }
    (folder / "run.json").write_text(json.dumps(scene))
    spec = {
        "parameters": [{"number": 10}],
        "variable_to_simulation": [
            {
                "type": "shape",
                "state": 0,
                "composite_map_type": "boundary_excluding_surface",
                "surface_selection": [1, 3],
                "composition": [],
            }
        ],
        "functionals": [
            {
                "type": "power",
                "power": 0.125,
                "objective": {"type": "stress_norm", "state": 0, "power": 8},
            },
            {
                "type": "soft_constraint",
                "weight": 1e2,
                "soft_bound": [0, 1.9],
                "objective": {"type": "volume", "state": 0},
            },
            {
                "type": "boundary_smoothing",
                "state": 0,
                "weight": 20,
                "power": 4,
                "surface_selection": [2, 4],
                "scale_invariant": False,
            },
        ],
        "states": [{"path": "run.json"}],
        "stopping_conditions": [
            {
                "type": "plus-const",
                "value": -1e-6,
                "objective": {"type": "min_jacobian", "state": 0},
            }
        ],
        "solver": {"nonlinear": {"solver": "L-BFGS", "max_iterations": 3, "grad_norm": 1e-8}},
    }
    path = folder / "opt.json"
    path.write_text(json.dumps(spec, indent=1))
    return path
