"""PolyFEM's optimisation JSON (``opt.json``) read and mapped onto diffsolids.

:func:`read_polyfem_optimization` reads an ``opt.json`` (PolyFEM's ``json-specs/
opt-input-spec.json``) and the scenes of its ``states`` (``{"path": ...}``, relative to the
file; read by :func:`~diffsolids.polyfem.read_polyfem_scene`, bodies as written).
:meth:`PolyFEMOptimization.build` makes the problem: state 0 is the optimised run, every other
state a target run (solved once at build, on the same mesh); ``variable_to_simulation``
becomes controls (:mod:`diffsolids.polyfem.variables`), ``functionals`` the objective
(:mod:`diffsolids.polyfem.functionals`), and ``solver.nonlinear`` the options of
:func:`~diffsolids.optimize.minimize`:

- ``solver``: ``L-BFGS`` or ``L-BFGS-B`` (both are diffsolids' projected L-BFGS);
  ``max_iterations`` (default 100 of the spec ... as written, else 100); ``grad_norm`` (stop
  when the projected gradient's norm is below it, absolute: PolyFEM's rule);
  ``box_constraints``: ``bounds`` [lower, upper] (scalars or one per parameter) and
  ``max_change`` (largest change of a parameter per iteration); ``line_search.method``
  ``Backtracking`` (Armijo backtracking, as diffsolids' line search) or ``None`` (diffsolids'
  line search is kept: it is what keeps every trial admissible).
- ``stopping_conditions``: forms; the optimisation stops when every one is <= 0 at an
  accepted iterate (``AdjointNLProblem::stop``).
- ``parameters``: one entry ``{"number", "initial"}``; without ``initial`` the start is the
  value the scene gives (``inverse_eval``).

Ignored as harmless: ``output``, ``solver.max_threads``, ``solver.advanced``,
``solver.nonlinear.advanced``, ``print_energy``. Anything else unsupported raises
:class:`~diffsolids.errors.ParameterError` naming it.
"""

import json
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from mpi4py import MPI

from diffsolids.errors import ParameterError
from diffsolids.polyfem.functionals import FunctionalContext, objective_of, objective_sum
from diffsolids.polyfem.scene import PolyFEMScene, read_polyfem_scene
from diffsolids.polyfem.variables import controls_of, needs_lame

if TYPE_CHECKING:
    from diffsolids.contact import ContactTerm
    from diffsolids.controls import Control
    from diffsolids.mesh import Domain
    from diffsolids.model import Model
    from diffsolids.objectives import Objective
    from diffsolids.optimize import LBFGSOptions
    from diffsolids.reduced_functional import ReducedFunctional
    from diffsolids.simulation import Simulation, Trajectory
    from diffsolids.solvers.newton import SolverOptions

__all__ = [
    "PolyFEMOptimization",
    "PolyFEMProblem",
    "StoppingConditions",
    "read_polyfem_optimization",
]

_TOP = {
    "parameters",
    "variable_to_simulation",
    "functionals",
    "states",
    "solver",
    "stopping_conditions",
    "output",
}
_SOLVER = {"nonlinear", "max_threads", "advanced"}
_NONLINEAR = {
    "solver",
    "line_search",
    "max_iterations",
    "grad_norm",
    "box_constraints",
    "advanced",
}
_METHODS = ("L-BFGS", "L-BFGS-B", "LBFGS", "LBFGSB")
_LINE_SEARCHES = ("Backtracking", "backtracking", "Armijo", "None")


def _check_keys(section: Mapping, known: set, where: str) -> None:
    if not isinstance(section, Mapping):
        raise ParameterError(f"{where} must be an object, got {section!r}")
    unknown = sorted(set(section) - known)
    if unknown:
        raise ParameterError(f"{where}: unsupported keys {unknown} (supported: {sorted(known)})")


