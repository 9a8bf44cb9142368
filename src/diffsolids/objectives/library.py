"""Ready-made objectives of the paper (sec. 9.2) as Series and Objectives.

Per-step quantities are :class:`~diffsolids.objectives.Series` (one value per step 0..N);
reduce them with time weights, e.g. ``time_integral(stress_lp_norm(model, 4), "uniform")`` or
``final_value(...)`` for a static solve. Quantities that are not per step (volume penalties)
are scalar :class:`~diffsolids.objectives.Objective` s. All of them combine with ``+ - * /``
and powers; the chain rule runs through the expression tree.

Targets, weights and other data may be given as
* a number or vector (a constant),
* a callable ``f(x)`` of rest positions (shape (dim, n) -> values), interpolated once on the
  rest mesh: the data then moves with the material points when the shape changes (paper eq.
  31, x^trg defined on the reference domain),
* a UFL expression (e.g. of ``model.fields.t`` for data that change in time) or a Function.
"""

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, override

import numpy as np
import numpy.typing as npt
import ufl
from dolfinx import default_scalar_type, fem
from ufl.core.expr import Expr

from diffsolids import forms
from diffsolids.errors import ParameterError
from diffsolids.model.terms import ElasticEnergy
from diffsolids.objectives.functional import (
    ConstantSeries,
    DataSeries,
    Integral,
    Objective,
    ObjectiveError,
    Series,
    final_value,
)

if TYPE_CHECKING:
    from diffsolids.model import Model, StepFields

__all__ = [
    "StepValues",
    "boundary_graph_fit",
    "center_of_mass",
    "center_of_mass_trajectory",
    "height_objective",
    "stress_bound_penalty",
    "stress_lp_norm",
    "target_displacement",
    "target_positions",
    "volume_penalty",
]

_STRESSES = ("cauchy", "piola", "von_mises")
Tags = int | str | Sequence[int | str] | None
# a number or vector, a callable of rest positions, a UFL expression or Function
Data = npt.ArrayLike | Callable | Expr


class StepValues(DataSeries):
    """Given values s_0..s_N (data, e.g. a target per step); no derivatives.

    NaN marks a state without data (e.g. state 0 of per-step values taken with "uniform"
    weights): an objective that gives such a state a nonzero weight raises an ObjectiveError
    naming it; the others never read it.

    Args:
        values: N + 1 numbers (checked against the run's steps when evaluated).
        name: Name used in error messages.

    Raises:
        ObjectiveError: Not 1D, or an infinite entry (naming the states).
    """

    def __init__(self, values: npt.ArrayLike, name: str = "step values") -> None:
        self.array = np.asarray(values, dtype=float)
        if self.array.ndim != 1:
            raise ObjectiveError(
                f"{name}: expected a finite 1D array of per-step values (one per state 0..N), "
                f"got shape {self.array.shape}"
            )
        bad = np.flatnonzero(np.isinf(self.array))
        if bad.size:
            shown = ", ".join(f"state {i}: {self.array[i]}" for i in bad[:5])
            raise ObjectiveError(
                f"{name}: per-step values must be finite (NaN: no data), {bad.size} are "
                f"infinite ({shown})"
            )
        self.name = name

    @override
    def values(self, table: dict) -> np.ndarray:
        n = self.num_states(table, len(self.array))
        if len(self.array) != n:
            raise ObjectiveError(
                f"{self.name} has {len(self.array)} values but the run has {n} states (0..{n - 1})"
            )
        return self.array


# -- helpers ---------------------------------------------------------------------------------
def _tags(ids: Tags) -> tuple:
    if ids is None:
        return ()
    if isinstance(ids, int | str | np.integer):
        return (ids,)
    return tuple(ids)


def _volume_measure(model: "Model", f: "StepFields", bodies: Tags) -> ufl.Measure:
    ids = tuple(model.domain.body_id(b) for b in _tags(bodies))
    return f.dx(ids) if ids else f.dx


def _facet_measure(model: "Model", f: "StepFields", facets: Tags) -> ufl.Measure:
    ids = tuple(model.domain.facet_id(t) for t in _tags(facets))
    if not ids:
        raise ParameterError("a boundary objective needs at least one facet tag")
    return f.ds(ids)


