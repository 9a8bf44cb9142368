"""The friction gradient of a 3D contact scene verified by central differences (issue 14).

Scene: an elastic box (Neo-Hookean, 3D, P1) thrown with v0 = (1, 0, -1) m/s onto a slab
clamped at its base, under gravity tilted by 25 degrees, with IPC contact (suggested barrier
stiffness, dhat 1e-3) and lagged smoothed friction (eps_v 1e-3, mu = 0.3), 5 BDF1 steps of
0.05 s. Objective: int_block x^2 at the final time.

With contact the step potential is not convex. With the exact contact Hessian from the first Newton
iteration (PSD-projected only when its step is not a descent direction;
``exact_hessian_below=inf``, the default before 1e-3) step 5 of the run at mu - 1e-6 left the basin
it was approaching after a projected step at iteration 10 and converged (residual 2.5e-11) to
another stationary point, 2.3e-3 above the minimum that mu and mu + 1e-6 reach (1.9e-3 apart in u,
one collision less): J jumped by 1.6e-5, and central differences gave 8.9e-3, 0.23 and 7.76 for h =
1e-2, 1e-4, 1e-6 against an adjoint -9.42e-4 (relative errors 8.5, 245, 8200). Newton steps on the
projected Hessian until the residual is below 1e-3 f_char (``exact_hessian_below``) descend into
the minimum: the differences converge to the adjoint (2.9e-3, 2.9e-5, 2.6e-7 for h = 1e-4, 1e-5,
1e-6, as h^2).
"""

import numpy as np
from mpi4py import MPI

import diffsolids as ds
from diffsolids.contact import ContactTerm, suggest_barrier_stiffness
from diffsolids.controls import FrictionControl
from diffsolids.mesh.scene import combine_meshes, simplex_box
from diffsolids.objectives import Integral, final_value
from diffsolids.reduced_functional import ReducedFunctional
from diffsolids.verification import finite_difference_check

MU = 0.3
FD_TOLERANCE = 1e-6
STEPS = np.array([1e-5, 1e-6])  # central-difference steps, times a direction of norm 1
DHAT = 1e-3
# projected Newton steps until ||F|| <= 1e-3 f_char: the default (see SolverOptions)
SMOOTH = ds.SolverOptions(exact_hessian_below=1e-3)


def box_on_slab(options: ds.SolverOptions, comm=MPI.COMM_SELF):
    """The thrown box on the clamped slab; returns (contact, simulation, objective)."""
    theta = np.deg2rad(25.0)
    slab = simplex_box([[0, 0, 0], [1.5, 0.6, 0.1]], [6, 3, 1])
    lo = [0.2137, 0.1791, 0.1 + 0.5 * DHAT]
    block = simplex_box([lo, [lo[0] + 0.3, lo[1] + 0.3, lo[2] + 0.15]], [2, 2, 1])
    domain = combine_meshes(comm, [slab, block], names={"slab": 1, "block": 2})
    materials = {
        1: ds.NeoHookean(E=1e6, nu=0.3, density=1000.0),
        2: ds.NeoHookean(E=1e5, nu=0.4, density=1000.0),
    }
    model = ds.Model(domain, materials, degree=1)
    model.add_body_force(9.81 * np.array([np.sin(theta), 0.1, -np.cos(theta)]), name="gravity")
    model.add_dirichlet(lambda x: x[2] < 0.1 + 1e-9, 0.0)
    integrator = ds.BDF(1, 0.05, 5)
    probe = ContactTerm(model, dhat=DHAT, stiffness=1.0)
    kappa = suggest_barrier_stiffness(probe, integrator)
    contact = ContactTerm(
        model, dhat=DHAT, stiffness=kappa, friction={("slab", "block"): MU}, eps_v=1e-3
    )
    model.add_numeric_term(contact)
    x = model.V.tabulate_dof_coordinates()
    v0 = np.zeros((x.shape[0], 3))
    v0[x[:, 2] > 0.1 + 1e-4] = [1.0, 0.0, -1.0]
    sim = ds.Simulation(model, integrator, options, v0=v0.ravel(), progress=False)
    objective = final_value(Integral(lambda f: (f.X[0] + f.u[0]) ** 2 * f.dx(2), "x2"))
    return contact, sim, objective


def friction_checks(options: ds.SolverOptions, comm=MPI.COMM_SELF):
    """Central differences of J(mu) in a random direction and along the gradient."""
    contact, sim, objective = box_on_slab(options, comm)
    rf = ReducedFunctional(sim, objective, FrictionControl(contact, pairs=[("slab", "block")]))
    q = np.array([MU])
    g = rf.gradient(q)
    # one parameter: the random direction is a random scale and sign, the gradient's its sign
    random = np.random.default_rng(3).uniform(-1.0, 1.0, 1)
    directions = {"random": random / np.linalg.norm(random), "gradient": g / np.linalg.norm(g)}
    return {k: finite_difference_check(rf, q, d, STEPS, gradient=g) for k, d in directions.items()}


def test_friction_gradient_matches_central_differences():
    for name, res in friction_checks(SMOOTH).items():
        assert abs(res.adjoint) > 1e-5, f"{name}: friction does not act\n{res}"
        assert res.relative_error <= FD_TOLERANCE, f"{name}\n{res}"


def test_exact_hessian_is_not_smooth():
    """The exact Hessian from the start (inf): J jumps at mu - 1e-6 (module docstring)."""
    res = friction_checks(ds.SolverOptions(exact_hessian_below=np.inf))["gradient"]
    assert res.relative_error > 1e-2, str(res)
