"""Run under ``mpiexec -n 2``: the paper's untagged meshes and transforms read on 2 ranks."""

from test_mesh_input import (  # noqa: F401 - collected here to run on 2 ranks
    test_a_box_selects_facets_by_barycentre_where_vertex_markers_do_not,
    test_create_domain_3d_matches_a_dolfinx_box,
    test_create_domain_from_arrays_tags_the_boundary_by_default,
    test_create_domain_refuses_bad_arrays,
    test_later_selections_win_and_bad_tags_are_refused,
    test_paper_meshes_without_physical_groups,
    test_selections_follow_polyfem,
    test_transform_on_loading_is_scale_then_rotation_then_translation,
    test_unreadable_and_surface_files_name_the_file_and_the_problem,
    test_untagged_msh_facets_are_tagged_one_and_blocks_are_bodies,
)
