"""Contact parameters of a PolyFEM scene, as PolyFEM uses them.

PolyFEM's step potential (BDF, h = beta dt) is

    Pi_P = 1/2 |x - x_tilde|_M^2 + h^2 [Psi(x) - f.x + kappa_P B_P(x) + beta dt D(v)],

with B_P = sum_k b(d_k^2, dhat^2), b(s, t) = -(s - t)^2 ln(s / t), every pair weighted 1 (the
default, non-"convergent" formulation). diffsolids' step potential is Pi_P / h^2 term by term
(see :mod:`diffsolids.contact.term`), so a numeric ``barrier_stiffness`` kappa_P is our
``stiffness`` as written, with ``area_weighting=False``, independently of dt and the BDF order.
``"barrier_stiffness": "adaptive"`` means ipctk's initial barrier stiffness, which
:func:`~diffsolids.contact.suggest_barrier_stiffness` computes in our units.

Defaults (PolyFEM's input spec): ``dhat`` 1e-3; ``epsv`` 1e-3; friction coefficient 0;
``barrier_stiffness`` adaptive. When a scene gives no ``dhat`` and the default 1e-3 is longer
than the shortest edge of the collision mesh at rest (the bodies' boundary edges and the
obstacles' edges), dhat is ``dhat_percentage`` (default 0.8) times that edge: PolyFEM's
``NonlinearElasticVarForm::preprocess_contact_parameters``
(``src/polyfem/varforms/NonlinearElasticVarForm.cpp``, polyfem/polyfem at commit 661588e; the
same rule in ``legacy/State.cpp``), which takes the minimum over ``collision_mesh.edges()``
at ``rest_positions()``. A dhat given in the scene is used as written (PolyFEM only warns
when it exceeds the shortest edge). PolyFEM reads ``barrier_stiffness`` from
``solver.contact``, the others from ``contact``.

``use_convergent_formulation: true`` is ``ContactTerm(formulation="convergent",
area_weighting=True)``: PolyFEM then sets ipctk's area weighting, improved max operator and
physical barrier (``use_area_weighting``, ``use_improved_max_operator``,
``use_physical_barrier``, each default true; ``legacy/state/StateSolveNonlinear.cpp``). The
physical barrier multiplies b(d^2, dhat^2) by dhat / units(dhat^2) = 1 / dhat^3
(ipctk ``BarrierPotential``, ``ClampedLogSqBarrier::units``), so a numeric kappa_P is our
stiffness kappa_P / dhat^3 (kappa_P with ``use_physical_barrier: false``). Switching off the
area weights or the improved max operator is refused.

With ipctk's squared-distance barrier a pair carrying a contact force f settles at a distance
d ~ 2 kappa dhat^4 / f: the scenes' kappa_P (1e4-1e5 with dhat ~ 1e-3) put pairs at gaps of
1e-11..1e-9 m, where every Newton step is cut by the collision check; the Newton solver then
reaches the step's minimiser through a stiffness continuation
(``SolverOptions.continuation_after``).
"""

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import dolfinx
import numpy as np
from mpi4py import MPI

from diffsolids.errors import ParameterError
from diffsolids.mesh import Domain

if TYPE_CHECKING:
    from diffsolids.contact.geometry.obstacle import Obstacle

__all__ = ["polyfem_contact_options", "shortest_boundary_edge", "shortest_obstacle_edge"]

_DEFAULT_DHAT = 1e-3
_DEFAULT_EPSV = 1e-3
_DEFAULT_DHAT_PERCENTAGE = 0.8


def shortest_boundary_edge(domain: Domain) -> float:
    """Length of the shortest edge of the boundary (collective)."""
    mesh = domain.mesh
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim - 1, tdim)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    nodes = dolfinx.mesh.entities_to_geometry(mesh, tdim - 1, facets)
    x = mesh.geometry.x[:, : domain.dim]
    pairs = [(0, 1)] if tdim == 2 else [(0, 1), (1, 2), (2, 0)]
    lengths = [np.linalg.norm(x[nodes[:, a]] - x[nodes[:, b]], axis=1) for a, b in pairs]
    local = min((float(v.min()) for v in lengths if v.size), default=np.inf)
    out = np.array(local)
    domain.comm.Allreduce(MPI.IN_PLACE, out, op=MPI.MIN)
    return float(out)