def _data(model: "Model", value: Data, shape: tuple, what: str) -> Expr:
    """A number/vector (Constant), callable of rest positions (interpolated), or UFL as is."""
    mesh = model.domain.mesh
    if isinstance(value, ufl.core.expr.Expr):
        if value.ufl_shape != shape:
            raise ParameterError(f"{what} has shape {value.ufl_shape}, expected {shape}")
        return value
    if callable(value):
        element = ("Lagrange", model.degree, shape) if shape else ("Lagrange", model.degree)
        fn = fem.Function(fem.functionspace(mesh, element), name=what)
        fn.interpolate(value)
        if not np.all(np.isfinite(fn.x.array)):
            raise ParameterError(f"{what} has non-finite values")
        return fn
    arr = np.asarray(value, dtype=default_scalar_type)
    if arr.shape != shape and not (arr.ndim == 0 and shape):
        raise ParameterError(f"{what} has shape {arr.shape}, expected {shape}")
    if not np.all(np.isfinite(arr)):
        raise ParameterError(f"{what} = {arr} is not finite")
    return fem.Constant(mesh, np.broadcast_to(arr, shape).copy() if shape else arr)


def _stress_tensor(
    kind: str, law: str, u: Expr, lmbda: Expr | float, mu: Expr | float, plane_strain: bool
) -> Expr:
    if kind == "piola":
        return forms.first_piola_kirchhoff(law, u, lmbda, mu)
    sigma = forms.cauchy_stress(law, u, lmbda, mu)
    if kind == "cauchy":
        return sigma
    # von Mises of the 3x3 stress: plane strain (2D) completes it with its sigma_zz
    sigma_zz = forms.plane_strain_normal_stress(law, u, lmbda, mu) if plane_strain else 0.0
    return forms.von_mises_tensor(sigma, sigma_zz)


def _stress_integral(
    model: "Model", integrand: Callable, kind: str, bodies: Tags, name: str
) -> Integral:
    """Integral of integrand(stress) over the bodies of every elastic law of the model."""
    if kind not in _STRESSES:
        raise ParameterError(f"unknown stress {kind!r}; choose from {_STRESSES}")
    wanted = {model.domain.body_id(b) for b in _tags(bodies)} or set(model.domain.body_ids)
    laws = [t for t in model.terms if isinstance(t, ElasticEnergy)]
    plane_strain = model.dim == 2 and not model.plane_stress

    def form(f: "StepFields") -> ufl.Form:
        total = 0
        for term in laws:
            ids = wanted if term.bodies is None else wanted & set(term.bodies)
            if not ids:
                continue
            lmbda, mu = term.lame(f)
            sigma = _stress_tensor(kind, term.law, f.u, lmbda, mu, plane_strain)
            whole = term.bodies is None and ids == set(model.domain.body_ids)
            dx = f.dx if whole else f.dx(tuple(sorted(ids)))
            total = total + integrand(sigma) * dx
        return total

    return Integral(form, name)


# -- stress ----------------------------------------------------------------------------------
def stress_lp_norm(
    model: "Model", p: float = 2.0, stress: str = "cauchy", bodies: Tags = None
) -> Series:
    """L_p norm of stress per step, (int ||sigma||_F^p dx)^(1/p) (paper eq. 30).

    Large p approximates the maximal stress. The norm is not differentiable at a state with
    zero stress everywhere (e.g. an unloaded u^0): give such steps zero time weight.

    Args:
        model: The Model (its constitutive laws give sigma(grad u)).
        p: Exponent, p >= 2 (the derivative of ||sigma||^p is singular at zero stress below).
        stress: "cauchy" (the small-strain stress for linear elasticity), "piola" (first
            Piola-Kirchhoff) or "von_mises" (the norm is then the von Mises stress).
        bodies: Restrict to these bodies (default: all).
    """
    p = float(p)
    if not (np.isfinite(p) and p >= 2.0):
        raise ParameterError(f"stress_lp_norm needs p >= 2, got {p}")
    integral = _stress_integral(
        model, lambda s: forms.stress_norm_power(s, p), stress, bodies, f"|{stress}|^{p:g}"
    )
    return integral ** (1.0 / p)


def stress_bound_penalty(
    model: "Model", bound: float, stress: str = "cauchy", bodies: Tags = None
) -> Series:
    """Soft upper bound on stress per step, int phi(||sigma||_F - s_t) dx (paper eq. 36).

    Args:
        model: The Model.
        bound: Stress magnitude s_t > 0 above which the quadratic penalty phi acts.
        stress: As in :func:`stress_lp_norm`.
        bodies: Restrict to these bodies (default: all).
    """
    if not (np.isfinite(bound) and bound > 0):
        raise ParameterError(f"stress bound must be positive and finite, got {bound}")
    s_t = fem.Constant(model.domain.mesh, default_scalar_type(bound))
    return _stress_integral(
        model, lambda s: forms.stress_penalty(s, s_t), stress, bodies, f"stress > {bound:g}"
    )


