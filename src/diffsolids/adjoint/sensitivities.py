"""What the adjoint computes: partial sensitivities of J to everything controls can move."""

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Sensitivities", "Targets"]


@dataclass(frozen=True)
class Targets:
    """The sensitivities a set of controls needs (only these are assembled).

    Attributes:
        shape: dJ/dX on the P1 vector space of the mesh.
        coefficients: Names of model coefficients (material fields, loads, ...).
        initial: dJ/du^0 and dJ/dv^0.
        dirichlet: dJ/d(prescribed values) per step.
        contact: Names of contact parameters (e.g. "friction").
    """

    shape: bool = False
    coefficients: frozenset[str] = frozenset()
    initial: bool = False
    dirichlet: bool = False
    contact: frozenset[str] = frozenset()

    def __or__(self, other: "Targets") -> "Targets":
        return Targets(
            self.shape or other.shape,
            self.coefficients | other.coefficients,
            self.initial or other.initial,
            self.dirichlet or other.dirichlet,
            self.contact | other.contact,
        )


@dataclass
class Sensitivities:
    """Partial derivatives of J (local arrays; entries of owned dofs are complete).

    Attributes:
        shape: dJ/dX over the dofs of the mesh's P1 vector space.
        coefficients: dJ/dc over the dofs of each requested coefficient's space.
        u0: dJ/du^0 (V layout).
        v0: dJ/dv^0 (V layout).
        dirichlet: dJ/du^i at Dirichlet dofs for i = 0..N (V layout; other entries meaningless).
        contact: Contact parameter sensitivities (global arrays, identical on all ranks).
    """

    shape: np.ndarray | None = None
    coefficients: dict[str, np.ndarray] = field(default_factory=dict)
    u0: np.ndarray | None = None
    v0: np.ndarray | None = None
    dirichlet: list[np.ndarray] = field(default_factory=list)
    contact: dict[str, np.ndarray] = field(default_factory=dict)