def shortest_obstacle_edge(obstacles: Sequence["Obstacle"]) -> float:
    """Length of the shortest edge of the obstacles at rest (inf without obstacles)."""
    lengths = [
        np.linalg.norm(o.rest_positions[o.edges[:, 0]] - o.rest_positions[o.edges[:, 1]], axis=1)
        for o in obstacles
    ]
    return min((float(v.min()) for v in lengths if v.size), default=np.inf)


def polyfem_contact_options(
    scene: Mapping[str, Any], domain: Domain, obstacles: Sequence["Obstacle"] = ()
) -> dict[str, Any]:
    """Keyword arguments of :class:`~diffsolids.contact.ContactTerm` for a PolyFEM scene.

    Without ``contact.dhat``, PolyFEM's rule (module docstring): 1e-3, or
    ``contact.dhat_percentage`` (0.8) times the shortest collision-mesh edge when 1e-3 is
    longer than that edge.

    Args:
        scene: The scene JSON as a dict (its ``contact`` and ``solver.contact`` sections).
        domain: The Domain the scene's geometry was assembled into (for the dhat default).
        obstacles: The scene's kinematic obstacles (their edges are collision-mesh edges too).

    Returns:
        ``dhat``, ``stiffness`` (None for "adaptive": use ``suggest_barrier_stiffness``),
        ``friction``, ``eps_v``, ``area_weighting`` (False; True with the convergent
        formulation, which also sets ``formulation="convergent"``).

    Raises:
        ParameterError: Contact disabled, a convergent formulation without area weights or
            the improved max operator, or a malformed value.
    """
    contact = dict(scene.get("contact", {}))
    if not contact.get("enabled", False):
        raise ParameterError("the scene has no contact (contact.enabled is not true)")
    convergent = bool(contact.get("use_convergent_formulation", False))
    if convergent:
        for key in ("use_area_weighting", "use_improved_max_operator"):
            if not contact.get(key, True):
                raise ParameterError(
                    f"contact.{key} = false: diffsolids' convergent formulation always has "
                    "area weights and the improved max approximation"
                )
    if "dhat" in contact:
        dhat = float(contact["dhat"])
    else:
        edge = min(shortest_boundary_edge(domain), shortest_obstacle_edge(obstacles))
        fraction = float(contact.get("dhat_percentage", _DEFAULT_DHAT_PERCENTAGE))
        if not (np.isfinite(fraction) and fraction > 0):
            raise ParameterError(f"contact.dhat_percentage = {fraction!r}: a number > 0")
        dhat = fraction * edge if edge < _DEFAULT_DHAT else _DEFAULT_DHAT
    kappa = scene.get("solver", {}).get("contact", {}).get("barrier_stiffness", "adaptive")
    if kappa == "adaptive":
        stiffness = None
    elif isinstance(kappa, int | float) and np.isfinite(kappa) and kappa > 0:
        stiffness = float(kappa)
    else:
        raise ParameterError(
            f"solver.contact.barrier_stiffness = {kappa!r}: a number > 0 or 'adaptive'"
        )
    if convergent and stiffness is not None and contact.get("use_physical_barrier", True):
        stiffness /= dhat**3  # ipctk's physical barrier: b(d^2, dhat^2) dhat / units(dhat^2)
    return {
        "dhat": dhat,
        "stiffness": stiffness,
        "friction": float(contact.get("friction_coefficient", 0.0)),
        "eps_v": float(contact.get("epsv", _DEFAULT_EPSV)),
        "area_weighting": convergent,
        **({"formulation": "convergent"} if convergent else {}),
    }
