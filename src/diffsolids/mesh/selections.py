"""Boundary selections as PolyFEM defines them: a facet is selected by its barycentre.

``diffsolids.mesh.tag_facets`` with a plain marker tests every vertex of a facet (DOLFINx's
``locate_entities_boundary``); PolyFEM tests the facet's barycentre, so a box that cuts through
a facet selects it in PolyFEM but not vertex-wise. :func:`select_facets` applies the selections
below to barycentres, which makes loaded lengths and areas equal to PolyFEM's. Selections with
``relative=True`` give coordinates as fractions of the mesh's bounding box (as in PolyFEM).
"""

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import dolfinx
import numpy as np

from diffsolids.errors import ParameterError
from diffsolids.mesh.domain import Domain

__all__ = [
    "AxisPlaneSelection",
    "BoxSelection",
    "PlaneSelection",
    "Selection",
    "SphereSelection",
    "select_facets",
]


class Selection:
    """A region of space; ``inside(points, bbox)`` tells which of the (n, dim) points it holds."""

    def inside(self, points: np.ndarray, bbox: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """Boolean mask of the points in the region (``bbox``: the mesh's (min, max) corners)."""
        raise NotImplementedError


def _relative(
    value: float | Sequence[float], bbox: tuple[np.ndarray, np.ndarray], relative: bool
) -> np.ndarray:
    value = np.asarray(value, dtype=float)
    return bbox[0] + (bbox[1] - bbox[0]) * value if relative else value


@dataclass(frozen=True)
class BoxSelection(Selection):
    """Points with ``lo <= p <= hi`` componentwise (PolyFEM ``box``)."""

    lo: Sequence[float]
    hi: Sequence[float]
    relative: bool = False

    def inside(  # noqa: D102
        self, points: np.ndarray, bbox: tuple[np.ndarray, np.ndarray]
    ) -> np.ndarray:
        lo, hi = _relative(self.lo, bbox, self.relative), _relative(self.hi, bbox, self.relative)
        return np.all((points >= lo) & (points <= hi), axis=1)


@dataclass(frozen=True)
class AxisPlaneSelection(Selection):
    """``p[k-1] >= position`` for ``axis = +k``, ``p[k-1] <= position`` for ``axis = -k``.

    PolyFEM's ``axis``/``position`` selection; ``axis`` is +-1, +-2, +-3 or ``"x"``, ``"-y"``, ...
    """

    axis: int | str
    position: float
    relative: bool = False

    def _signed_axis(self) -> int:
        if isinstance(self.axis, str):
            sign = -1 if self.axis.startswith("-") else 1
            return sign * (" xyz".index(self.axis[-1].lower()))
        if int(self.axis) not in (-3, -2, -1, 1, 2, 3):
            raise ParameterError(f"axis {self.axis} must be +-1, +-2 or +-3")
        return int(self.axis)

    def inside(  # noqa: D102
        self, points: np.ndarray, bbox: tuple[np.ndarray, np.ndarray]
    ) -> np.ndarray:
        axis = self._signed_axis()
        k = abs(axis) - 1
        if k >= points.shape[1]:
            raise ParameterError(f"axis {self.axis} of a {points.shape[1]}D mesh")
        pos = self.position
        if self.relative:
            pos = bbox[0][k] + (bbox[1][k] - bbox[0][k]) * pos
        return points[:, k] >= pos if axis > 0 else points[:, k] <= pos


@dataclass(frozen=True)
class PlaneSelection(Selection):
    """Points on the side of the plane through ``point`` that ``normal`` points to (inclusive)."""

    normal: Sequence[float]
    point: Sequence[float]
    relative: bool = False

    def inside(  # noqa: D102
        self, points: np.ndarray, bbox: tuple[np.ndarray, np.ndarray]
    ) -> np.ndarray:
        n = np.asarray(self.normal, dtype=float)
        return (points - _relative(self.point, bbox, self.relative)) @ (n / np.linalg.norm(n)) >= 0


@dataclass(frozen=True)
class SphereSelection(Selection):
    """Points with ``|p - center|^2 <= radius^2`` (relative: radius scales with the diagonal)."""

    center: Sequence[float]
    radius: float
    relative: bool = False

    def inside(  # noqa: D102
        self, points: np.ndarray, bbox: tuple[np.ndarray, np.ndarray]
    ) -> np.ndarray:
        c = _relative(self.center, bbox, self.relative)
        r = self.radius * (np.linalg.norm(bbox[1] - bbox[0]) if self.relative else 1.0)
        return np.sum((points - c) ** 2, axis=1) <= r**2


def select_facets(
    domain: Domain, selections: Mapping[int, Selection], names: Mapping[str, int] | None = None
) -> Domain:
    """A Domain whose boundary facets are tagged by the selections their barycentres fall in.

    Args:
        domain: The Domain (its existing facet tags are replaced).
        selections: ``{tag: selection}``; where several hold a facet, the later one wins.
        names: Names of the new tags (added to the domain's names).

    Raises:
        ParameterError: A tag that is not a positive integer.
    """
    mesh = domain.mesh
    fdim = mesh.topology.dim - 1
    mesh.topology.create_connectivity(fdim, fdim + 1)
    boundary = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    centres = dolfinx.mesh.compute_midpoints(mesh, fdim, boundary)[:, : domain.dim]
    bbox = domain.bounding_box()
    values = np.zeros(len(boundary), dtype=np.int32)
    for tag, selection in selections.items():
        if int(tag) != tag or tag <= 0:
            raise ParameterError(f"facet tag {tag} must be a positive integer")
        values[selection.inside(centres, bbox)] = tag
    keep = values > 0
    tags = dolfinx.mesh.meshtags(mesh, fdim, boundary[keep].astype(np.int32), values[keep])
    return Domain(mesh, domain.cell_tags, tags, {**domain.names, **dict(names or {})})
