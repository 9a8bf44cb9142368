"""Explicit (energy-momentum) shape partials against UFL's coordinate derivative.

The built-in terms give lambda . dG/dX explicitly (``Term.shape_partial``,
``forms.shape_partials``) and the adjoint uses them; UFL's coordinate derivative stays the
reference. Here every built-in law, damping, inertia, body force and traction, and the built-in
objective integrals, are assembled both ways in 2D and 3D with P1 and P2 displacements at a
random state and adjoint (relative difference <= 1e-12), the fall-backs to UFL are checked, and
a damped dynamic shape gradient is compared with the UFL-path gradient and central differences.
"""

import functools

import numpy as np
import pytest
import ufl
from dolfinx import fem
from dolfinx.la import InsertMode
from mpi4py import MPI

import diffsolids as ds
from diffsolids import forms
from diffsolids.adjoint import AdjointSolverOptions
from diffsolids.adjoint.forms import (
    objective_shape_partial,
    residual_shape_partial,
)
from diffsolids.controls import ShapeControl
from diffsolids.errors import ParameterError
from diffsolids.mesh import create_box, create_rectangle
from diffsolids.model import BodyForce, ElasticEnergy, EnergyTerm
from diffsolids.objectives import (
    Integral,
    stress_lp_norm,
    target_displacement,
    target_positions,
    time_integral,
)
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.solvers.forms import compile_form
from diffsolids.verification import finite_difference_check

RTOL = 1e-12
LAWS = ("linear", "st_venant_kirchhoff", "neo_hookean")


def _domain(dim: int):
    facets = {1: lambda x: np.isclose(x[0], 0.0), 2: lambda x: np.isclose(x[0], 1.0)}
    bodies = {2: lambda x: x[0] > 0.5}
    if dim == 2:
        return create_rectangle(
            MPI.COMM_WORLD, [[0, 0], [1, 0.5]], [4, 2], facets=facets, bodies=bodies
        )
    return create_box(
        MPI.COMM_WORLD, [[0, 0, 0], [1, 0.5, 0.5]], [2, 2, 1], facets=facets, bodies=bodies
    )


@functools.cache
def _model(dim: int, degree: int, law: str, variant: str = "") -> ds.Model:
    """A damped two-body model with gravity and a traction, at a random state.

    ``variant``: "cg1" (E a CG1 field), "bodies" (two laws: elastic terms on body subsets),
    "plane_stress".
    """
    domain = _domain(dim)
    damping = {"damping_psi": 3.0, "damping_phi": 2.0}
    if variant == "bodies":
        other = "neo_hookean" if law != "neo_hookean" else "linear"
        materials = {
            1: ds.Material(law, E=1e3, nu=0.3, density=2.0, **damping),
            2: ds.Material(other, E=2e3, nu=0.25, density=3.0, **damping),
        }
    else:
        materials = ds.Material(law, E=1e3, nu=0.3, density=2.0, **damping)
    fields = None
    if variant == "cg1":
        E = fem.Function(fem.functionspace(domain.mesh, ("Lagrange", 1)), name="E")
        E.interpolate(lambda x: 1e3 * (1.0 + 0.5 * x[0] + 0.3 * x[1]))
        fields = {"E": E}
    model = ds.Model(
        domain, materials, degree=degree, plane_stress=variant == "plane_stress", fields=fields
    )
    model.add_gravity(9.81)
    model.add_traction(2, np.arange(1.0, dim + 1.0))
    f = model.fields
    rng = np.random.default_rng(dim + 10 * degree)
    for fn in (f.u, f.u_prev, f.u_tilde, f.v):
        fn.x.array[:] = 0.01 * rng.standard_normal(fn.x.array.size)
    f.dt.value, f.beta_dt.value = 0.1, 0.07
    return model


def _adjoint(model: ds.Model) -> fem.Function:
    lam = fem.Function(model.V, name="adjoint")
    lam.x.array[:] = np.random.default_rng(7).standard_normal(lam.x.array.size)
    return lam


def _assemble(form: ufl.Form) -> np.ndarray:
    vec = fem.assemble_vector(compile_form(form))
    vec.scatter_reverse(InsertMode.add)
    return vec.array[: vec.index_map.size_local * vec.block_size].copy()


def _relative_difference(a: np.ndarray, b: np.ndarray) -> float:
    comm = MPI.COMM_WORLD
    diff = np.sqrt(comm.allreduce(float(np.sum((a - b) ** 2)), op=MPI.SUM))
    norm = np.sqrt(comm.allreduce(float(np.sum(b**2)), op=MPI.SUM))
    assert norm > 0, "the reference shape partial is zero: nothing compared"
    return diff / norm


def _coordinate_derivative(model: ds.Model, form: ufl.Form, lam) -> ufl.Form:
    theta = ufl.TestFunction(model.shape_space)
    return ufl.derivative(ufl.derivative(form, model.fields.u, lam), model.fields.X, theta)


CASES = [(dim, degree, law) for dim in (2, 3) for degree in (1, 2) for law in LAWS]


