"""Constitutive laws and their parameters (per body), with validation."""

import math
from dataclasses import dataclass

from diffsolids.errors import ParameterError
from diffsolids.forms.elasticity import StrainEnergy, strain_law

__all__ = ["LinearElastic", "Material", "NeoHookean", "StVenantKirchhoff"]


@dataclass(frozen=True)
class Material:
    """Material of one body: a strain energy with elastic, inertial and damping parameters.

    Give the elastic parameters either as Young's modulus and Poisson's ratio (``E``, ``nu``) or
    as Lamé parameters (``lmbda``, ``mu``).

    Attributes:
        law: The constitutive law: a ``forms.StrainEnergy`` (any subclass), or the name of a
            built-in one ("linear", "st_venant_kirchhoff", "neo_hookean"), stored as the law.
        E: Young's modulus.
        nu: Poisson's ratio.
        lmbda: First Lamé parameter.
        mu: Shear modulus.
        density: Mass density (> 0).
        damping_psi: Shear viscous damping psi >= 0 (paper sec. 8.1).
        damping_phi: Bulk viscous damping phi >= 0.
    """

    law: StrainEnergy | str
    E: float | None = None
    nu: float | None = None
    lmbda: float | None = None
    mu: float | None = None
    density: float = 1.0
    damping_psi: float = 0.0
    damping_phi: float = 0.0

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "law", strain_law(self.law))
        except KeyError as error:
            raise ParameterError(error.args[0]) from None
        young = self.E is not None or self.nu is not None
        lame = self.lmbda is not None or self.mu is not None
        if (
            young == lame
            or (young and None in (self.E, self.nu))
            or (lame and None in (self.lmbda, self.mu))
        ):
            raise ParameterError(
                "give the elastic parameters either as (E, nu) or as (lmbda, mu), both of a pair"
            )
        for name in ("E", "nu", "lmbda", "mu", "density", "damping_psi", "damping_phi"):
            value = getattr(self, name)
            if value is not None and not math.isfinite(float(value)):
                raise ParameterError(f"material parameter {name} = {value} is not finite")
        if young and self.E <= 0:
            raise ParameterError(f"Young's modulus E = {self.E} must be positive")
        if lame and self.mu <= 0:
            raise ParameterError(f"shear modulus mu = {self.mu} must be positive")
        if self.density <= 0:
            raise ParameterError(f"density = {self.density} must be positive")
        if self.damping_psi < 0 or self.damping_phi < 0:
            raise ParameterError(
                f"damping parameters psi = {self.damping_psi}, phi = {self.damping_phi} "
                "must be non-negative"
            )

    @property
    def parametrisation(self) -> tuple[str, str]:
        """("E", "nu") or ("lmbda", "mu")."""
        return ("E", "nu") if self.E is not None else ("lmbda", "mu")

    def validate_for(self, dim: int, plane_stress: bool) -> None:
        """Check the Poisson ratio / bulk modulus range for the dimension and plane model.

        Raises:
            ParameterError: nu outside (-1, 1/2) (3D, plane strain) or (-1, 1) (plane stress), or
                a non-positive bulk modulus for Lamé input.
        """
        if self.nu is not None:
            upper = 1.0 if (dim == 2 and plane_stress) else 0.5
            if not -1.0 < self.nu < upper:
                model = "plane stress" if (dim == 2 and plane_stress) else f"{dim}D/plane strain"
                raise ParameterError(
                    f"Poisson's ratio nu = {self.nu} is outside the physical range (-1, {upper}) "
                    f"for {model}"
                )
        else:
            bulk = self.lmbda + 2.0 * self.mu / dim
            if bulk <= 0:
                raise ParameterError(
                    f"lmbda = {self.lmbda}, mu = {self.mu} give a non-positive bulk modulus "
                    f"lmbda + 2 mu / {dim} = {bulk}"
                )


def LinearElastic(**params) -> Material:
    """Small-strain linear elasticity."""
    return Material("linear", **params)


def StVenantKirchhoff(**params) -> Material:
    """St. Venant-Kirchhoff hyperelasticity."""
    return Material("st_venant_kirchhoff", **params)


def NeoHookean(**params) -> Material:
    """Compressible Neo-Hookean hyperelasticity."""
    return Material("neo_hookean", **params)
