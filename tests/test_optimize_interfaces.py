"""The reduced functional used by external optimisers without glue: scipy and PETSc TAO."""

import numpy as np
import pytest
import scipy.optimize
from optimize_script import E_TRUE
from petsc4py import PETSc


def test_scipy_lbfgsb(bar2):
    rf, _ = bar2
    q0 = rf.initial_parameters()
    lo, hi = rf.bounds()
    result = scipy.optimize.minimize(
        rf.value_and_gradient,
        q0,
        jac=True,
        method="L-BFGS-B",
        bounds=scipy.optimize.Bounds(lo, hi),
        options={"ftol": 1e-30, "gtol": 1e-12, "maxiter": 200},
    )
    assert result.success, result.message
    assert np.allclose(np.exp(result.x), E_TRUE, rtol=1e-6)
    # with finite bounds that cut off the optimum of body 1
    cap = np.log([1500.0, 1e5])
    result = scipy.optimize.minimize(
        rf.value_and_gradient,
        q0,
        jac=True,
        method="L-BFGS-B",
        bounds=list(zip(np.log([100.0, 100.0]), cap, strict=True)),
        options={"ftol": 1e-30, "gtol": 1e-12, "maxiter": 200},
    )
    assert result.success, result.message
    assert np.isclose(result.x[0], cap[0], rtol=0, atol=1e-12)
    rf.controls.assign(q0)


def test_petsc_tao_blmvm(bar2):
    rf, _ = bar2
    q0 = rf.initial_parameters()
    x = PETSc.Vec().createSeq(rf.size, comm=PETSc.COMM_SELF)
    x.setArray(q0)
    g = x.duplicate()
    lower, upper = x.duplicate(), x.duplicate()
    lower.setArray(np.log([100.0, 100.0]))
    upper.setArray(np.log([1e5, 1e5]))
    tao = PETSc.TAO().create(PETSc.COMM_SELF)
    tao.setType("blmvm")
    tao.setObjectiveGradient(rf.tao_objective_gradient, g)
    tao.setVariableBounds(lower, upper)
    tao.setTolerances(gatol=1e-13, grtol=0.0, gttol=0.0)
    tao.setMaximumIterations(200)
    tao.setSolution(x)
    tao.solve()
    assert tao.getConvergedReason() > 0, tao.getConvergedReason()
    assert np.allclose(np.exp(x.getArray()), E_TRUE, rtol=1e-6)
    # the callback filled g with the adjoint gradient at the solution
    J, grad = rf.value_and_gradient(x.getArray().copy())
    assert np.allclose(g.getArray(), grad, rtol=1e-12, atol=0)
    assert tao.getObjectiveValue() == pytest.approx(J, rel=1e-12, abs=1e-30)
    tao.destroy()
    for v in (x, g, lower, upper):
        v.destroy()
    rf.controls.assign(q0)


def test_the_optimiser_contract(bar2):
    """minimize takes what provides OptimizableFunctional and refuses anything else by name."""
    import diffsolids as ds
    from diffsolids.optimize import OptimizableFunctional, OptimizationError

    rf, _ = bar2
    assert isinstance(rf, OptimizableFunctional)

    class HalfAFunctional:
        def forward(self, q):
            return float(np.sum(q**2))

    with pytest.raises(OptimizationError, match=r"OptimizableFunctional.*HalfAFunctional"):
        ds.minimize(HalfAFunctional(), np.zeros(2))
