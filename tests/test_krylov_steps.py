"""Newton steps solved by GMRES + algebraic multigrid (``pc_type`` ``gamg``) instead of MUMPS LU.

The forward with ``petsc_options={"pc_type": "gamg"}`` assembles a scalar (AIJ) Jacobian with the
rigid body modes as near-null space and solves each Newton system by GMRES; the adjoint then
solves its systems by GMRES with the same preconditioner on the assembled exact Jacobian (no
factorisation anywhere). Checked on the incline scene of test_gradients_contact.py (damped
Neo-Hookean, IPC contact with lagged friction, BDF2, 2D), on its static 3D contact scene (shape
gradient) and on a 3D P2 linear-elastic bar (a quadratic potential, whose LU adjoint reuses the
forward's factors): values and gradients equal to the LU ones, central differences in a random
direction and along the gradient, the solver options reaching the multigrid levels and leaving
the options database, and the failure of a Krylov adjoint solve as a clear error (in this
process and in a child process).
"""

import gc
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import test_gradients_contact as scenes
import ufl
from child_process import assert_child_raises
from gradient_scenes import SCENES, build_model
from petsc4py import PETSc

import diffsolids as ds
from diffsolids.adjoint.linear import AdjointSolverOptions
from diffsolids.controls import FrictionControl, ParameterControl, ShapeControl
from diffsolids.errors import ConvergenceError
from diffsolids.objectives import Integral, final_value
from diffsolids.reduced_functional import ReducedFunctional

GAMG = {"pc_type": "gamg", "ksp_rtol": 1e-12}


def _incline(monkeypatch, petsc_options: dict, adjoint: AdjointSolverOptions | None = None):
    monkeypatch.setattr(scenes, "NEWTON", ds.SolverOptions(rtol=1e-12, petsc_options=petsc_options))
    model, contact, sim, objective = scenes.incline_scene(1, 2, num_steps=4)
    controls = [
        ParameterControl(model, "E", "field", log=True),
        FrictionControl(contact, pairs=[("slab", "block")]),
    ]
    kwargs = {} if adjoint is None else {"adjoint_options": adjoint}
    return ReducedFunctional(sim, objective, controls, **kwargs), contact


def test_gamg_matrix_and_defaults(monkeypatch):
    rf, _ = _incline(monkeypatch, {"pc_type": "gamg"})
    newton = rf.simulation.solver
    ksp = newton.snes.getKSP()
    assert newton.A.getType() == PETSc.Mat.Type.SEQAIJ
    assert newton.A.getNearNullSpace().handle != 0
    assert len(newton.A.getNearNullSpace().getVecs()) == 3  # 2D: two translations, a rotation
    assert (ksp.getType(), ksp.getPC().getType()) == ("gmres", "gamg")
    assert ksp.getTolerances()[0] == pytest.approx(1e-8)
    lu = _incline(monkeypatch, {})[0].simulation.solver
    assert lu.A.getType() == PETSc.Mat.Type.SEQBAIJ and lu.snes.getKSP().getType() == "preonly"


def test_options_reach_the_solvers_and_leave_the_database(monkeypatch):
    options = {**GAMG, "pc_gamg_threshold": 0.02, "mg_levels_ksp_max_it": 3}
    rf, _ = _incline(monkeypatch, options)
    rf(rf.initial_parameters())
    rf.derivative()
    forward, adjoint = rf.simulation.solver.snes.getKSP(), rf._sweep.linear._iterative
    assert forward.getTolerances()[0] == pytest.approx(1e-12)
    for ksp in (forward, adjoint):  # mg_levels_ksp_max_it reached both multigrid hierarchies
        assert ksp.getPC().getType() == "gamg"
        assert ksp.getPC().getMGSmoother(1).getTolerances()[3] == 3
    prefix = rf.simulation.solver.prefix
    assert prefix.startswith("diffsolids_s")
    names = PETSc.Options().getAll()
    assert names[f"{prefix}mg_levels_ksp_max_it"] == "3"  # kept while the solver lives
    assert not [k for k in names if re.match(r"diffsolids_(?!s\d+_)", k)]  # none for others
    del rf, forward, adjoint, ksp
    gc.collect()
    leftovers = [k for k in PETSc.Options().getAll() if k.startswith(prefix)]
    assert not leftovers, leftovers  # removed with the solver


def _lu_and_gamg(build) -> list[tuple]:
    """(J, gradient, adjoint stats, solver) of ``build(petsc_options)`` with LU, then GAMG."""
    out = []
    for options in ({}, GAMG):
        rf = build(options)
        q = rf.initial_parameters()
        out.append((rf(q), rf.derivative(), dict(rf.adjoint_stats), rf.simulation.solver))
    return out