@dataclass
class StoppingConditions:
    """PolyFEM's stopping conditions: stop when every form is <= 0 at an accepted iterate.

    An ``optimizer.stop_conditions`` callable (collective): the forms are evaluated on the
    accepted iterate's trajectory.
    """

    simulation: "Simulation"
    objectives: list["Objective"]
    values: list[float] = field(default_factory=list)

    def evaluate(self, trajectory: "Trajectory") -> list[float]:
        """The forms' values along a trajectory of the simulation."""
        from diffsolids.objectives.functional import TimeGrid
        from diffsolids.objectives.values import series_values

        integ = self.simulation.integrator
        grid = TimeGrid(integ.num_steps, integ.dt, integ.dynamic)
        out = []
        for obj in self.objectives:
            table = {}
            for leaf in obj.leaves():
                table[leaf] = np.asarray(series_values(self.simulation, leaf, trajectory))
            reg = {r: r.evaluate(self.simulation.model) for r in obj.regularisers()}
            out.append(float(obj.value(table, reg, grid)))
        return out

    def __call__(self, record: Any, optimizer: Any) -> bool | str:
        """Whether to stop (a reason string) at the optimiser's accepted iterate."""
        if not self.objectives:
            return False
        self.values = self.evaluate(optimizer.point.trajectory)
        if all(v <= 0.0 for v in self.values):
            return "stopping_conditions: every condition <= 0 " + str(
                [f"{v:.3g}" for v in self.values]
            )
        return False


@dataclass
class PolyFEMProblem:
    """The built problem of an opt.json.

    Attributes:
        model: The model of state 0.
        contact: Its contact term (None without contact).
        simulation: The simulation of state 0.
        targets: The target runs, by state index.
        controls: The controls (their concatenated parameters are PolyFEM's x).
        rf: The ReducedFunctional of the functionals' sum.
        labels: One label per functional (its ``print_energy`` or type).
        q0: The initial parameters.
        options: The L-BFGS options of ``solver.nonlinear``.
        stopping: The stopping conditions (pass as ``stop_conditions=[problem.stopping]``).
        inner_product: The initial inverse Hessian of L-BFGS (pass as ``inner_product``):
            the mesh motion's Riesz map for shape variables, else None (the identity).
    """

    model: "Model"
    contact: "ContactTerm | None"
    simulation: "Simulation"
    targets: dict[int, "Trajectory"]
    controls: list["Control"]
    rf: "ReducedFunctional"
    labels: list[str]
    q0: np.ndarray
    options: "LBFGSOptions"
    stopping: StoppingConditions
    inner_product: "Callable[[np.ndarray], np.ndarray] | None" = None