# -- deformation targets -----------------------------------------------------------------
def _target_integral(
    model: "Model",
    target: Data,
    weight: Data,
    facets: Tags,
    bodies: Tags,
    positions: bool,
    name: str,
) -> Integral:
    dim = model.dim
    trg = _data(model, target, (dim,), f"{name} target")
    w = _data(model, weight, (), f"{name} weight")
    if facets is not None and bodies is not None:
        raise ParameterError("give facets (boundary target) or bodies (volume target), not both")

    def form(f: "StepFields") -> ufl.Form:
        x = forms.deformed_position(f.X, f.u) if positions else f.u
        measure = (
            _facet_measure(model, f, facets)
            if facets is not None
            else _volume_measure(model, f, bodies)
        )
        return forms.weighted_squared_distance(x, trg, w) * measure

    # resolve the tags now: unknown tags fail at construction
    form(model.fields)
    return Integral(form, name)


def target_displacement(
    model: "Model", target: Data, weight: Data = 1.0, facets: Tags = None, bodies: Tags = None
) -> Series:
    """Weighted squared distance of u from a target displacement, per step (paper eq. 31).

    int w ||u - u^trg||^2 over the bodies (volume) or over tagged facets (boundary).

    Args:
        model: The Model.
        target: Target displacement (vector, callable of rest positions, UFL, Function).
        weight: Weight w (number, callable of rest positions, UFL, Function).
        facets: Facet tag(s): integrate over these boundary parts instead of the volume.
        bodies: Restrict the volume integral to these bodies.

    Raises:
        TagError: Unknown facet tags or bodies.
    """
    return _target_integral(model, target, weight, facets, bodies, False, "target displacement")


def target_positions(
    model: "Model", target: Data, weight: Data = 1.0, facets: Tags = None, bodies: Tags = None
) -> Series:
    """Weighted squared distance of the deformed positions X + u from targets (paper eq. 31).

    Arguments as in :func:`target_displacement`; ``target`` is a position x^trg (e.g. a
    callable of the rest positions mapping each material point to where it should go).
    """
    return _target_integral(model, target, weight, facets, bodies, True, "target positions")


def boundary_graph_fit(model: "Model", facets: Tags, function: Callable, axis: int = -1) -> Series:
    """Misfit of a deformed boundary part to the graph of a function, per step.

    int_{facets} (x^d_axis - f(other coordinates of x^d))^2 ds with x^d = X + u, e.g.
    ``boundary_graph_fit(model, "top", lambda x: 0.7 * ufl.sin(x))`` fits y = 0.7 sin x in 2D.

    Args:
        model: The Model.
        facets: Facet tag(s) of the boundary part.
        function: f of the remaining deformed coordinates (UFL scalars -> UFL scalar).
        axis: Coordinate that should equal f (default: the last one).
    """
    if not -model.dim <= axis < model.dim:
        raise ParameterError(f"axis {axis} out of range for dimension {model.dim}")

    def form(f: "StepFields") -> ufl.Form:
        x = forms.deformed_position(f.X, f.u)
        return forms.graph_misfit(x, function, axis) * _facet_measure(model, f, facets)

    form(model.fields)
    return Integral(form, "graph fit")


# -- centre of mass ----------------------------------------------------------------------------
def _mass_and_moments(model: "Model", bodies: Tags) -> tuple[Integral, list[Integral]]:
    """J^D = int rho dx and J^P_k = int rho x^d_k dx with x^d = X + u (paper eq. 32)."""
    rho = model.coefficients["density"]
    _volume_measure(model, model.fields, bodies)  # unknown bodies fail here
    mass = Integral(lambda f: rho * _volume_measure(model, f, bodies), "mass")

    def moment(k: int) -> Integral:
        def form(f: "StepFields") -> ufl.Form:
            x = forms.deformed_position(f.X, f.u)
            return rho * x[k] * _volume_measure(model, f, bodies)

        return Integral(form, f"moment[{k}]")

    return mass, [moment(k) for k in range(model.dim)]


