"""Time series output readable in ParaView: displacement, velocity and von Mises stress."""

import os
from pathlib import Path

import numpy as np
from dolfinx import fem, io

from diffsolids import forms
from diffsolids.model.terms import ElasticEnergy

__all__ = ["TrajectoryWriter", "von_mises_field"]


class _VonMises:
    """Cellwise (DG0) von Mises stress of the current displacement."""

    def __init__(self, model, u: fem.Function):
        mesh = model.domain.mesh
        self.field = fem.Function(fem.functionspace(mesh, ("DG", 0)), name="von_mises")
        midpoint = mesh.basix_cell()
        import basix

        points = basix.geometry(midpoint).mean(axis=0)[None, :]
        self.parts = []
        for term in model.terms:
            if isinstance(term, ElasticEnergy):
                lmbda, mu = model.lame()
                sigma = forms.cauchy_stress(term.law, u, lmbda, mu)
                expr = fem.Expression(forms.von_mises(sigma), points)
                if term.bodies is None:
                    cells = None
                else:
                    cells = np.concatenate([model.domain.cells_of(b) for b in term.bodies])
                self.parts.append((expr, cells))

    def update(self) -> fem.Function:
        for expr, cells in self.parts:
            if cells is None:
                self.field.interpolate(expr)
            else:
                self.field.interpolate(expr, cells0=cells.astype(np.int32))
        return self.field


def von_mises_field(model, u_array: np.ndarray) -> fem.Function:
    """DG0 von Mises stress of a displacement array."""
    u = fem.Function(model.V)
    u.x.array[:] = u_array
    return _VonMises(model, u).update()


class TrajectoryWriter:
    """Writes u, v and von Mises stress per step to VTX (``.bp``) or XDMF (``.xdmf``).

    Args:
        model: The model whose fields are written.
        path: Output path; the suffix selects the format.
        extra: Further functions to write (VTX: same element as u or DG0; XDMF: P1/DG0).
    """

    def __init__(self, model, path: str | os.PathLike, extra: list[fem.Function] | None = None):
        self.path = Path(path)
        mesh = model.domain.mesh
        comm = mesh.comm
        if comm.rank == 0:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        comm.barrier()
        self.u = fem.Function(model.V, name="displacement")
        self.v = fem.Function(model.V, name="velocity")
        self.stress = _VonMises(model, self.u)
        self.extra = list(extra or [])
        if self.path.suffix == ".bp":
            self._xdmf = None
            self._vtx = io.VTXWriter(comm, self.path, [self.u, self.v])
            self._vtx_cell = io.VTXWriter(
                comm, self.path.with_name(self.path.stem + "_cells.bp"), [self.stress.field]
            )
        elif self.path.suffix == ".xdmf":
            self._vtx = None
            self._xdmf = io.XDMFFile(comm, self.path, "w")
            self._xdmf.write_mesh(mesh)
            P1 = fem.functionspace(mesh, ("Lagrange", 1, (mesh.geometry.dim,)))
            self._u1 = fem.Function(P1, name="displacement")
            self._v1 = fem.Function(P1, name="velocity")
        else:
            raise ValueError(f"output path {path} must end in .bp (VTX) or .xdmf")

    def write(self, t: float, u: np.ndarray, v: np.ndarray) -> None:
        """Write the state at time ``t``."""
        self.u.x.array[:] = u
        self.v.x.array[:] = v
        self.stress.update()
        if self._vtx is not None:
            self._vtx.write(t)
            self._vtx_cell.write(t)
            return
        self._u1.interpolate(self.u)
        self._v1.interpolate(self.v)
        for f in (self._u1, self._v1, self.stress.field, *self.extra):
            self._xdmf.write_function(f, t)

    def close(self) -> None:
        """Flush and close the files."""
        if self._vtx is not None:
            self._vtx.close()
            self._vtx_cell.close()
        else:
            self._xdmf.close()