def _assert_equal(lu: tuple, mg: tuple) -> None:
    """Both solved to 1e-12: measured differences up to 1e-15 (value) and 1e-12 (gradient); an
    adjoint solved to the forward's 1e-8 misses the gradient tolerance by 100x."""
    assert mg[2]["factorisations"] == 0 and mg[2]["direct_solves"] == 0
    assert mg[2]["krylov_iterations"] > 0
    assert abs(mg[0] - lu[0]) <= 1e-12 * abs(lu[0])
    assert np.linalg.norm(mg[1] - lu[1]) <= 1e-10 * np.linalg.norm(lu[1])


def test_gamg_value_and_gradient_equal_lu(monkeypatch):
    lu, mg = _lu_and_gamg(lambda options: _incline(monkeypatch, options)[0])
    assert mg[2]["krylov_iterations"] >= 4  # every adjoint solve (4 steps) was a GMRES solve
    _assert_equal(lu, mg)


def test_gamg_static_contact_3d_shape(monkeypatch):
    def build(options):
        monkeypatch.setattr(scenes, "NEWTON", ds.SolverOptions(rtol=1e-12, petsc_options=options))
        model, _, sim, objective = scenes.static_scene(3)
        return ReducedFunctional(sim, objective, ShapeControl(model, "all"))

    lu, mg = _lu_and_gamg(build)
    assert len(mg[3].A.getNearNullSpace().getVecs()) == 6  # 3D: three translations, rotations
    _assert_equal(lu, mg)


def test_gamg_linear_elasticity_3d_p2(monkeypatch):
    """A quadratic potential: the adjoint must not reuse the forward's (1e-8) Krylov solver."""

    def build(options):
        model = build_model(SCENES["3d-p2-lin-lame"])
        opts = ds.SolverOptions(rtol=1e-12, petsc_options={**options, "ksp_rtol": 1e-8})
        sim = ds.Simulation(model, ds.BDF(2, 0.05, 3), opts, v0=[0.0, 0.0, 0.3], progress=False)
        objective = final_value(Integral(lambda f: ufl.dot(f.u, f.u) * f.dx, "u2"))
        controls = [ShapeControl(model, "all"), ParameterControl(model, "mu", "bodies")]
        return ReducedFunctional(sim, objective, controls)

    lu, mg = _lu_and_gamg(build)
    assert mg[3].quadratic
    _assert_equal(lu, mg)


def test_gamg_gradient_against_finite_differences(monkeypatch):
    rf, contact = _incline(monkeypatch, GAMG)
    scenes.check_gradient(rf, contact, scenes._direction(rf.size, 0.05), taylor_h0=0.2)
    assert rf.adjoint_stats["factorisations"] == 0


def test_krylov_adjoint_failure_is_named(monkeypatch):
    rf, _ = _incline(monkeypatch, GAMG, AdjointSolverOptions(max_iterative=1))
    rf(rf.initial_parameters())
    with pytest.raises(ConvergenceError, match=r"GMRES preconditioned by 'gamg' stopped after 1"):
        rf.derivative()


_SCRIPT = """
import sys
sys.path.insert(0, {tests!r})
import pytest
from test_krylov_steps import GAMG, _incline
from diffsolids.adjoint.linear import AdjointSolverOptions
mp = pytest.MonkeyPatch()
rf, _ = _incline(mp, GAMG, AdjointSolverOptions(max_iterative=1))
rf(rf.initial_parameters())
rf.derivative()
"""


def test_krylov_adjoint_failure_in_a_child_process(tmp_path):
    script = _SCRIPT.format(tests=str(Path(__file__).parent))
    error = "diffsolids.errors.ConvergenceError: adjoint linear solve of step"
    assert_child_raises(script, error, tmp_path)


_COMMAND_LINE = """
import sys
sys.path.insert(0, {tests!r})
import test_gradients_contact as scenes
import diffsolids as ds
scenes.NEWTON = ds.SolverOptions(rtol=1e-10)
model, contact, sim, objective = scenes.incline_scene(1, 2, num_steps=1)
print("line search", sim.solver.snes.getLineSearch().getType())
sim.run()
"""


def test_command_line_options_reach_the_solver_and_count_as_used(tmp_path):
    """``-diffsolids_*`` options are copied to the solver's own prefix and read there."""
    script = _COMMAND_LINE.format(tests=str(Path(__file__).parent))
    env = {**os.environ, "PETSC_OPTIONS": "-diffsolids_snes_linesearch_type basic"}
    child = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300
    )
    assert child.returncode == 0, child.stderr
    assert "line search basic" in child.stdout, child.stdout  # above the default (bt)
    assert "not used" not in child.stderr + child.stdout, child.stderr + child.stdout
