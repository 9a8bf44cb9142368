"""The discrete adjoint of a forward run: one linear solve per step, backward in time.

Reverse-mode differentiation of exactly what the forward computed. With BDF_m (start-up orders
m_i = min(i, m)) step i solves G_i(u^i; u_tilde^i, u^{i-1}, X, q) = 0 with the predictor
u_tilde^i = -sum_j alpha_j (u^{i-j} + beta dt v^{i-j}) and then sets
v^i = (u^i + sum_j alpha_j u^{i-j}) / (beta dt). Walking i = N..1 with accumulated adjoints
ubar^i, vbar^i (seeded with dJ/du^i, dJ/dv^i):
  1. vbar^i is complete: push it through the velocity formula into ubar^i and ubar^{i-j};
  2. solve K_i lambda_i = -ubar^i (K_i = dG_i/du^i, symmetric; zero on Dirichlet rows);
  3. push lambda_i into the inputs of G_i: ubar^{i-j} and vbar^{i-j} through u_tilde, ubar^{i-1}
     through damping (and contact through lagged friction and the BDF velocity), and X, q.
The objective's partials with respect to u_prev and u_tilde of step i (integrals reading the
history fields) take the same paths into ubar^{i-1} and ubar^{i-j}, vbar^{i-j}. Step i is
set up as the forward set it up (:meth:`~diffsolids.simulation.Simulation.begin_step`), and
the pushes through the velocity and the predictor are the transposes that the step's
:class:`~diffsolids.integrators.TimeStep` holds (static: no predictor, v^i = (u^i - u^{i-1})/dt).
At i = 0, ubar^0 and vbar^0 are dJ/du^0 and dJ/dv^0. This is the recurrence of paper eqs. 12-15
and appendix A.2 written with the eliminated velocity: lambda_i plays the role of p_i (scaled by
beta dt), the pushes of step 1 and 3 are the mu/nu recurrences, the start-up steps use their own
alpha and beta (consistency), and the mass-matrix shape derivative (appendix A.3) is the
coordinate derivative of the inertia term inside L_i.
"""

import logging
import time
from collections import defaultdict
from collections.abc import Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager
from typing import TYPE_CHECKING

import dolfinx.la
import numpy as np
from dolfinx import fem
from mpi4py import MPI

from diffsolids.adjoint.forms import AdjointForms
from diffsolids.adjoint.linear import AdjointLinearSolver, AdjointSolverOptions
from diffsolids.adjoint.sensitivities import Sensitivities, Targets
from diffsolids.integrators import TimeStep
from diffsolids.io.progress import ProgressBar, progress_bar
from diffsolids.parallel import collective_comm
from diffsolids.solvers.packing import CoefficientGathers, FormPacker
from diffsolids.states import Phase

if TYPE_CHECKING:
    from diffsolids.adjoint.checkpointing import CheckpointedRun
    from diffsolids.objectives import Integral, NumericIntegral
    from diffsolids.simulation import Simulation
    from diffsolids.states import StateHistory, Trajectory

__all__ = ["BackwardSweep"]

logger = logging.getLogger("diffsolids")


class _Adjoints(dict):
    """Accumulated adjoints ubar^i (or vbar^i) by step, created as zeros when first touched."""

    def __init__(self, n: int) -> None:
        super().__init__()
        self.n = n

    def __missing__(self, i: int) -> np.ndarray:
        value = self[i] = np.zeros(self.n)
        return value


