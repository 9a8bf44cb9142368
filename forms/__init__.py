"""UFL form library (installed as ``diffsolids.forms``).

Pure UFL: functions of UFL objects that return UFL expressions. No PETSc, no solver state. Every
physical term of an incremental potential and every objective integrand lives here, so that the
shape, state and parameter derivatives all come from ``ufl.derivative``.
"""

from diffsolids.forms.damping import (
    damping_density,
    damping_potential,
    damping_stresses,
    green_strain_rate,
)
from diffsolids.forms.elasticity import (
    STRAIN_ENERGIES,
    LinearElasticEnergy,
    NeoHookeanEnergy,
    StrainEnergy,
    StVenantKirchhoffEnergy,
    cauchy_stress,
    first_piola_kirchhoff,
    lame_parameters,
    linear_energy,
    neo_hookean_energy,
    plane_strain_normal_stress,
    st_venant_kirchhoff_energy,
    strain_energy,
    strain_law,
    von_mises,
    von_mises_tensor,
)
from diffsolids.forms.inertia import inertia_energy
from diffsolids.forms.kinematics import deformation_gradient, green_strain, small_strain
from diffsolids.forms.loads import body_force_potential, traction_potential
from diffsolids.forms.objectives import (
    deformed_position,
    graph_misfit,
    log_barrier,
    penalty,
    stress_norm,
    stress_norm_power,
    stress_penalty,
    weighted_squared_distance,
)
from diffsolids.forms.shape_partials import (
    energy_momentum_tensor,
    form_shape_partial,
    is_transformable,
    residual_shape_partial,
    surface_residual_shape_partial,
)

__all__ = [
    "STRAIN_ENERGIES",
    "LinearElasticEnergy",
    "NeoHookeanEnergy",
    "StVenantKirchhoffEnergy",
    "StrainEnergy",
    "body_force_potential",
    "cauchy_stress",
    "damping_density",
    "damping_potential",
    "damping_stresses",
    "deformation_gradient",
    "deformed_position",
    "energy_momentum_tensor",
    "first_piola_kirchhoff",
    "form_shape_partial",
    "graph_misfit",
    "green_strain",
    "green_strain_rate",
    "inertia_energy",
    "is_transformable",
    "lame_parameters",
    "linear_energy",
    "log_barrier",
    "neo_hookean_energy",
    "penalty",
    "plane_strain_normal_stress",
    "residual_shape_partial",
    "small_strain",
    "st_venant_kirchhoff_energy",
    "strain_energy",
    "strain_law",
    "stress_norm",
    "stress_norm_power",
    "stress_penalty",
    "surface_residual_shape_partial",
    "traction_potential",
    "von_mises",
    "von_mises_tensor",
    "weighted_squared_distance",
]
