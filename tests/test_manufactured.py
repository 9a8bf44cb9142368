"""Manufactured solutions: static linear elasticity converges at the optimal L2 rate k + 1.

The exact displacement is a smooth non-polynomial field; its body force f = -div sigma(u_exact)
enters as a user EnergyTerm -f . u dx built with UFL from the rest coordinates, and the Dirichlet
value on the whole boundary is the exact solution through a ``value(x, t)`` callable.
"""

import numpy as np
import pytest
import ufl
from dolfinx import fem
from mpi4py import MPI

import diffsolids as ds
from diffsolids.mesh import create_box, create_rectangle
from diffsolids.model import EnergyTerm

E, NU = 2.0, 0.3
LMBDA, MU = E * NU / ((1 + NU) * (1 - 2 * NU)), E / (2 * (1 + NU))

# (dim, degree) -> cells per direction of the three meshes (h halves each time)
MESHES = {
    (2, 1): (8, 16, 32),
    (2, 2): (4, 8, 16),
    (2, 3): (2, 4, 8),
    (3, 1): (3, 6, 12),
    (3, 2): (2, 4, 8),
    (3, 3): (1, 2, 4),
}


def _exact(X, dim: int, lib):
    """Exact displacement as a list of components (lib = ufl or numpy)."""
    x, y = X[0], X[1]
    if dim == 2:
        return [
            0.1 * lib.sin(1.3 * x + 0.4) * lib.cos(0.9 * y),
            0.1 * lib.cos(0.7 * x) * lib.sin(1.1 * y + 0.3) + 0.05 * x * y,
        ]
    z = X[2]
    return [
        0.1 * lib.sin(1.3 * x + 0.4) * lib.cos(0.9 * y - 0.5 * z),
        0.1 * lib.cos(0.7 * x + 0.6 * z) * lib.sin(1.1 * y + 0.3),
        0.1 * lib.sin(0.8 * x + 0.9 * y + 1.2 * z) + 0.05 * x * z,
    ]


def _l2_error(dim: int, degree: int, n: int) -> float:
    comm = MPI.COMM_WORLD
    boundary = {1: lambda x: np.full(x.shape[1], True)}
    if dim == 2:
        dom = create_rectangle(comm, [[0, 0], [1, 1]], [n, n], facets=boundary)
    else:
        dom = create_box(comm, [[0, 0, 0], [1, 1, 1]], [n, n, n], facets=boundary)
    model = ds.Model(dom, ds.LinearElastic(E=E, nu=NU), degree=degree)

    def exact_ufl(X):
        return ufl.as_vector(_exact(X, dim, ufl))

    def body_force(X):
        eps = ufl.sym(ufl.grad(exact_ufl(X)))
        sigma = 2 * MU * eps + LMBDA * ufl.tr(eps) * ufl.Identity(dim)
        return -ufl.div(sigma)

    model.add_term(
        EnergyTerm(lambda f: -ufl.dot(body_force(f.X), f.u) * f.dx, "mms", quadratic=True)
    )
    model.add_dirichlet(1, lambda x, t: np.array(_exact(x, dim, np)))
    traj = ds.Simulation(model, ds.Static(), progress=False).run()
    assert traj.records[-1].residual < 1e-10  # forces are O(1): solved to roundoff
    uh = fem.Function(model.V)
    uh.x.array[:] = traj.u[-1]
    X = ufl.SpatialCoordinate(dom.mesh)
    diff = uh - exact_ufl(X)
    dx = ufl.dx(domain=dom.mesh, metadata={"quadrature_degree": 2 * degree + 3})
    local = fem.assemble_scalar(fem.form(ufl.inner(diff, diff) * dx))
    return float(np.sqrt(comm.allreduce(local, op=MPI.SUM)))


@pytest.mark.parametrize(("dim", "degree"), list(MESHES))
def test_l2_convergence_rate(dim, degree):
    sizes = MESHES[dim, degree]
    errors = np.array([_l2_error(dim, degree, n) for n in sizes])
    rates = np.log2(errors[:-1] / errors[1:])
    print(f"{dim}D P{degree}: n = {sizes}, L2 errors {errors}, rates {rates}")
    assert abs(rates[-1] - (degree + 1)) < 0.2, rates
    assert abs(rates[0] - (degree + 1)) < 0.4, rates
