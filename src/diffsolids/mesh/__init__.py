"""Meshes with body (cell) and boundary (facet) tags: built-in boxes, gmsh and meshio files."""

from diffsolids.mesh.arrays import MeshArrays, boundary_facets, create_domain
from diffsolids.mesh.domain import Domain, create_box, create_rectangle, tag_facets
from diffsolids.mesh.gmsh_session import gmsh_session
from diffsolids.mesh.ordering import CanonicalLayout
from diffsolids.mesh.quality import (
    check_orientation,
    inverted_cells,
    min_scaled_jacobian,
    signed_cell_volumes,
)
from diffsolids.mesh.readers import (
    check_cells,
    check_points_and_cells,
    from_geo,
    from_gmsh_model,
    read_mesh,
    transform_domain,
)
from diffsolids.mesh.scene import combine_meshes, simplex_ball, simplex_box
from diffsolids.mesh.selections import (
    AxisPlaneSelection,
    BoxSelection,
    PlaneSelection,
    Selection,
    SphereSelection,
    select_facets,
)

__all__ = [
    "AxisPlaneSelection",
    "BoxSelection",
    "CanonicalLayout",
    "Domain",
    "MeshArrays",
    "PlaneSelection",
    "Selection",
    "SphereSelection",
    "boundary_facets",
    "check_cells",
    "check_orientation",
    "check_points_and_cells",
    "combine_meshes",
    "create_box",
    "create_domain",
    "create_rectangle",
    "from_geo",
    "from_gmsh_model",
    "gmsh_session",
    "inverted_cells",
    "min_scaled_jacobian",
    "read_mesh",
    "select_facets",
    "signed_cell_volumes",
    "simplex_ball",
    "simplex_box",
    "tag_facets",
    "transform_domain",
]