def center_of_mass(model: "Model", bodies: Tags = None) -> list[Series]:
    """Components of the deformed centre of mass per step, J^P_k / J^D (paper eq. 32).

    Series of an objective, and the numbers along any trajectory: ``series_values(sim,
    center_of_mass(model, "B"), trajectory)`` is the (N + 1, dim) path of body B's centre.

    Args:
        model: The Model (its density).
        bodies: Restrict to these bodies (default: all).
    """
    mass, moments = _mass_and_moments(model, bodies)
    return [m / mass for m in moments]


def center_of_mass_trajectory(
    model: "Model", target: npt.ArrayLike | Callable, bodies: Tags = None
) -> Series:
    """Squared distance of the centre of mass from a target, per step (paper eq. 32).

    ||c^i - x^ctr(t_i)||^2 with c the deformed centre of mass.

    Args:
        model: The Model.
        target: A vector (fixed target), an array of shape (N + 1, dim) (one target per state
            0..N), or a callable ``t -> UFL vector`` of the UFL time of the step
            (``model.fields.t``), e.g. ``lambda t: ufl.as_vector([0.5 * t, 1.0])``.
        bodies: Restrict to these bodies (default: all).
    """
    dim = model.dim
    mass, moments = _mass_and_moments(model, bodies)
    com = [m / mass for m in moments]
    if callable(target) and not isinstance(target, ufl.core.expr.Expr):
        trg = _data(model, target(model.fields.t), (dim,), "centre-of-mass target")
        rho = model.coefficients["density"]

        def weighted_target(k: int) -> Series:
            return Integral(lambda f: rho * trg[k] * _volume_measure(model, f, bodies), "target")

        parts = [weighted_target(k) / mass for k in range(dim)]
    else:
        arr = np.asarray(target, dtype=float)
        if arr.shape == (dim,):
            parts = [ConstantSeries(float(a)) for a in arr]
        elif arr.ndim == 2 and arr.shape[1] == dim:
            parts = [StepValues(arr[:, k], "centre-of-mass target") for k in range(dim)]
        else:
            raise ParameterError(
                f"centre-of-mass target has shape {arr.shape}; expected ({dim},) or (N + 1, {dim})"
            )
    terms = [(c - t) ** 2 for c, t in zip(com, parts, strict=True)]
    return sum(terms[1:], terms[0])


def height_objective(model: "Model", axis: int | None = None, bodies: Tags = None) -> Series:
    """Negative height of the centre of mass per step, -J^P_z / J^D (paper eqs. 33-34).

    Minimising it maximises the height.

    Args:
        model: The Model.
        axis: Vertical axis (default: the last one).
        bodies: Restrict to these bodies (default: all).
    """
    axis = model.dim - 1 if axis is None else axis
    if not 0 <= axis < model.dim:
        raise ParameterError(f"axis {axis} out of range for dimension {model.dim}")
    return -center_of_mass(model, bodies)[axis]


# -- volume ----------------------------------------------------------------------------------
def volume_penalty(
    model: "Model",
    target: float,
    bound: str = "upper",
    bodies: Tags = None,
    deformed: bool = False,
) -> Objective:
    """Soft volume constraint phi(V - V_t) (upper) or phi(V_t - V) (lower) (paper eq. 35).

    phi(z) = z^2 for z > 0, else 0. V is the rest volume int dx (changes with the shape), or
    with ``deformed`` the deformed volume int det F dx at the final step.

    Args:
        model: The Model.
        target: Target volume V_t.
        bound: "upper" (penalise V > V_t) or "lower" (penalise V < V_t).
        bodies: Restrict to these bodies (default: all).
        deformed: Use the deformed volume of the last state.
    """
    if bound not in ("upper", "lower"):
        raise ParameterError(f"volume bound must be 'upper' or 'lower', got {bound!r}")
    if not np.isfinite(target):
        raise ParameterError(f"target volume {target} is not finite")
    one = fem.Constant(model.domain.mesh, default_scalar_type(1.0))

    def form(f: "StepFields") -> ufl.Form:
        density = ufl.det(forms.deformation_gradient(f.u)) if deformed else one
        return density * _volume_measure(model, f, bodies)

    form(model.fields)
    volume = final_value(Integral(form, "deformed volume" if deformed else "volume"))
    excess = volume - float(target) if bound == "upper" else float(target) - volume
    return excess.apply(
        lambda z: np.maximum(z, 0.0) ** 2, lambda z: 2.0 * np.maximum(z, 0.0), "penalty"
    )
