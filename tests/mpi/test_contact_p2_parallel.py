"""Run under ``mpiexec -n 2``: the subdivided P2/P3 collision surface and its contact on 2 ranks.

The surface built on COMM_WORLD equals the serial one (same nodes in the same order, same
sub-facets, rest positions, bodies), and the lifted block of test_contact_p2.py has on 2 ranks
the value, the shape and Young's-modulus gradient (canonical order) and the collision counts of
the serial run (under the lid and under a kinematic obstacle).
"""

import numpy as np
import pytest
from mpi4py import MPI
from parallel_checks import assert_world_equals_self, value_and_gradient
from test_contact_p2 import bulge_model, bulge_scene

from diffsolids.contact.geometry.surface import CollisionSurface
from diffsolids.controls import ParameterControl, ShapeControl
from diffsolids.reduced_functional import ReducedFunctional

RTOL = 1e-8


@pytest.mark.parametrize(("dim", "degree"), [(2, 2), (2, 3), (3, 2), (3, 3)])
def test_subdivided_surface_world_equals_self(dim, degree):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    surfaces = {}
    for c in (comm, MPI.COMM_SELF):
        model = bulge_model(dim, degree, comm=c)
        surf = CollisionSurface(model.domain, model.V, boundary="nodes")
        coords = np.ascontiguousarray(model.V.tabulate_dof_coordinates()[:, :dim]).ravel()
        gathered = surf.gather(coords)  # every node gathered from the rank that owns it
        assert np.abs(gathered - surf.rest_positions).max() < 1e-14
        surfaces[c.size > 1] = surf
    par, ser = surfaces[True], surfaces[False]
    assert par.subdivided and par.num_vertices == ser.num_vertices
    for name in ("rest_positions", "edges", "faces", "body", "primitive_body"):
        assert np.array_equal(getattr(par, name), getattr(ser, name)), name
    assert np.array_equal(par.current_rest_positions(), ser.rest_positions)
    owned = comm.allgather(len(par.displacement.cv))
    assert sum(owned) == par.num_body_vertices and min(owned) > 0


def _value_and_gradient(dim: int, obstacle: bool, comm):
    model, contact, sim, objective = bulge_scene(dim, 2, comm=comm, obstacle=obstacle)
    controls = [ShapeControl(model, "all"), ParameterControl(model, "E", "bodies", log=True)]
    result = value_and_gradient(ReducedFunctional(sim, objective, controls))
    return result, [r.num_collisions for r in contact.records]


@pytest.mark.parametrize(("dim", "obstacle"), [(2, False), (3, False), (2, True)])
def test_p2_contact_gradient_world_equals_self(dim, obstacle):
    comm = MPI.COMM_WORLD
    assert comm.size > 1, "run with mpiexec -n 2"
    world, counts_par = _value_and_gradient(dim, obstacle, comm)
    serial, counts_ser = _value_and_gradient(dim, obstacle, MPI.COMM_SELF)
    assert counts_par == counts_ser and min(counts_ser) > 0
    assert_world_equals_self(world, serial, RTOL)