@dataclass
class PolyFEMOptimization:
    """An opt.json as written, with the scenes of its states.

    Attributes:
        path: The file.
        states: The scenes of ``states`` (0: the optimised run; others: targets).
        raw: The JSON.
    """

    path: Path
    states: list[PolyFEMScene]
    raw: dict

    @property
    def num_parameters(self) -> int:
        """``parameters[0].number``."""
        return int(self.raw["parameters"][0]["number"])

    @property
    def initial(self) -> np.ndarray | None:
        """``parameters[0].initial`` (None: the scene's values)."""
        init = self.raw["parameters"][0].get("initial")
        return None if init is None else np.asarray(init, dtype=float)

    def lbfgs_options(
        self, max_iterations: int | None = None, grad_norm: float | None = None
    ) -> "LBFGSOptions":
        """The LBFGSOptions of ``solver.nonlinear``.

        Args:
            max_iterations: Replace ``max_iterations``.
            grad_norm: Replace ``grad_norm`` (the projected gradient's norm at which to stop).
        """
        from diffsolids.optimize import LBFGSOptions

        nl = self.raw.get("solver", {}).get("nonlinear", {})
        box = nl.get("box_constraints", {})
        iterations = max_iterations if max_iterations is not None else nl.get("max_iterations")
        max_change = box.get("max_change")
        if grad_norm is None:
            grad_norm = float(nl.get("grad_norm", 1e-8))
        elif not grad_norm >= 0.0:
            raise ParameterError(f"grad_norm must be >= 0, got {grad_norm}")
        return LBFGSOptions(
            max_iterations=int(iterations if iterations is not None else 100),
            gradient_atol=float(grad_norm),
            gradient_rtol=0.0,
            max_change=None if max_change is None else float(max_change),
        )

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``solver.nonlinear.box_constraints.bounds`` per parameter (default unbounded)."""
        n = self.num_parameters
        bounds = self.raw.get("solver", {}).get("nonlinear", {}).get("box_constraints", {})
        if "bounds" not in bounds:
            return np.full(n, -np.inf), np.full(n, np.inf)
        lo, hi = bounds["bounds"]
        return (
            np.broadcast_to(np.asarray(lo, dtype=float), n).copy(),
            np.broadcast_to(np.asarray(hi, dtype=float), n).copy(),
        )

    def build(
        self,
        comm: MPI.Comm = MPI.COMM_WORLD,
        steps: int | None = None,
        solver_options: "SolverOptions | None" = None,
        max_iterations: int | None = None,
        stiffness: float | str | None = "suggest",
        contact_options: Mapping[str, Any] | None = None,
        follow_branch: bool = False,
        grad_norm: float | None = None,
    ) -> PolyFEMProblem:
        """Build the problem: state 0's simulation, the target runs, controls and objective.

        Args:
            comm: Communicator of the mesh.
            steps: Run only the first ``steps`` time steps of every state (None: as written).
            solver_options: Newton options (default :class:`~diffsolids.SolverOptions`).
            max_iterations: Replace ``solver.nonlinear.max_iterations``.
            stiffness: The barrier stiffness: "suggest" (the default:
                :func:`~diffsolids.contact.suggest_barrier_stiffness` for state 0's scene,
                used by every state), None (each scene's ``barrier_stiffness`` as PolyFEM
                means it, :mod:`diffsolids.polyfem.contact`) or a number.
            contact_options: Further ContactTerm arguments of every state (e.g.
                ``area_weighting``).
            follow_branch: Make the run at the initial parameters the branch reference of
                every forward (``ReducedFunctional(..., branch_reference=q0)``): for scenes
                whose contact steps have several local minima.
            grad_norm: Replace ``solver.nonlinear.grad_norm`` (where a parameter barely
                seen by J needs a smaller one than the file's).

        Raises:
            ParameterError: An unsupported or inconsistent entry (named).
        """
        from diffsolids.controls import ControlSet
        from diffsolids.optimize import MeshMotionControl, ShapeInnerProduct
        from diffsolids.reduced_functional import ReducedFunctional

        lame = needs_lame(self.raw["variable_to_simulation"])
        domain = self.states[0].domain(comm)
        setup = {"lame": lame, "steps": steps, "solver_options": solver_options}
        setup["contact_options"] = dict(contact_options or {})
        runs = [self._setup(self.states[0], domain, stiffness=stiffness, **setup)]
        model, contact, sim = runs[0]
        if contact is not None and stiffness is not None:
            stiffness = contact.stiffness  # the targets' barrier is the run's
        runs += [
            self._setup(scene, domain, stiffness=stiffness, **setup) for scene in self.states[1:]
        ]
        targets = {k: runs[k][2].run() for k in self._target_states()}
        controls = controls_of(
            sim,
            contact,
            self.raw["variable_to_simulation"],
            self.num_parameters,
            self.states[0].body_ids,
        )
        controls = self._bounded(controls)
        ctx = FunctionalContext(sim, targets)
        objective, labels = objective_sum(ctx, self.raw["functionals"])
        stops = [
            objective_of(ctx, s, f"stopping_conditions[{k}]")
            for k, s in enumerate(self.raw.get("stopping_conditions", []))
        ]
        q0 = ControlSet(controls, sim).value() if self.initial is None else self.initial
        size = sum(c.size for c in controls)
        if q0.size != size:
            raise ParameterError(
                f"{self.path}: parameters[0].initial has {q0.size} values, the variables "
                f"take {size}"
            )
        reference = np.asarray(q0, dtype=float) if follow_branch else None
        rf = ReducedFunctional(sim, objective, controls, branch_reference=reference)
        shapes = [c for c in controls if isinstance(c, MeshMotionControl)]
        return PolyFEMProblem(
            model=model,
            contact=contact,
            simulation=sim,
            targets=targets,
            controls=controls,
            rf=rf,
            labels=labels,
            q0=np.asarray(q0, dtype=float),
            options=self.lbfgs_options(max_iterations, grad_norm),
            stopping=StoppingConditions(sim, stops),
            inner_product=ShapeInnerProduct(rf) if shapes else None,
        )

    @staticmethod
    def _setup(
        scene: PolyFEMScene,
        domain: "Domain",
        lame: bool,
        steps: int | None,
        solver_options: "SolverOptions | None",
        stiffness: float | str | None,
        contact_options: dict,
    ) -> tuple["Model", "ContactTerm | None", "Simulation"]:
        """One state's model, contact term and simulation on the shared domain."""
        from diffsolids.integrators import BDF

        model = scene.model(domain, lame=lame)
        integrator = scene.integrator()
        if steps is not None and not scene.static:
            integrator = BDF(scene.bdf_order, scene.dt, min(int(steps), scene.num_steps))
        contact = scene.contact_term(model, integrator, stiffness, **contact_options)
        sim = scene.simulation(model, integrator, solver_options)
        return model, contact, sim

    def _target_states(self) -> list[int]:
        """States a form names as its ``target_state``."""
        found: set[int] = set()

        def walk(node: object) -> None:
            if isinstance(node, Mapping):
                if "target_state" in node:
                    found.add(int(node["target_state"]))
                for v in node.values():
                    walk(v)
            elif isinstance(node, list):
                for v in node:
                    walk(v)

        walk(self.raw["functionals"])
        walk(self.raw.get("stopping_conditions", []))
        bad = sorted(s for s in found if not 0 < s < len(self.states))
        if bad:
            raise ParameterError(
                f"{self.path}: target_state {bad} is not a target state (1..{len(self.states) - 1})"
            )
        return sorted(found)

    def _bounded(self, controls: list["Control"]) -> list["Control"]:
        """The controls, wrapped with box_constraints.bounds when given."""
        from diffsolids.controls import AffineControl

        lo, hi = self.bounds()
        if np.all(np.isinf(lo)) and np.all(np.isinf(hi)):
            return controls
        n = self.num_parameters
        inner_lo = np.concatenate([c.bounds()[0] for c in controls])
        inner_hi = np.concatenate([c.bounds()[1] for c in controls])
        return [
            AffineControl(
                controls,
                np.eye(n),
                name="parameters",
                lower=np.maximum(lo, inner_lo),
                upper=np.minimum(hi, inner_hi),
            )
        ]


def _check(raw: dict, path: Path) -> None:
    _check_keys(raw, _TOP, f"{path}")
    for key in ("parameters", "variable_to_simulation", "functionals", "states"):
        if key not in raw:
            raise ParameterError(f"{path}: no {key!r} section")
    params = raw["parameters"]
    if not isinstance(params, list) or len(params) != 1:
        raise ParameterError(f"{path}: parameters must be a list of one entry, got {params!r}")
    _check_keys(params[0], {"number", "initial"}, f"{path}: parameters[0]")
    solver = raw.get("solver", {})
    _check_keys(solver, _SOLVER, f"{path}: solver")
    nl = solver.get("nonlinear", {})
    _check_keys(nl, _NONLINEAR, f"{path}: solver.nonlinear")
    if nl.get("solver", "L-BFGS") not in _METHODS:
        raise ParameterError(
            f"{path}: solver.nonlinear.solver {nl['solver']!r} is not supported ({_METHODS})"
        )
    ls = nl.get("line_search", {})
    _check_keys(ls, {"method", "min_step_size"}, f"{path}: solver.nonlinear.line_search")
    if ls.get("method", "Backtracking") not in _LINE_SEARCHES:
        raise ParameterError(
            f"{path}: line_search.method {ls['method']!r} is not supported ({_LINE_SEARCHES})"
        )
    _check_keys(
        nl.get("box_constraints", {}),
        {"bounds", "max_change"},
        f"{path}: solver.nonlinear.box_constraints",
    )
    states = raw["states"]
    if not isinstance(states, list) or not states:
        raise ParameterError(f"{path}: states must be a non-empty list")
    for k, s in enumerate(states):
        _check_keys(s, {"path"}, f"{path}: states[{k}]")


def read_polyfem_optimization(path: str | os.PathLike) -> PolyFEMOptimization:
    """Read a PolyFEM ``opt.json`` and the scenes of its states.

    Raises:
        ParameterError: A missing file, invalid JSON, an unsupported key (named) or target
            scenes that place other meshes than state 0.
    """
    path = Path(path)
    if not path.is_file():
        raise ParameterError(f"PolyFEM optimisation file {path} does not exist")
    try:
        raw = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ParameterError(f"{path} is not valid JSON: {error}") from None
    _check(raw, path)
    states = [read_polyfem_scene(path.parent / s["path"]) for s in raw["states"]]
    for k, scene in enumerate(states[1:], start=1):
        if not states[0].same_geometry(scene):
            raise ParameterError(
                f"{path}: states[{k}] ({scene.path.name}) places other meshes than states[0]"
            )
    return PolyFEMOptimization(path=path, states=states, raw=raw)
