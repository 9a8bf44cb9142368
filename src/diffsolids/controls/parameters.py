"""Controls of model coefficients: material fields, density, damping, load vectors."""

import functools
from collections.abc import Sequence
from typing import TYPE_CHECKING, override

import numpy as np
import numpy.typing as npt
from mpi4py import MPI

from diffsolids.adjoint.sensitivities import Sensitivities, Targets
from diffsolids.controls.base import Control, ControlError
from diffsolids.controls.maps import ParameterMap, as_map
from diffsolids.controls.transfer import interpolate_nonmatching
from diffsolids.mesh.ordering import CanonicalLayout
from diffsolids.model import undo_on_refusal
from diffsolids.parallel import collective_comm

if TYPE_CHECKING:
    from diffsolids.model import Model
    from diffsolids.simulation import Simulation

__all__ = ["ParameterControl"]

_MODES = ("field", "bodies", "uniform", "scale")


class ParameterControl(Control):
    """A coefficient of the model as parameters.

    Args:
        model: The Model owning the coefficient.
        name: Coefficient name in ``model.coefficients`` ("E", "nu", "lmbda", "mu", "density",
            "damping_psi", "damping_phi", "gravity", "traction_<tag>", ...).
        mode: "field" (every dof, canonical order), "bodies" (one value per listed body and
            component, DG0 coefficients), "uniform" (one value per component everywhere) or
            "scale" (one factor multiplying the current field, e.g. a load magnitude).
        bodies: Bodies of mode "bodies" (default: all).
        log: Parametrise by the logarithm (value = exp(q)), for positive parameters; the same
            as ``map=Log()``.
        lower: Lower bound of q (scalar or array), intersected with the map's own bounds.
        upper: Upper bound of q.
        map: Change of variables value = map(q) (:mod:`diffsolids.controls.maps`: Log, Affine,
            Power, Simp, Compose, or a user ParameterMap). In mode "scale" it maps the factor.
    """

    def __init__(
        self,
        model: "Model",
        name: str,
        mode: str = "field",
        bodies: Sequence[int | str] | None = None,
        log: bool = False,
        lower: npt.ArrayLike = -np.inf,
        upper: npt.ArrayLike = np.inf,
        map: ParameterMap | None = None,
    ) -> None:
        if name not in model.coefficients:
            hint = ""
            other = {("E", "nu"): ("lmbda", "mu"), ("lmbda", "mu"): ("E", "nu")}
            if name in other.get(model.parametrisation, ()):
                given = ", ".join(f"{p}=..." for p in other[model.parametrisation])
                hint = (
                    f" (its materials give {model.parametrisation}: to control {name!r}, give "
                    f"them as {given}, e.g. ds.NeoHookean({given}))"
                )
            raise ControlError(
                f"the model has no coefficient {name!r}; it has {sorted(model.coefficients)}" + hint
            )
        if mode not in _MODES:
            raise ControlError(f"unknown parameter mode {mode!r}; choose from {_MODES}")
        self.model, self.coefficient_name, self.mode = model, name, mode
        self.map = as_map(map, log)
        self.name = f"{name}[{mode}{'' if map is None and not log else ', ' + self.map.name}]"
        self.function = model.coefficients[name]
        V = self.function.function_space
        self.bs = V.dofmap.index_map_bs
        self.owned = V.dofmap.index_map.size_local
        self.comm = model.domain.comm
        self._lower, self._upper = lower, upper
        self.base = self.function.x.array.copy()
        self._scale = 1.0
        if mode == "field":
            self.layout = CanonicalLayout(V)
        elif mode == "bodies":
            if V.element.basix_element.degree != 0:
                raise ControlError(f"per-body control of {name!r} needs a DG0 coefficient")
            ids = model.domain.body_ids if bodies is None else bodies
            self.bodies = [model.domain.body_id(b) for b in ids]
            self._cells = [model.domain.cells_of(b) for b in self.bodies]
        try:
            self.map.inverse(self._physical_values())
        except ControlError as err:
            raise ControlError(f"coefficient {name!r} cannot be parametrised: {err}") from None
        self._check_bounds()

    def _check_bounds(self) -> None:
        """Refuse bounds of the wrong size, NaN, or a lower bound above the upper one."""
        try:
            lower, upper = self.bounds()
        except ValueError:
            shapes = f"{np.shape(self._lower)} and {np.shape(self._upper)}"
            raise ControlError(
                f"control {self.name}: bounds of shapes {shapes} for {self.size} parameters"
            ) from None
        if np.any(np.isnan(lower)) or np.any(np.isnan(upper)):
            raise ControlError(f"control {self.name}: bounds contain NaN")
        crossed = np.flatnonzero(lower > upper)
        if crossed.size:
            i = int(crossed[0])
            raise ControlError(
                f"control {self.name}: lower bound above the upper bound for {crossed.size} "
                f"parameters (parameter {i}: lower {lower[i]:g} > upper {upper[i]:g}, the map "
                f"{self.map.name} allows [{self.map.bounds()[0]:g}, {self.map.bounds()[1]:g}])"
            )

    @override
    def check(self, simulation: "Simulation") -> None:
        if simulation.model is not self.model:
            raise ControlError(f"control {self.name} belongs to a different model")

    @override
    def footprint(self) -> set[tuple]:
        quantity = f"coefficient {self.coefficient_name!r}"
        if self.mode == "bodies":
            return {(quantity, f"body {b}") for b in self.bodies}
        return {(quantity, None)}

    @override
    @property
    def size(self) -> int:
        if self.mode == "field":
            return self.layout.size
        if self.mode == "bodies":
            return len(self.bodies) * self.bs
        return self.bs if self.mode == "uniform" else 1

    def _physical_values(self) -> np.ndarray:
        arr = self.function.x.array.reshape(-1, self.bs)
        if self.mode == "field":
            return self.layout.gather(self.function.x.array)
        if self.mode == "bodies":
            vals = np.zeros((len(self.bodies), self.bs))
            for k, cells in enumerate(self._cells):
                owned = cells[cells < self.owned]
                local = arr[owned].mean(axis=0) if len(owned) else np.full(self.bs, -np.inf)
                vals[k] = collective_comm(self.comm).allreduce(local, op=MPI.MAX)
            return vals.ravel()
        if self.mode == "uniform":
            n = collective_comm(self.comm).allreduce(len(arr[: self.owned]), op=MPI.SUM)
            return (
                collective_comm(self.comm).allreduce(arr[: self.owned].sum(axis=0), op=MPI.SUM) / n
            )
        return np.array([self._scale])

    @override
    def value(self) -> np.ndarray:
        return self.map.inverse(self._physical_values())

    @override
    def assign(self, q: np.ndarray) -> None:
        p = self.map.forward(np.asarray(q, dtype=float))
        arr = self.function.x.array
        with self.model.parameter_update():  # a refused value leaves the fields as they were
            if self.mode == "field":
                self.layout.scatter(p, self.function)
            elif self.mode == "bodies":
                view = arr.reshape(-1, self.bs)
                for k, cells in enumerate(self._cells):
                    view[cells] = p[k * self.bs : (k + 1) * self.bs]
            elif self.mode == "uniform":
                arr.reshape(-1, self.bs)[:] = p
            else:
                arr[:] = self.base * p[0]
                undo_on_refusal(functools.partial(setattr, self, "_scale", self._scale))
                self._scale = float(p[0])

    @override
    def targets(self) -> Targets:
        return Targets(coefficients=frozenset({self.coefficient_name}))

    @override
    def pullback(self, sens: Sensitivities) -> np.ndarray:
        g_local = sens.coefficients[self.coefficient_name][: self.owned * self.bs]
        if self.mode == "field":
            g = self.layout.gather(g_local)
        elif self.mode == "bodies":
            view = g_local.reshape(-1, self.bs)
            local = np.array([view[c[c < self.owned]].sum(axis=0) for c in self._cells])
            g = collective_comm(self.comm).allreduce(local, op=MPI.SUM).ravel()
        elif self.mode == "uniform":
            g = collective_comm(self.comm).allreduce(
                g_local.reshape(-1, self.bs).sum(axis=0), op=MPI.SUM
            )
        else:
            g = np.array(
                [
                    collective_comm(self.comm).allreduce(
                        float(g_local @ self.base[: len(g_local)]), op=MPI.SUM
                    )
                ]
            )
        return self.map.pullback(self.value(), g)

    @override
    def transfer(self, old: Control, block: np.ndarray) -> np.ndarray:
        if self.mode != "field" or not isinstance(old, ParameterControl):
            return super().transfer(old, block)
        old.assign(block)
        interpolate_nonmatching(old.function, self.function)
        return self.value()

    @override
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        low, high = self.map.bounds()
        return (
            np.maximum(np.broadcast_to(self._lower, self.size).astype(float), low),
            np.minimum(np.broadcast_to(self._upper, self.size).astype(float), high),
        )
