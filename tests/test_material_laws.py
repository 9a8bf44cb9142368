"""Material laws as objects: a new law is one StrainEnergy subclass, nothing else edited.

A compressible Mooney-Rivlin law is written here; the model, the solver (inversion guard), the
stress objectives and the adjoint use it through the same interface as the built-in laws.
"""

import numpy as np
import pytest
import ufl
from demo_modules import load_docs_example
from dolfinx import fem
from mpi4py import MPI

import diffsolids as ds
from diffsolids import forms
from diffsolids.controls import ParameterControl, ShapeControl
from diffsolids.mesh import create_box, create_rectangle
from diffsolids.objectives import final_value, stress_lp_norm, target_displacement
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.solvers.forms import compile_form
from diffsolids.solvers.inversion import InversionGuard
from diffsolids.verification import finite_difference_check, taylor_test

# the how-to's law (docs/examples/howto_extend.py), checked here in depth
MooneyRivlin = load_docs_example("howto_extend").MooneyRivlin


def _field(dim: int, degree: int = 2):
    dom = (create_rectangle if dim == 2 else create_box)(
        MPI.COMM_SELF, [[0.0] * dim, [1.0] * dim], [2] * dim
    )
    V = fem.functionspace(dom.mesh, ("Lagrange", degree, (dim,)))
    u = fem.Function(V)
    u.interpolate(
        lambda x: 0.2 * np.array([np.sin(2 * x[k] + k) * x[(k + 1) % dim] for k in range(dim)])
    )
    return dom, u


def _integral(dom, expr) -> float:
    return fem.assemble_scalar(compile_form(expr * ufl.dx(domain=dom.mesh)))


@pytest.mark.parametrize("dim", [2, 3])
def test_mooney_rivlin_with_ratio_one_is_neo_hookean(dim):
    dom, u = _field(dim)
    nh = forms.STRAIN_ENERGIES["neo_hookean"]
    for a, b in (
        (MooneyRivlin(1.0).energy(u, 3.0, 1.5), nh.energy(u, 3.0, 1.5)),
        (MooneyRivlin(1.0).cauchy_stress(u, 3.0, 1.5), nh.cauchy_stress(u, 3.0, 1.5)),
    ):
        diff, size = _integral(dom, ufl.inner(a - b, a - b)), _integral(dom, ufl.inner(b, b))
        assert size > 1e-3 and diff <= 1e-24 * size
    # a different ratio is a different law
    other = MooneyRivlin(0.3).energy(u, 3.0, 1.5) - nh.energy(u, 3.0, 1.5)
    assert _integral(dom, other**2) > 1e-8


@pytest.mark.parametrize("law", ["linear", "st_venant_kirchhoff", "neo_hookean"])
def test_written_out_plane_strain_stress_equals_the_derived_one(law):
    dom, u = _field(2)
    builtin = forms.STRAIN_ENERGIES[law]
    derived = forms.StrainEnergy.plane_strain_normal_stress(builtin, u, 3.0, 1.5)
    written = builtin.plane_strain_normal_stress(u, 3.0, 1.5)
    diff, size = _integral(dom, (derived - written) ** 2), _integral(dom, written**2)
    assert size > 1e-3 and diff <= 1e-24 * size


def test_laws_by_name_and_unknown_names():
    assert ds.NeoHookean(E=1.0, nu=0.3).law is forms.STRAIN_ENERGIES["neo_hookean"]
    law = MooneyRivlin(0.5)
    assert ds.Material(law, E=1.0, nu=0.3).law is law
    with pytest.raises(ds.ParameterError, match="unknown constitutive law 'rubber'"):
        ds.Material("rubber", E=1.0, nu=0.3)


def _beam(law) -> ds.Simulation:
    dom = create_rectangle(
        MPI.COMM_WORLD,
        [[0, 0], [2.0, 0.3]],
        [8, 2],
        facets={1: lambda x: np.isclose(x[0], 0.0), 2: lambda x: np.isclose(x[0], 2.0)},
    )
    model = ds.Model(dom, ds.Material(law, E=400.0, nu=0.3, density=10.0))
    model.add_gravity(9.81)
    model.add_dirichlet(1, 0.0)
    return ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-13), progress=False)


def test_a_new_law_runs_through_solver_objectives_and_adjoint():
    sim = _beam(MooneyRivlin(0.6))
    model = sim.model
    assert any(isinstance(b, InversionGuard) for b in sim.solver.step_bounds)
    objective = final_value(stress_lp_norm(model, 4, "von_mises")) + final_value(
        target_displacement(model, [0.0, -0.05], facets=2)
    )
    controls = [ParameterControl(model, "E", "bodies"), ShapeControl(model, "boundary")]
    rf = ReducedFunctional(sim, objective, controls)
    q0 = rf.initial_parameters()
    try:
        g = rf.gradient(q0)
        rng = np.random.default_rng(3)
        d = rng.standard_normal(len(q0))
        d[0] *= 4.0  # E ~ 400: a relative step of 1e-2
        d[1:] *= 1e-2 / np.linalg.norm(d[1:])
        steps = np.array([1e-2, 1e-3, 1e-4])
        for direction in (d, g * (1e-2 / np.abs(g[1:]).max())):
            res = finite_difference_check(rf, q0, direction, steps, gradient=g)
            assert abs(res.adjoint) > 0 and res.relative_error <= 1e-6, str(res)
        assert taylor_test(rf, q0, d, h0=0.5, num=3).min_rate >= 1.9
    finally:
        rf.controls.assign(q0)
    # and the law changes the answer: the same beam with Neo-Hookean sags differently
    nh = _beam("neo_hookean").run().u[-1]
    assert not np.allclose(sim.run().u[-1], nh, rtol=1e-6, atol=0)
