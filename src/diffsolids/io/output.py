"""Time series output readable in ParaView: displacement, velocity and von Mises stress."""

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import dolfinx.mesh
import numpy as np
from dolfinx import fem, io
from mpi4py import MPI

from diffsolids import forms
from diffsolids.errors import ParameterError
from diffsolids.forms.elasticity import plane_strain_normal_stress
from diffsolids.model.terms import ElasticEnergy
from diffsolids.solvers.forms import compile_expression

if TYPE_CHECKING:
    from diffsolids.model import Model
    from diffsolids.states import Trajectory

__all__ = ["TrajectoryWriter", "at_rest_geometry", "von_mises_field", "write_trajectory"]


class _VonMises:
    """Cellwise (DG0) von Mises stress of the current displacement."""

    def __init__(self, model: "Model", u: fem.Function) -> None:
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
                sigma_zz = 0.0
                if model.dim == 2 and not model.plane_stress:
                    sigma_zz = plane_strain_normal_stress(term.law, u, lmbda, mu)
                expr = compile_expression(forms.von_mises(sigma, sigma_zz), points)
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


def von_mises_field(model: "Model", u_array: np.ndarray) -> fem.Function:
    """DG0 von Mises stress of a displacement array."""
    u = fem.Function(model.V)
    u.x.array[:] = u_array
    return _VonMises(model, u).update()


def _element_key(f: fem.Function) -> tuple:
    """(family, degree, discontinuous) of a function's (scalar) element."""
    e = f.function_space.ufl_element().basix_element
    return (e.family, e.degree, e.discontinuous)


def _key_label(key: tuple) -> str:
    _, degree, discontinuous = key
    return f"{'dg' if discontinuous else 'p'}{degree}"


