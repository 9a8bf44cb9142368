"""An obstacle driven into contact by Dirichlet values: continuation within a step, gradients.

A stiff indenter whose vertices are all prescribed (a static obstacle for the contact term) is
moved down into a soft block clamped at its bottom. Applying a step's new Dirichlet values to
the previous state would push the indenter through the block's surface; the Simulation reaches
them through lifted steps (the linearised response, contact coupling included) and, where even
those collide, intermediate equilibria with the prescribed dofs held part-way
(``Simulation._dirichlet_continuation``). The step's own solve then starts from an admissible
guess and its solution, and adjoint, are those of the full values.
"""

import ipctk
import numpy as np
import pytest
import ufl
from contact_checks import IntersectionMonitor
from mpi4py import MPI
from test_gradients_contact import _direction, check_gradient

import diffsolids as ds
from diffsolids.contact import ContactTerm, suggest_barrier_stiffness
from diffsolids.controls import ParameterControl, ShapeControl
from diffsolids.errors import NewtonConvergenceError
from diffsolids.mesh.scene import combine_meshes, simplex_box
from diffsolids.objectives import Integral, final_value, time_integral
from diffsolids.reduced_functional import ReducedFunctional

DHAT = 1e-2
GAP = 0.5 * DHAT
DEPTH = 0.05  # five dhat: the indenter ends 0.045 below the block's rest surface


def _indenter_scene(dynamic: bool, friction: float = 0.0, comm=MPI.COMM_SELF):
    block = simplex_box([[0, 0], [1, 0.3]], [6, 3])
    indenter = simplex_box([[0.4137, 0.3 + GAP], [0.6137, 0.4 + GAP]], [2, 1])
    dom = combine_meshes(comm, [block, indenter], names={"block": 1, "indenter": 2})
    materials = {
        1: ds.NeoHookean(E=1e4, nu=0.3, density=10.0, damping_psi=1.0),
        2: ds.NeoHookean(E=1e6, nu=0.3, density=10.0),
    }
    model = ds.Model(dom, materials)
    model.add_dirichlet(lambda x: x[1] < 1e-9, 0.0)
    duration = 0.1 if dynamic else 1.0
    integ = ds.BDF(2, duration / 6, 6) if dynamic else ds.Static(num_steps=3, dt=duration / 3)
    path = np.array([0.2 * DEPTH, -DEPTH]) / duration  # down, and sideways (friction)
    model.add_dirichlet(lambda x: x[1] > 0.3 + GAP / 2, lambda t: path * t)
    probe = ContactTerm(model, dhat=DHAT, stiffness=1.0)
    kappa = suggest_barrier_stiffness(probe, integ)
    contact = ContactTerm(model, dhat=DHAT, stiffness=kappa, friction=friction, eps_v=1e-2)
    model.add_numeric_term(contact)
    sim = ds.Simulation(model, integ, ds.SolverOptions(rtol=1e-12), progress=False)
    objective = final_value(
        Integral(lambda f: ufl.dot(f.u, f.u) * f.dx(1), "block_u2")
    ) + time_integral(Integral(lambda f: f.u[0] * f.dx(1), "block_ux"))
    return model, contact, sim, objective


def _check_indentation(model, contact, sim):
    monitor = IntersectionMonitor(sim, contact)
    traj = sim.run()
    assert sim.substeps, "the scene should need intermediate solves (continuation)"
    assert monitor.checked > 0 and not monitor.bad
    surf = contact.surface
    U = surf.gather(traj.u[-1])
    on_indenter = surf.body == 2
    # the prescribed motion is met exactly
    assert np.allclose(U[on_indenter], [0.2 * DEPTH, -DEPTH], rtol=0, atol=1e-14)
    # the block's surface under the indenter was pushed down ahead of it
    X = surf.rest_positions
    under = (surf.body == 1) & (np.abs(X[:, 0] - 0.5137) < 0.1) & (X[:, 1] > 0.3 - 1e-9)
    assert under.sum() >= 1
    assert np.all(U[under, 1] < -(DEPTH - GAP) + DHAT)
    records = contact.records
    assert len(records) == sim.integrator.num_steps
    assert all(r.num_collisions > 0 and 0 < r.min_distance < DHAT for r in records)
    x = X + U
    assert not ipctk.has_intersections(surf.mesh, np.asfortranarray(x))
    return traj


@pytest.mark.parametrize(
    ("dynamic", "friction"), [(False, 0.0), (True, 0.3)], ids=["static-3-load-steps", "bdf2"]
)
def test_indenter_driven_by_dirichlet_values(dynamic, friction):
    model, contact, sim, objective = _indenter_scene(dynamic, friction)
    _check_indentation(model, contact, sim)
    if friction:
        assert max(np.abs(r.friction_force).max() for r in contact.records) > 0
    controls = [
        ParameterControl(model, "E", "bodies", bodies=["block"], log=True),
        ShapeControl(model, "all"),
    ]
    rf = ReducedFunctional(sim, objective, controls)
    # entries of about 0.05 in log E and 1e-5 in the rest positions
    direction = np.concatenate([_direction(1, 0.05), _direction(rf.size - 1, 1e-5, seed=1)])
    check_gradient(rf, contact, direction, taylor_h0=1.0)
    assert sim.substeps  # the gradient went through continued steps


def test_continuation_limit_is_reported():
    _, _, sim, _ = _indenter_scene(dynamic=True)
    sim.max_substeps = 1
    with pytest.raises(NewtonConvergenceError, match=r"step 1 .*within 1 substeps"):
        sim.run()
