"""Moving a control's parameters to a new mesh of the same bodies (after remeshing)."""

import numpy as np
from dolfinx import fem
from mpi4py import MPI

from diffsolids.parallel import collective_comm

__all__ = ["interpolate_nonmatching"]


def interpolate_nonmatching(src: fem.Function, dst: fem.Function) -> None:
    """Interpolate between functions on non-matching meshes covering the same domain.

    Collective on the destination mesh. Destination points outside the source mesh by less than
    1e-8 of the mesh extent (snapped boundary coordinates of a new mesh) still take values.
    """
    V = dst.function_space
    mesh = V.mesh
    tdim = mesh.topology.dim
    imap = mesh.topology.index_map(tdim)
    cells = np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32)
    x = mesh.geometry.x
    extent = np.ptp(x, axis=0) if len(x) else np.zeros(3)
    padding = 1e-8 * collective_comm(mesh.comm).allreduce(float(np.linalg.norm(extent)), op=MPI.MAX)
    data = fem.create_interpolation_data(V, src.function_space, cells, padding)
    dst.interpolate_nonmatching(src, cells, data)
    dst.x.scatter_forward()