class BackwardSweep:
    """Computes Sensitivities of an objective for the last forward run of a Simulation.

    Args:
        simulation: The Simulation (its model, integrator, Newton solver).
        leaves: Integral leaves of the objective.
        targets: Sensitivities to compute.
        options: Adjoint linear-solver options.

    Attributes:
        stats: Of the last sweep: wall ``seconds``, the linear solver's counts, Krylov iterations
            per step and ``phase_seconds``: the objective's state partials, the linear solves, the
            pushes into earlier steps (history), the parameter and shape partials, and the rest.
    """

    def __init__(
        self,
        simulation: "Simulation",
        leaves: Sequence["Integral | NumericIntegral"],
        targets: Targets,
        options: AdjointSolverOptions | None = None,
    ) -> None:
        self.sim = simulation
        self.model = simulation.model
        self.targets = targets
        options = options or AdjointSolverOptions()
        self.forms = AdjointForms(
            self.model,
            simulation.integrator.dynamic,
            leaves,
            targets,
            shape_partials=options.shape_partials,
        )
        self.linear = AdjointLinearSolver(simulation.solver, options)
        V = self.model.V
        imap = V.dofmap.index_map
        self.bs = V.dofmap.index_map_bs
        self.owned = imap.size_local * self.bs
        self.bc_dofs = self.model.dirichlet_dofs()
        self._rhs = simulation.solver.create_matrix().createVecRight()
        self._sol = self._rhs.duplicate()
        self.stats: dict = {}
        self._vectors: dict[fem.Form, dolfinx.la.Vector] = {}
        # the step's forms share the packing of their fields (u^i, history, lambda, materials)
        self._gathers = CoefficientGathers()
        self._packers: dict[fem.Form, FormPacker] = {}
        self._phases: dict[str, float] = defaultdict(float)

    @contextmanager
    def _phase(self, name: str) -> Iterator[None]:
        """Adds the wall time of the block to phase ``name`` of :attr:`stats`."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._phases[name] += time.perf_counter() - t0

    # -- assembly helpers ----------------------------------------------------------------
    def _assemble(self, form: fem.Form) -> np.ndarray:
        """Owned entries of an assembled vector form (ghost contributions summed).

        Each form assembles into a vector of its own, kept for the next step: the result is a
        view of it, valid until the same form is assembled again.
        """
        vec = self._vectors.get(form)
        if vec is None:
            vec = self._vectors[form] = fem.create_vector(form.function_spaces[0], form.dtype)
            self._packers[form] = FormPacker(form, self._gathers)
        vec.array[:] = 0.0
        fem.assemble_vector(vec.array, form, coeffs=self._packers[form].pack())
        vec.scatter_reverse(dolfinx.la.InsertMode.add)
        n = vec.index_map.size_local * vec.block_size
        return vec.array[:n]

    def _add(self, target: np.ndarray, form: fem.Form | None) -> None:
        if form is not None:
            target[: self.owned] += self._assemble(form)

    # -- the sweep ----------------------------------------------------------------------------
    def run(self, traj: "Trajectory", leaf_weights: dict) -> Sensitivities:
        """Backward sweep over ``traj`` with chain-rule weights ``leaf_weights[leaf][i]``."""
        self._begin(traj.num_steps, len(traj.u[0]), leaf_weights)
        with self._progress(traj.num_steps) as bar:
            for i in range(traj.num_steps, 0, -1):
                self._step(i, traj)
                bar.update()
        return self._finish((traj.u[0], traj.v[0]))

    def _progress(self, num_steps: int) -> AbstractContextManager[ProgressBar]:
        """The adjoint's progress bar (shown where the simulation shows its own)."""
        return progress_bar(num_steps, self.model.domain.comm, self.sim.progress, "adjoint")

    def run_checkpointed(self, run: "CheckpointedRun", leaf_weights: dict) -> Sensitivities:
        """Backward sweep of a :class:`~diffsolids.adjoint.checkpointing.CheckpointedRun`.

        The run's schedule recomputes the states each step needs; the forward factorisations
        of recomputed steps precondition their adjoint solves and are freed after them. Same
        arithmetic as :meth:`run`: the gradient of the all-in-memory sweep.
        """
        u0, v0 = run.initial_state()
        self._begin(run.N, len(u0), leaf_weights)
        store = self.sim.solver.factor_store
        # without a store the adjoint preconditions with the factors the SNES holds at its start
        # (step N's, as after an all-in-memory forward); recomputed steps factorise elsewhere
        frozen = self.sim.solver.detach_last_factors() if store is None else None

        def step(i: int, view: "StateHistory") -> None:
            if store is not None:  # the factors of steps recomputed since the last step
                self.linear.refresh(store.factors)
            self._step(i, view)
            if store is not None:
                store.discard_after(i)
            bar.update()

        try:
            with self._progress(run.N) as bar:
                run.reverse(step)
        finally:
            if store is not None:
                store.clear()
            if frozen is not None:
                frozen.destroy()
        return self._finish((u0, v0))

    def _begin(self, N: int, n: int, leaf_weights: dict) -> None:
        self._t0 = time.perf_counter()
        self._phases.clear()  # also drops the times of a sweep that raised part-way
        # accumulated adjoints of the states not yet swept (those of step i are complete at i)
        self._ubar = _Adjoints(n)
        self._vbar = _Adjoints(n)
        self._weights = leaf_weights
        self._sens = self._empty_sensitivities(N)
        self.linear.begin()
        self._krylov = []

    def _step(self, i: int, traj: "StateHistory") -> None:
        """Adjoint of step i: reads u^{i-d..i}, v^{i-d..i} of ``traj``."""
        forms = self.forms
        ubar, vbar, sens = self._ubar, self._vbar, self._sens
        step = self.sim.prepare_step(i, traj, Phase.BACKWARD).step  # as the forward set it up
        self._load_state(traj, i)
        active = forms.set_weights(self._weights, i)
        if active:
            with self._phase("objective_state"):
                self._add(ubar[i], forms.objective_u)
                self._add(vbar[i], forms.objective_v)
                self._add(ubar[i - 1], forms.objective_prev)
                if forms.objective_tilde is not None:
                    step.add_predictor_transpose(self._assemble(forms.objective_tilde), ubar, vbar)
        self._numeric_objective(ubar[i], sens)
        # 1. vbar^i is complete: through v^i = (u^i + sum_j alpha_j u^{i-j}) / (beta dt)
        step.add_velocity_transpose(vbar[i], ubar)
        # 2. K_i lambda_i = -ubar^i on free dofs
        with self._phase("linear_solves"):
            self._krylov.append(self._solve(ubar[i], i))
        # 3. push lambda_i (and the objective's own partials) into the inputs of step i
        with self._phase("history"):
            self._history(ubar, vbar, step)
        with self._phase("parameters"):
            self._parameters(sens, active)
        if self.targets.dirichlet:
            ubar[i][: self.owned] += self._assemble(forms.jacobian_action)
            sens.dirichlet[i] = ubar[i]
        ubar.pop(i)
        vbar.pop(i)

    def _finish(self, state0: tuple[np.ndarray, np.ndarray]) -> Sensitivities:
        sens = self._sens
        self._initial_step(state0, self._weights, self._ubar, self._vbar, sens)
        seconds = time.perf_counter() - self._t0
        phases = dict(self._phases)
        phases["other"] = seconds - sum(phases.values())  # loading states, step 0, Dirichlet
        self.stats = {
            "seconds": seconds,
            **self.linear.stats,
            "phase_seconds": phases,
            "krylov_per_step": self._krylov[::-1],
        }
        self._ubar = self._vbar = self._sens = None
        return sens

    def _empty_sensitivities(self, N: int) -> Sensitivities:
        sens = Sensitivities()
        if self.targets.shape:
            S = self.model.shape_space
            sens.shape = np.zeros(S.dofmap.index_map.size_local * S.dofmap.index_map_bs)
        for name in self.targets.coefficients:
            V = self.model.coefficients[name].function_space
            sens.coefficients[name] = np.zeros(
                V.dofmap.index_map.size_local * V.dofmap.index_map_bs
            )
        sens.dirichlet = [None] * (N + 1)
        return sens

    def _load_state(self, traj: "StateHistory", i: int) -> None:
        f = self.model.fields
        f.u.x.array[:] = traj.u[i]
        f.v.x.array[:] = traj.v[i]

    def _solve(self, ubar_i: np.ndarray, step: int) -> int:
        rhs, sol = self._rhs, self._sol
        rhs.array_w[:] = -ubar_i[: self.owned]
        owned_bc = self.bc_dofs[self.bc_dofs < self.owned]
        rhs.array_w[owned_bc] = 0.0
        its = self.linear.solve(rhs, sol, step)
        lam = self.forms.lam
        lam.x.petsc_vec.array_w[:] = sol.array_r
        lam.x.scatter_forward()
        return its

    def _history(self, ubar: _Adjoints, vbar: _Adjoints, step: TimeStep) -> None:
        """lambda_i . G_i pushed into u^{i-j}, v^{i-j} (through u_tilde) and u^{i-1}."""
        forms = self.forms
        if forms.history_tilde is not None:
            step.add_predictor_transpose(self._assemble(forms.history_tilde), ubar, vbar)
        self._add(ubar[step.index - 1], forms.history_prev)
        self._numeric_history(ubar, step.index)

    def _numeric_history(self, ubar: _Adjoints, i: int) -> None:
        lam = self.forms.lam.x.array
        for term in self.model.numeric_terms:
            for j, g in term.adjoint_history(self.model.fields.u, lam).items():
                ubar[i - j][: self.owned] += g[: self.owned]

    def _partials(self, sens: Sensitivities, part: int) -> None:
        """Coefficient and shape partials of lambda . G_i (part 0) or of J_i (part 1)."""
        for name, forms in self.forms.coefficients.items():
            if forms[part] is not None:
                sens.coefficients[name] += self._assemble(forms[part])
        if self.forms.shape is not None and self.forms.shape[part] is not None:
            sens.shape += self._assemble(self.forms.shape[part])

    def _parameters(self, sens: Sensitivities, active: bool) -> None:
        """Coefficient and shape partials of L_i + J_i (J_i only when its weights are nonzero)."""
        self._partials(sens, 0)
        if active:
            self._partials(sens, 1)
        if self.forms.shape is not None and self.model.numeric_terms:
            lam = self.forms.lam.x.array
            # collective decision: the numeric terms' kernels gather the surface on every rank
            # (a rank whose dofs are all prescribed holds lambda = 0 alone)
            comm = self.model.domain.comm
            if collective_comm(comm).allreduce(bool(np.any(lam)), op=MPI.LOR):
                for term in self.model.numeric_terms:
                    g = term.adjoint_shape(self.model.fields.u, lam)
                    if g is not None:
                        sens.shape += g[: len(sens.shape)]
        lam = self.forms.lam.x.array
        for name in self.targets.contact:
            for term in self.model.numeric_terms:
                if name in term.parameter_names:
                    contrib = term.adjoint_parameter(name, self.model.fields.u, lam)
                    sens.contact[name] = sens.contact.get(name, 0.0) + contrib

    def _numeric_objective(self, ubar_i: np.ndarray, sens: Sensitivities) -> None:
        """c_i dJ/du^i and c_i dJ/dX of the numeric objective leaves (weights set for step i)."""
        for leaf, weight in self.forms.numeric.items():
            if weight == 0.0:
                continue
            ubar_i[: self.owned] += weight * leaf.state_gradient(self.model)[: self.owned]
            if sens.shape is not None:
                g = leaf.shape_gradient(self.model)
                if g is not None:
                    sens.shape += weight * g[: len(sens.shape)]

    def _initial_step(
        self,
        state0: tuple[np.ndarray, np.ndarray],
        leaf_weights: dict,
        ubar: _Adjoints,
        vbar: _Adjoints,
        sens: Sensitivities,
    ) -> None:
        """Step 0: objective partials at u^0, v^0 (lambda = 0) and the initial sensitivities."""
        forms = self.forms
        self.model.update_time(0.0)
        f = self.model.fields
        f.u.x.array[:], f.v.x.array[:] = state0
        forms.lam.x.array[:] = 0.0
        if forms.set_weights(leaf_weights, 0):
            self._add(ubar[0], forms.objective_u)
            self._add(vbar[0], forms.objective_v)
            self._partials(sens, 1)
        self._numeric_objective(ubar[0], sens)
        sens.u0, sens.v0 = ubar[0], vbar[0]
        if self.targets.dirichlet:
            sens.dirichlet[0] = ubar[0]
