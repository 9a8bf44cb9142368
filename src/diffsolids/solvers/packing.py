"""Coefficient packing shared by the forms of one state (numpy gathers, reused while unchanged).

DOLFINx packs every coefficient of a form anew at each assembly, one cell at a time; the
adjoint sweep assembles five to seven forms per step over the same few fields (u^i, its history
fields, lambda, the material fields), so most of that work repeats: in ``bench_gradient``'s
dynamic case (48 000 cells, P1) packing cost 55 ms per step against 60 ms of kernels. Here each
coefficient is gathered per cell once (``values[cell_dofs]``) and kept while its values are
unchanged (an exact comparison of the dof array, which is small next to the gathered one); each
form's packed array is filled from these gathers, a column block only when its gather is new.

Only layouts the gathers reproduce are handled: cell and exterior-facet integrals over the
form's own mesh with elements needing no DOF transformations. Each layout is checked once
against DOLFINx's own packing with distinct values in every coefficient (which also finds the
coefficients an integral does not use, left zero as DOLFINx does); any other form is left to
DOLFINx (:meth:`FormPacker.pack` returns None).
"""

import hashlib
from dataclasses import dataclass, field

import numpy as np
from dolfinx import fem

__all__ = ["CoefficientGathers", "FormPacker", "coefficient_layout"]

_SUPPORTED = (fem.IntegralType.cell, fem.IntegralType.exterior_facet)


# below this many dof values a gather's values are compared as bytes (0.4 us for 462 values
# against 3.1 us for np.array_equal's checks and temporaries); above it np.array_equal is faster
_BYTES_COMPARE_MAX = 16384


@dataclass
class _Gather:
    coefficient: object  # the C++ Function, kept alive with its id
    dofs: np.ndarray  # (num_entities, width) dof of each packed entry
    values: np.ndarray | bytes | None = None  # the dof values the gather was taken from
    gathered: np.ndarray | None = None


class CoefficientGathers:
    """Per-entity gathers of coefficient values, shared by the FormPackers made with it."""

    def __init__(self) -> None:
        self._gathers: dict[tuple[int, bytes], _Gather] = {}

    def entry(self, coefficient: object, dofs: np.ndarray) -> _Gather:
        """The gather of ``coefficient`` at ``dofs`` (made once per coefficient and dofs)."""
        key = (id(coefficient), hashlib.blake2b(dofs.tobytes(), digest_size=16).digest())
        gather = self._gathers.get(key)
        if gather is None:
            gather = self._gathers[key] = _Gather(coefficient, dofs)
        return gather

    @staticmethod
    def current(gather: _Gather) -> np.ndarray:
        """The gathered values, gathered again only if the coefficient's values changed.

        Values are compared exactly: as bytes (bit for bit) for small arrays, with
        ``np.array_equal`` for large ones.
        """
        values = gather.coefficient.x.array
        if values.size <= _BYTES_COMPARE_MAX:
            raw = values.tobytes()
            if raw != gather.values:
                gather.values = raw
                gather.gathered = values[gather.dofs]
        elif not isinstance(gather.values, np.ndarray) or not np.array_equal(values, gather.values):
            gather.values = values.copy()
            gather.gathered = values[gather.dofs]
        return gather.gathered


@dataclass
class _Block:
    gather: _Gather
    columns: slice
    last: np.ndarray | None = field(default=None)  # the gather copied in last