@pytest.mark.parametrize(("dim", "degree", "law"), CASES, ids=lambda v: str(v))
def test_terms_match_coordinate_derivative(dim, degree, law):
    """Every built-in term of a BDF step: explicit form == UFL coordinate derivative."""
    model = _model(dim, degree, law)
    f, lam = model.fields, _adjoint(model)
    theta = ufl.TestFunction(model.shape_space)
    names = []
    for term in model.active_terms(dynamic=True):
        explicit = term.shape_partial(f, lam, theta)
        assert explicit is not None, f"{term.name} has no explicit shape partial"
        reference = _coordinate_derivative(model, term.energy(f), lam)
        error = _relative_difference(_assemble(explicit), _assemble(reference))
        assert error <= RTOL, f"{term.name}: relative difference {error:.2e}"
        names.append(term.name)
    assert names == ["inertia", f"elastic[{law}]", "damping", "gravity", "traction_2"]


@pytest.mark.parametrize("variant", ["cg1", "bodies", "plane_stress"])
@pytest.mark.parametrize(("dim", "degree"), [(2, 1), (2, 2), (3, 1), (3, 2)])
def test_model_partial_matches_coordinate_derivative(dim, degree, variant):
    """The adjoint's whole step partial (auto) == UFL's (a CG1 E field, laws per body, plane
    stress); static steps too."""
    if variant == "plane_stress" and dim == 3:
        pytest.skip("plane stress is 2D")
    model = _model(dim, degree, "neo_hookean", variant)
    lam = _adjoint(model)
    theta = ufl.TestFunction(model.shape_space)
    for dynamic in (True, False):
        explicit = residual_shape_partial(model, dynamic, lam, theta, "auto")
        assert "CoordinateDerivative" not in repr(explicit)
        reference = residual_shape_partial(model, dynamic, lam, theta, "ufl")
        assert "CoordinateDerivative" in repr(reference)
        error = _relative_difference(_assemble(explicit), _assemble(reference))
        assert error <= RTOL, f"dynamic={dynamic}: relative difference {error:.2e}"


def _objectives(model: ds.Model) -> dict:
    dim = model.dim
    X = model.fields.X
    return {
        "stress-cauchy": stress_lp_norm(model, 4),
        "stress-piola": stress_lp_norm(model, 3, stress="piola"),
        "stress-von-mises": stress_lp_norm(model, 2, stress="von_mises"),
        "target-facets": target_displacement(model, 0.01 * np.ones(dim), facets=2),
        "target-volume": target_displacement(model, 0.01 * np.ones(dim)),
        "positions": target_positions(model, lambda x: 1.1 * x[:dim]),
        # reads X itself: the partial dj/dX . theta is added (cell and facet integrals)
        "reads-X": Integral(lambda f: ufl.dot(X, X) * ufl.dot(f.u, f.v) * f.dx, "x-weighted"),
        "reads-X-facets": Integral(lambda f: X[0] * ufl.dot(f.u, f.u) * f.ds(2), "x-facet"),
        "velocity-gradient": Integral(
            lambda f: ufl.inner(ufl.grad(f.v), ufl.grad(f.u_prev)) * f.dx, "grad-v"
        ),
    }


@pytest.mark.parametrize(("dim", "degree"), [(2, 1), (2, 2), (3, 1), (3, 2)])
@pytest.mark.parametrize("law", LAWS)
def test_objectives_match_coordinate_derivative(dim, degree, law):
    """The generic rule on objective integrals (cell and facet, reading X): == UFL's."""
    model = _model(dim, degree, law)
    f = model.fields
    theta = ufl.TestFunction(model.shape_space)
    for name, series in _objectives(model).items():
        for leaf in dict.fromkeys(series.leaves()):
            J = leaf.form(f)
            explicit = forms.form_shape_partial(J, theta)
            assert explicit is not None, f"{name}: the rule should apply"
            reference = ufl.derivative(J, f.X, theta)
            error = _relative_difference(_assemble(explicit), _assemble(reference))
            assert error <= RTOL, f"{name}: relative difference {error:.2e}"