class TrajectoryWriter:
    """Writes u, v and von Mises stress per step to VTX (``.bp``) or XDMF (``.xdmf``).

    VTX keeps the displacement's own element (P1, P2, P3): ``<name>.bp`` holds displacement and
    velocity, ``<name>_cells.bp`` the cellwise (DG0) von Mises stress. XDMF (``<name>.xdmf`` with
    ``<name>.h5``) stores everything on the mesh vertices: P2/P3 fields are interpolated into P1.

    Args:
        model: The model whose fields are written.
        path: Output path; the suffix selects the format.
        extra: Further functions written with their current values at every step. VTX: Lagrange
            or DG of any degree (extra files ``<name>_<p2|dg1|...>.bp`` for elements other than
            the displacement's and DG0); XDMF: interpolated into P1 unless P1 or DG0.

    Attributes:
        files: The files (VTX folders, XDMF and HDF5 files) the writer writes.

    Raises:
        ParameterError: A suffix other than .bp/.xdmf, an extra function on another mesh, of a
            non-Lagrange family (VTX), or with a name already used.
    """

    def __init__(
        self, model: "Model", path: str | os.PathLike, extra: list[fem.Function] | None = None
    ) -> None:
        self.path = Path(path)
        if self.path.suffix not in (".bp", ".xdmf"):
            raise ParameterError(f"output path {path} must end in .bp (VTX) or .xdmf (XDMF)")
        mesh = model.domain.mesh
        comm = mesh.comm
        self.extra = list(extra or [])
        names = ["displacement", "velocity", "von_mises", *(f.name for f in self.extra)]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ParameterError(f"output functions need distinct names; repeated: {duplicates}")
        for f in self.extra:
            if f.function_space.mesh is not mesh:
                raise ParameterError(f"extra output function {f.name!r} is on another mesh")
        if comm.rank == 0:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        comm.barrier()
        self.u = fem.Function(model.V, name="displacement")
        self.v = fem.Function(model.V, name="velocity")
        self.stress = _VonMises(model, self.u)
        self._closed = False
        self.files: list[Path] = []
        if self.path.suffix == ".bp":
            self._open_vtx(comm)
        else:
            self._open_xdmf(mesh)

    def _open_vtx(self, comm: MPI.Comm) -> None:
        lagrange = _element_key(self.u)[0]
        groups: dict[tuple, list[fem.Function]] = {
            _element_key(self.u): [self.u, self.v],
            _element_key(self.stress.field): [self.stress.field],
        }
        for f in self.extra:
            key = _element_key(f)
            if key[0] != lagrange:
                raise ParameterError(
                    f"VTX output needs Lagrange/DG functions; {f.name!r} has family {key[0]}"
                )
            groups.setdefault(key, []).append(f)
        self._xdmf = None
        self._vtx = []
        for key, functions in groups.items():
            if functions[0] is self.u:
                path = self.path
            elif functions[0] is self.stress.field:
                path = self.path.with_name(self.path.stem + "_cells.bp")
            else:
                path = self.path.with_name(f"{self.path.stem}_{_key_label(key)}.bp")
            self._vtx.append(io.VTXWriter(comm, path, functions))
            self.files.append(path)

    def _open_xdmf(self, mesh: dolfinx.mesh.Mesh) -> None:
        self._vtx = []
        self._xdmf = io.XDMFFile(mesh.comm, self.path, "w")
        self.files += [self.path, self.path.with_suffix(".h5")]
        self._xdmf.write_mesh(mesh)
        vertex_keys = {_element_key(self.stress.field)}  # DG0
        self._xdmf_pairs = []  # (source, function written: source itself or its P1 copy)
        for f in (self.u, self.v, self.stress.field, *self.extra):
            key = _element_key(f)
            if key in vertex_keys or (key[1] == 1 and not key[2]):
                self._xdmf_pairs.append((f, f))
                continue
            shape = f.function_space.value_shape
            P1 = fem.functionspace(mesh, ("Lagrange", 1, shape) if shape else ("Lagrange", 1))
            self._xdmf_pairs.append((f, fem.Function(P1, name=f.name)))

    def write(self, t: float, u: np.ndarray, v: np.ndarray) -> None:
        """Write the state at time ``t`` (``u``, ``v``: local arrays including ghosts)."""
        if self._closed:
            raise ParameterError(f"{self.path} is closed")
        self.u.x.array[:] = u
        self.v.x.array[:] = v
        self.u.x.scatter_forward()
        self.v.x.scatter_forward()
        self.stress.update()
        for writer in self._vtx:
            writer.write(t)
        if self._xdmf is not None:
            for source, target in self._xdmf_pairs:
                if target is not source:
                    target.interpolate(source)
                self._xdmf.write_function(target, t)

    def close(self) -> None:
        """Flush and close the files (a second call does nothing)."""
        if self._closed:
            return
        self._closed = True
        for writer in self._vtx:
            writer.close()
        if self._xdmf is not None:
            self._xdmf.close()

    def __enter__(self) -> "TrajectoryWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_trajectory(
    model: "Model",
    trajectory: "Trajectory",
    path: str | os.PathLike,
    extra: list[fem.Function] | None = None,
) -> list[Path]:
    """Write every state of a trajectory (u, v, von Mises stress) with a :class:`TrajectoryWriter`.

    Args:
        model: The model of the trajectory.
        trajectory: The Trajectory (its times, u and v).
        path: Output path ending in ``.bp`` (VTX) or ``.xdmf``.
        extra: Further functions written with their current values at every state.

    Returns:
        The files written (``TrajectoryWriter.files``).
    """
    with at_rest_geometry(model, trajectory), TrajectoryWriter(model, path, extra) as writer:
        for t, u, v in zip(trajectory.times, trajectory.u, trajectory.v, strict=True):
            writer.write(t, u, v)
    return list(writer.files)


@contextlib.contextmanager
def at_rest_geometry(model: "Model", trajectory: "Trajectory") -> Iterator[None]:
    """The model's mesh at the trajectory's own rest geometry for the block, then back.

    A trajectory computed before a shape change is written (and its stresses evaluated) on the
    rest shape it was computed on, not on the mesh's current one.

    Raises:
        ParameterError: The trajectory was computed on another mesh (a different node count).
    """
    rest = trajectory.rest_geometry
    x = model.domain.mesh.geometry.x
    if rest is None:
        yield
        return
    if rest.shape != x.shape:
        raise ParameterError(
            f"the trajectory was computed on another mesh ({rest.shape[0]} geometry nodes on "
            f"this rank, the model's mesh has {x.shape[0]}); write it with the model it "
            "belongs to"
        )
    current = x.copy()
    x[:] = rest
    try:
        yield
    finally:
        x[:] = current
