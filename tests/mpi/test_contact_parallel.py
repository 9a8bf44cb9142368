"""Run under ``mpiexec -n 2``: contact on 2 ranks gives the serial energies, residuals, solutions.

The collision surface is gathered on every rank and numbered by input vertex index, so ipctk sees
the same problem as in serial; each rank adds its owned rows.
"""

import dolfinx.fem.petsc as fem_petsc
import numpy as np
from contact_checks import crate_on_incline
from dolfinx import fem
from mpi4py import MPI

from diffsolids.states import Phase, StepContext

DHAT = 1e-3


def _sorted_nodal(model, arr: np.ndarray) -> np.ndarray:
    """Owned nodal values of all ranks, ordered by node coordinates (partition independent)."""
    V = model.V
    comm = V.mesh.comm
    n = V.dofmap.index_map.size_local
    d = model.dim
    x = np.round(V.tabulate_dof_coordinates()[:n, :d], 12)
    xs = np.concatenate(comm.allgather(x))
    vs = np.concatenate(comm.allgather(arr.reshape(-1, d)[:n]))
    return vs[np.lexsort(xs.T[::-1])]


def _run(comm):
    model, contact, sim = crate_on_incline(comm, DHAT, [4, 2], [2, 1], 8)
    integ = sim.integrator
    traj = sim.run()
    out = {
        "energies": np.array([r.energy for r in traj.records]),
        "collisions": [r.num_collisions for r in contact.records],
        "min_distance": np.array([r.min_distance for r in contact.records]),
        "normal_force": np.array([r.normal_force for r in contact.records]),
        "u": _sorted_nodal(model, traj.u[-1]),
        "rebuilds": sim.solver.patterns.rebuilds,
    }
    # kernels at the last state, lagged from the one before
    i = integ.num_steps
    contact.begin_step(StepContext.of(integ, i, traj, Phase.BACKWARD))
    u = fem.Function(model.V)
    u.x.array[:] = traj.u[i]
    b = fem_petsc.create_vector(model.V)
    b.set(0.0)
    contact.add_residual(u, b)
    out["contact_energy"] = contact.energy(u)
    lam = fem.Function(model.V)
    lam.interpolate(lambda x: np.vstack([np.sin(7 * x[0]) * x[1], np.cos(5 * x[1]) + x[0]]))
    lam.x.array[model.dirichlet_dofs()] = 0.0
    out["residual"] = _sorted_nodal(model, b.array_r)
    out["history"] = [_sorted_nodal(model, g) for g in contact.adjoint_history(u, lam).values()]
    out["friction"] = contact.adjoint_friction(u, lam)
    S = model.shape_space
    out["shape"] = _sorted_nodal_space(S, contact.adjoint_shape(u, lam), model.dim)
    return out


def _sorted_nodal_space(S, arr, d):
    comm = S.mesh.comm
    n = S.dofmap.index_map.size_local
    x = np.round(S.tabulate_dof_coordinates()[:n, :d], 12)
    xs = np.concatenate(comm.allgather(x))
    vs = np.concatenate(comm.allgather(arr.reshape(-1, d)[:n]))
    return vs[np.lexsort(xs.T[::-1])]


def _close(a, b, rtol):
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    scale = max(np.abs(b).max(initial=0.0), 1e-300)
    return np.abs(a - b).max(initial=0.0) <= rtol * scale


def test_contact_parallel_matches_serial():
    par = _run(MPI.COMM_WORLD)
    ser = _run(MPI.COMM_SELF)
    assert par["collisions"] == ser["collisions"] and max(ser["collisions"]) > 0
    assert ser["rebuilds"] > 0 and par["rebuilds"] > 0  # crate-lid contact couples free bodies
    assert _close(par["energies"], ser["energies"], 1e-9)
    assert _close(par["min_distance"], ser["min_distance"], 1e-7)
    assert _close(par["normal_force"], ser["normal_force"], 1e-7)
    assert _close(par["u"], ser["u"], 1e-8)
    assert abs(par["contact_energy"] - ser["contact_energy"]) <= 1e-10 * abs(ser["contact_energy"])
    assert _close(par["residual"], ser["residual"], 1e-9)
    for gp, gs in zip(par["history"], ser["history"], strict=True):
        assert _close(gp, gs, 1e-9)
    assert _close(par["friction"], ser["friction"], 1e-9)
    assert _close(par["shape"], ser["shape"], 1e-9)