def test_fall_backs_to_coordinate_derivative():
    """Where the rule does not hold (or the term is user-written) UFL's derivative is used."""
    model = _model(2, 1, "neo_hookean")
    f, lam = model.fields, _adjoint(model)
    theta = ufl.TestFunction(model.shape_space)
    n = ufl.FacetNormal(model.domain.mesh)
    h = ufl.CellDiameter(model.domain.mesh)
    # integrands the rule must refuse: normals, cell sizes, a gradient on a facet, grad grad
    refused = {
        "normal": ufl.dot(f.u, n) * f.ds(2),
        "cell size": h * ufl.dot(f.u, f.u) * f.dx,
        "facet gradient": ufl.inner(ufl.grad(f.u), ufl.grad(f.u)) * f.ds(2),
        "interior facet": ufl.avg(ufl.dot(f.u, f.u)) * ufl.dS,
    }
    for name, J in refused.items():
        assert forms.form_shape_partial(J, theta) is None, name
        assert "CoordinateDerivative" in repr(objective_shape_partial(J, f.X, theta)), name
    model_p2 = _model(2, 2, "neo_hookean")
    u2 = model_p2.fields.u
    assert not forms.is_transformable(ufl.inner(ufl.grad(ufl.grad(u2)), ufl.grad(ufl.grad(u2))))
    # user-written terms and laws have no explicit partial
    user = EnergyTerm(lambda g: ufl.dot(g.u, g.u) * g.dx)
    assert user.shape_partial(f, lam, theta) is None

    class MyLaw(forms.NeoHookeanEnergy):
        pass

    term = ElasticEnergy(MyLaw(), None, model.lame)
    assert term.shape_partial(f, lam, theta) is None

    class MyForce(BodyForce):  # a subclass may read gradients: not the built-in rule
        def energy_density(self, g):
            return super().energy_density(g) + ufl.inner(ufl.grad(g.u), ufl.grad(g.u))

    assert MyForce("gravity").shape_partial(f, lam, theta) is None
    with pytest.raises(ParameterError, match="shape_partials"):
        residual_shape_partial(model, True, lam, theta, "reverse")


def test_user_term_uses_coordinate_derivative():
    """A model with a user-written term: the whole step partial is UFL's, and it is right."""
    domain = _domain(2)
    model = ds.Model(domain, ds.NeoHookean(E=1e3, nu=0.3, density=2.0, damping_psi=1.0))
    model.add_term(lambda g: 5.0 * ufl.dot(g.u, g.u) * g.dx)
    f = model.fields
    f.u.x.array[:] = 0.01 * np.random.default_rng(3).standard_normal(f.u.x.array.size)
    lam = _adjoint(model)
    theta = ufl.TestFunction(model.shape_space)
    form = residual_shape_partial(model, True, lam, theta)
    assert "CoordinateDerivative" in repr(form)
    reference = ufl.derivative(
        ufl.derivative(model.potential(True), f.u, lam), f.X, ufl.TestFunction(model.shape_space)
    )
    assert _relative_difference(_assemble(form), _assemble(reference)) == 0.0


# -- a damped dynamic shape gradient ----------------------------------------------------------
def _dynamic_problem(dim: int):
    model = ds.Model(
        _domain(dim),
        ds.NeoHookean(E=300.0, nu=0.3, density=1.0, damping_psi=0.4, damping_phi=0.2),
        degree=1,
    )
    model.add_gravity(4.0)
    model.add_traction(2, np.eye(dim)[-1] * -3.0)
    model.add_dirichlet(1, 0.0)
    v0 = np.eye(dim)[-1] * 0.3
    sim = ds.Simulation(
        model, ds.BDF(2, 0.05, 3), ds.SolverOptions(rtol=1e-13), v0=v0, progress=False
    )
    objective = time_integral(stress_lp_norm(model, 4) * 1e-2, "uniform") + time_integral(
        target_displacement(model, np.eye(dim)[-1] * -0.01, facets=2) * 1e2, "uniform"
    )
    return sim, objective


@pytest.mark.parametrize("dim", [2, 3])
def test_dynamic_shape_gradient(dim):
    """Damped BDF2 shape gradient: explicit partials == UFL path (1e-12), and central
    differences along a random direction and along the gradient."""
    sim, objective = _dynamic_problem(dim)
    rf = ReducedFunctional(sim, objective, [ShapeControl(sim.model, "all")])
    q0 = rf.initial_parameters()
    g = rf.gradient(q0)
    # the step partials of this model take the explicit path
    lam = fem.Function(sim.model.V)
    theta = ufl.TestFunction(sim.model.shape_space)
    assert "CoordinateDerivative" not in repr(residual_shape_partial(sim.model, True, lam, theta))
    reference = ReducedFunctional(
        sim,
        objective,
        [ShapeControl(sim.model, "all")],
        adjoint_options=AdjointSolverOptions(shape_partials="ufl"),
    )
    g_ufl = reference.gradient(q0)
    assert (rf._sweep.forms.shape_partials, reference._sweep.forms.shape_partials) == (
        "auto",
        "ufl",
    )
    comm = MPI.COMM_WORLD
    norm = np.sqrt(comm.allreduce(float(g_ufl @ g_ufl), op=MPI.SUM))
    diff = np.sqrt(comm.allreduce(float((g - g_ufl) @ (g - g_ufl)), op=MPI.SUM))
    assert norm > 0 and diff <= RTOL * norm, f"explicit vs UFL: {diff / norm:.2e}"
    rng = np.random.default_rng(5)
    d = rng.standard_normal(q0.size)
    d *= 1e-2 / np.abs(d).max()  # a vertex motion well inside the cells
    steps = np.array([1.0, 1e-1, 1e-2])
    random = finite_difference_check(rf, q0, d, steps, gradient=g)
    assert abs(random.adjoint) > 1e-10 and random.relative_error <= 1e-6, str(random)
    along = finite_difference_check(rf, q0, g * (1e-2 / np.abs(g).max()), steps, gradient=g)
    assert along.relative_error <= 1e-6, str(along)
