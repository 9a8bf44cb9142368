"""Helpers of the material optimisation demos: state output, invariants, field plots.

Shared by ``sine_bar``, ``bridge_material``, ``bouncing_ball_height`` and ``kangaroo_material``:
writing the initial and final states (with the material fields) to VTX/XDMF, the invariants
every run checks (no inverted element in any deformed state, no intersection in contact
scenes), CPU time, and the deformed mesh coloured by a cellwise field for the figures.
"""

import time
from pathlib import Path

import ipctk
import numpy as np
from dolfinx import fem
from mpi4py import MPI

from diffsolids.io import TrajectoryWriter
from diffsolids.mesh import signed_cell_volumes
from diffsolids.parallel import collective_comm

__all__ = [
    "TrajectoryGrabber",
    "body_cell_mask",
    "cell_values",
    "center_of_mass_history",
    "cpu_seconds",
    "deformed_triangles",
    "intersection_free",
    "min_volume_ratio",
    "write_states",
]


def cpu_seconds(comm: MPI.Comm, start: float = 0.0) -> float:
    """Process CPU time since ``start`` summed over the ranks (the machine is shared)."""
    return collective_comm(comm).allreduce(time.process_time() - start, op=MPI.SUM)


class TrajectoryGrabber:
    """An optimiser stop condition that never stops; keeps the initial iterate's trajectory.

    ``minimize(..., stop_conditions=[grab])`` then ``grab.initial`` is the Trajectory of the
    initial parameters (no extra forward solve is needed for the "before" output).
    """

    def __init__(self):
        self.initial = None

    def __call__(self, record, optimizer) -> bool:
        """Keep the trajectory at iteration 0; never stop."""
        if record.iteration == 0 and self.initial is None:
            self.initial = optimizer.point.trajectory
        return False


def _p1_displacement(model, u: np.ndarray) -> np.ndarray:
    """Displacement at the local geometry nodes, shape (num nodes, dim)."""
    mesh = model.domain.mesh
    d = model.dim
    uf = fem.Function(model.V)
    uf.x.array[:] = u
    uf.x.scatter_forward()
    if model.degree != 1:
        P1 = fem.functionspace(mesh, ("Lagrange", 1, (d,)))
        u1 = fem.Function(P1)
        u1.interpolate(uf)
        uf = u1
    node_of_dof = np.empty(len(mesh.geometry.x), dtype=np.int64)
    nv = mesh.geometry.dofmaps[0].shape[1]
    node_of_dof[mesh.geometry.dofmaps[0].ravel()] = uf.function_space.dofmap.list[:, :nv].ravel()
    return uf.x.array.reshape(-1, d)[node_of_dof]


def min_volume_ratio(model, u: np.ndarray) -> float:
    """Smallest deformed/rest volume ratio of the (vertex-)deformed cells, over all ranks.

    A non-positive value means an inverted element. Linear elasticity has no inversion guard,
    so the demos check every state they report.
    """
    mesh = model.domain.mesh
    d = model.dim
    owned = mesh.topology.index_map(mesh.topology.dim).size_local
    x = mesh.geometry.x.copy()
    x[:, :d] += _p1_displacement(model, u)
    rest = signed_cell_volumes(mesh)[:owned]
    deformed = signed_cell_volumes(mesh, x)[:owned]
    local = float((deformed / rest).min()) if owned else np.inf
    return collective_comm(mesh.comm).allreduce(local, op=MPI.MIN)


def intersection_free(contact, trajectories) -> bool:
    """No state of the trajectories intersects (ipctk exact check on the collision surface)."""
    surf = contact.surface
    for traj in trajectories:
        for u in traj.u:
            x = np.asfortranarray(surf.rest_positions + surf.gather(u))
            if ipctk.has_intersections(surf.mesh, x):
                return False
    return True


def cell_values(model, name: str) -> np.ndarray:
    """Owned values of a scalar DG0 coefficient, in local cell order."""
    fn = model.coefficients[name]
    owned = model.domain.mesh.topology.index_map(model.dim).size_local
    cells = np.arange(owned, dtype=np.int32)
    return fn.x.array[fn.function_space.dofmap.list[cells, 0]]


def deformed_triangles(model, u: np.ndarray | None, values: np.ndarray | None = None):
    """Deformed triangles (n, 3, 2) of the owned cells with their values, gathered on all ranks.

    For plotting 2D meshes (``matplotlib.collections.PolyCollection``).
    """
    mesh = model.domain.mesh
    owned = mesh.topology.index_map(mesh.topology.dim).size_local
    x = mesh.geometry.x[:, :2].copy()
    if u is not None:
        x += _p1_displacement(model, u)
    tris = x[mesh.geometry.dofmaps[0][:owned, :3]]
    comm = mesh.comm
    tris = np.concatenate(collective_comm(comm).allgather(tris))
    if values is None:
        return tris, None
    return tris, np.concatenate(collective_comm(comm).allgather(np.asarray(values)))


def write_states(
    model,
    controls,
    states: dict,
    out: Path,
    name: str,
    xdmf: bool,
    fields: list[str],
) -> list[Path]:
    """Write each labelled state ``{label: (q, trajectory)}`` as a time series with its fields.

    The controls are assigned the state's parameters while writing (the material fields in
    ``fields`` are written as extra cellwise functions); the last state's parameters stay set.
    """
    suffix = ".xdmf" if xdmf else ".bp"
    extra = [model.coefficients[f] for f in fields]
    paths = []
    for label, (q, traj) in states.items():
        controls.assign(q)
        path = out / f"{name}_{label}{suffix}"
        with TrajectoryWriter(model, path, extra=extra) as writer:
            for t, u, v in zip(traj.times, traj.u, traj.v, strict=True):
                writer.write(t, u, v)
        paths.append(path)
    return paths


def center_of_mass_history(model, trajectory, body) -> np.ndarray:
    """Deformed centre of mass of a body at every state, shape (N + 1, dim), on all ranks."""
    f = model.fields
    rho = model.coefficients["density"]
    dx = f.dx(model.domain.body_id(body))
    comm = model.domain.comm
    mass = collective_comm(comm).allreduce(fem.assemble_scalar(fem.form(rho * dx)), op=MPI.SUM)
    moments = [fem.form(rho * (f.X[k] + f.u[k]) * dx) for k in range(model.dim)]
    saved = f.u.x.array.copy()
    out = []
    for u in trajectory.u:
        f.u.x.array[:] = u
        out.append(
            [
                collective_comm(comm).allreduce(fem.assemble_scalar(m), op=MPI.SUM) / mass
                for m in moments
            ]
        )
    f.u.x.array[:] = saved
    return np.array(out)


def body_cell_mask(model, layout, body) -> np.ndarray:
    """Canonical-order mask of the cells of ``body`` for a DG0 CanonicalLayout (all ranks)."""
    tags = model.domain.cell_tags
    marker = fem.Function(layout.V)
    marker.x.array[layout.V.dofmap.list[tags.indices, 0]] = tags.values
    return layout.gather(marker.x.array) == model.domain.body_id(body)
