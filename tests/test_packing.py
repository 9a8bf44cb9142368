"""Shared coefficient packing (``solvers/packing.py``) equals DOLFINx's, bit for bit.

Forms of a damped dynamic Neo-Hookean model with a facet objective (cell and exterior-facet
integrals, an integral that does not use every coefficient), P1 and P2, 2D and 3D: after the
fields change, after only some change, after one value of one changes and after none does,
with the values compared as bytes (small arrays) and with np.array_equal (large ones); a form
with an interior-facet integral is left to DOLFINx.
"""

import numpy as np
import pytest
import ufl
from dolfinx import fem
from mpi4py import MPI

import diffsolids as ds
from diffsolids.adjoint.forms import AdjointForms
from diffsolids.adjoint.sensitivities import Targets
from diffsolids.mesh import create_box, create_rectangle
from diffsolids.objectives import stress_lp_norm, target_displacement, time_integral
from diffsolids.solvers import packing
from diffsolids.solvers.forms import compile_form
from diffsolids.solvers.packing import CoefficientGathers, FormPacker


def _model(dim: int, degree: int):
    box = [[0.0] * dim, [2.0] + [0.5] * (dim - 1)]
    cells = [8] + [2] * (dim - 1)
    create = create_box if dim == 3 else create_rectangle
    domain = create(MPI.COMM_WORLD, box, cells, facets={2: lambda x: np.isclose(x[0], 2)})
    law = ds.NeoHookean(E=1e4, nu=0.3, density=10.0, damping_psi=1.0, damping_phi=0.5)
    model = ds.Model(domain, law, degree=degree)
    model.add_gravity(9.81)
    goal = [0.0] * (dim - 1) + [-1e-3]
    objective = time_integral(stress_lp_norm(model, 4), "uniform") + time_integral(
        target_displacement(model, goal, facets=2), "uniform"
    )
    return model, list(dict.fromkeys(objective.leaves()))


def _assert_packs_equal(packers) -> None:
    for packer in packers:
        mine, ref = packer.pack(), fem.pack_coefficients(packer.form)
        assert mine is not None and set(mine) == set(ref)
        for key in ref:
            assert np.array_equal(mine[key], ref[key])


@pytest.mark.parametrize("compare_bytes_below", [0, 2**40])
@pytest.mark.parametrize(("dim", "degree"), [(2, 1), (2, 2), (3, 1), (3, 2)])
def test_shared_packing_equals_dolfinx(dim, degree, compare_bytes_below, monkeypatch):
    monkeypatch.setattr(packing, "_BYTES_COMPARE_MAX", compare_bytes_below)
    model, leaves = _model(dim, degree)
    forms = AdjointForms(model, True, leaves, Targets(shape=True))
    candidates = [forms.objective_u, forms.history_tilde, forms.history_prev, *forms.shape]
    gathers = CoefficientGathers()
    packers = [FormPacker(form, gathers) for form in candidates if form is not None]
    assert len(packers) == 5 and all(p.supported for p in packers)
    kinds = {k for p in packers for k in p.form._cpp_object.integral_types}
    assert fem.IntegralType.exterior_facet in kinds
    rng = np.random.default_rng(1)
    f = model.fields
    for changed in [(f.u, f.u_prev, f.u_tilde, forms.lam), (f.u,), (forms.lam,), ()]:
        for field in changed:
            field.x.array[:] = rng.standard_normal(field.x.array.size)
        _assert_packs_equal(packers)
    f.u_prev.x.array[3] += 1.0  # one value of one field
    _assert_packs_equal(packers)


def test_interior_facet_forms_are_left_to_dolfinx():
    model, _ = _model(2, 1)
    u = model.fields.u
    w = ufl.TestFunction(model.V)
    form = compile_form(ufl.inner(ufl.avg(u), ufl.avg(w)) * ufl.dS)
    packer = FormPacker(form, CoefficientGathers())
    assert not packer.supported and packer.pack() is None