class FormPacker:
    """Packed coefficients of one form, filled from shared gathers.

    Args:
        form: The compiled form.
        gathers: The gathers shared with the other forms of the same fields.
    """

    def __init__(self, form: fem.Form, gathers: CoefficientGathers) -> None:
        self.form = form
        self._gathers = gathers
        self._blocks: dict[tuple, list[_Block]] | None = None
        self._packed: dict[tuple, np.ndarray] = {}
        layout = coefficient_layout(form)
        checked = None if layout is None else _checked(form, layout)
        if checked is not None:
            self._blocks = {
                key: [_Block(gathers.entry(c, dofs), cols) for c, cols, dofs in parts]
                for key, parts in checked.items()
            }
            self._packed = {
                key: np.zeros((parts[0][2].shape[0], parts[-1][1].stop))
                for key, parts in layout.items()
            }

    @property
    def supported(self) -> bool:
        """Whether the gathers pack this form (else DOLFINx does)."""
        return self._blocks is not None

    def pack(self) -> dict | None:
        """The packed coefficients for ``fem.assemble_vector`` (None: let DOLFINx pack)."""
        if self._blocks is None:
            return None
        for key, blocks in self._blocks.items():
            out = self._packed[key]
            for block in blocks:
                values = self._gathers.current(block.gather)
                if block.last is not values:
                    out[:, block.columns] = values
                    block.last = values
        return self._packed


def _entities(cpp: object, kind: fem.IntegralType, i: int) -> np.ndarray:
    """The cell of each entity of integral i (a facet's cell for exterior facets)."""
    domains = np.asarray(cpp.domains(kind, i))
    if kind == fem.IntegralType.exterior_facet:
        return domains.reshape(-1, 2)[:, 0]
    return domains


def _coefficient_dofs(coefficient: object, cells: np.ndarray) -> np.ndarray | None:
    V = coefficient.function_space
    if V.element.needs_dof_transformations:
        return None
    bs = V.dofmap.index_map_bs
    cell_dofs = np.asarray(V.dofmap.map())
    if cell_dofs.shape[1] * bs != V.element.space_dimension:
        return None
    dofs = cell_dofs[cells][:, :, None] * bs + np.arange(bs)
    return dofs.reshape(len(cells), V.element.space_dimension)


def coefficient_layout(form: fem.Form) -> dict[tuple, list] | None:
    """Per packed key, (coefficient, columns, dofs) of each coefficient; None if unsupported.

    ``columns`` are the coefficient's columns in DOLFINx's packed array of that integral and
    ``dofs`` (num_entities, width) the dof of each entry, for cell and exterior-facet integrals
    over the form's mesh with elements needing no DOF transformations.
    """
    cpp = form._cpp_object
    if not cpp.coefficients or any(k not in _SUPPORTED for k in cpp.integral_types):
        return None
    if any(c.function_space.mesh is not cpp.mesh for c in cpp.coefficients):
        return None
    layout = {}
    for kind in cpp.integral_types:
        for i in range(cpp.num_integrals(kind, 0)):
            cells = _entities(cpp, kind, i)
            parts, start = [], 0
            for c in cpp.coefficients:
                dofs = _coefficient_dofs(c, cells)
                if dofs is None:
                    return None
                parts.append((c, slice(start, start + dofs.shape[1]), dofs))
                start += dofs.shape[1]
            layout[(kind, i)] = parts
    return layout


def _checked(form: fem.Form, layout: dict[tuple, list]) -> dict[tuple, list] | None:
    """The layout's blocks DOLFINx fills, checked with distinct values in every coefficient.

    DOLFINx packs, per integral, only the coefficients that integral uses (the others' columns
    stay zero): those blocks are dropped. None if any other block differs from DOLFINx's.
    """
    coefficients = form._cpp_object.coefficients
    saved = [c.x.array.copy() for c in coefficients]
    try:
        start = 0
        for c in coefficients:
            n = c.x.array.size
            c.x.array[:] = 1.0 + start + np.arange(n)  # nonzero, distinct across coefficients
            start += n
        reference = fem.pack_coefficients(form)
        if set(reference) != set(layout):
            return None
        checked = {}
        for key, parts in layout.items():
            ref = reference[key]
            if ref.shape != (parts[0][2].shape[0], parts[-1][1].stop):
                return None
            checked[key] = []
            for c, columns, dofs in parts:
                if np.array_equal(ref[:, columns], c.x.array[dofs]):
                    checked[key].append((c, columns, dofs))
                elif np.any(ref[:, columns]):
                    return None
        return checked
    finally:
        for c, values in zip(coefficients, saved, strict=True):
            c.x.array[:] = values
