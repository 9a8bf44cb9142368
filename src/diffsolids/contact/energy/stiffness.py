"""A barrier stiffness suggested from the scene, as ipctk's ``initial_barrier_stiffness`` does.

ipctk balances the barrier gradient against the gradient of the other energies at the initial
state and clamps the result to [kappa_min, 100 kappa_min], with kappa_min proportional to an
average nodal mass in IPC's units (energies multiplied by dt^2). Our incremental potential has
elasticity with coefficient 1 (energies divided by (beta dt)^2), so the nodal "mass" becomes
m / (beta dt)^2 for BDF steps and, for static steps, the nodal elastic stiffness E h^(dim-2).
"""

from typing import TYPE_CHECKING, Protocol

import dolfinx.la
import ipctk
import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI
from ufl.core.expr import Expr

from diffsolids.parallel import collective_comm
from diffsolids.solvers.forms import compile_form

if TYPE_CHECKING:
    from diffsolids.contact.detection.collision_set import CollisionBuilder
    from diffsolids.contact.geometry.surface import CollisionSurface
    from diffsolids.integrators import Integrator
    from diffsolids.model import Model

__all__ = ["BarrierContact", "suggest_barrier_stiffness"]


class BarrierContact(Protocol):
    """What :func:`suggest_barrier_stiffness` reads of a contact term (met by ContactTerm)."""

    model: "Model"
    surface: "CollisionSurface"
    builder: "CollisionBuilder"
    dhat: float
    area_weighting: bool


def _young_modulus(model: "Model") -> Expr:
    c = model.coefficients
    if "E" in c:
        return c["E"]
    lmbda, mu = c["lmbda"], c["mu"]
    return mu * (3 * lmbda + 2 * mu) / (lmbda + mu)


def suggest_barrier_stiffness(
    contact: BarrierContact, integrator: "Integrator | None" = None, u: fem.Function | None = None
) -> float:
    """Suggest a fixed barrier stiffness kappa for a ContactTerm (collective).

    Args:
        contact: The ContactTerm (its dhat and collision surface are used; its own stiffness not).
        integrator: The integrator (BDF: mass-based minimum; Static or None: stiffness-based).
        u: Displacement to evaluate at (default: zero).

    Returns:
        kappa in [kappa_min, 100 kappa_min]: the value balancing the barrier gradient against the
        gradient of the other (static) energies when bodies are already within dhat, else
        kappa_min.
    """
    model = contact.model
    comm = model.domain.comm
    surf = contact.surface
    dim = model.dim
    dx = model.fields.dx
    volume = collective_comm(comm).allreduce(
        fem.assemble_scalar(compile_form(1.0 * dx)), op=MPI.SUM
    )
    num_nodes = model.V.dofmap.index_map.size_global
    if integrator is not None and integrator.dynamic:
        mass = collective_comm(comm).allreduce(
            fem.assemble_scalar(compile_form(model.coefficients["density"] * dx)), op=MPI.SUM
        )
        beta_dt = integrator.coefficients(1).beta_dt
        nodal = mass / num_nodes / beta_dt**2
    else:
        E = collective_comm(comm).allreduce(
            fem.assemble_scalar(compile_form(_young_modulus(model) * dx)), op=MPI.SUM
        )
        h = np.mean(np.linalg.norm(np.diff(surf.rest_positions[surf.edges], axis=1), axis=-1))
        nodal = E / volume * h ** (dim - 2)
    u = u if u is not None else fem.Function(model.V)
    saved = model.fields.u.x.array.copy()
    model.fields.u.x.array[:] = u.x.array
    residual = ufl.derivative(model.potential(False), model.fields.u, ufl.TestFunction(model.V))
    vec = fem.assemble_vector(compile_form(residual))
    vec.scatter_reverse(dolfinx.la.InsertMode.add)
    model.fields.u.x.array[:] = saved
    grad_energy = surf.gather(vec.array).ravel()
    x = np.asfortranarray(surf.rest_positions + surf.gather(u.x.array))
    unit = ipctk.BarrierPotential(contact.dhat, 1.0)
    C = contact.builder.whole_set(x)
    grad_barrier = unit.gradient(C, surf.mesh, x)
    if contact.area_weighting:  # the bodies' vertices: an obstacle's triangulation is no scale
        weights = surf.mesh.vertex_areas[: surf.num_body_vertices]
        nodal /= float(np.mean(weights)) if len(weights) else 1.0
    lo, hi = surf.rest_positions.min(axis=0), surf.rest_positions.max(axis=0)
    kappa, _ = ipctk.initial_barrier_stiffness(
        float(np.linalg.norm(hi - lo)), unit.barrier, contact.dhat, nodal, grad_energy, grad_barrier
    )
    return float(collective_comm(comm).bcast(kappa, root=0))
