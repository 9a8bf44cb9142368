"""Per-pair friction coefficients: the fast paths of ``tangential_collisions`` are exact.

``friction_table.tangential_collisions`` builds ipctk's TangentialCollisions with one
coefficient (ipctk's scalar build) when every pair of bodies has the same one, and through a
blend callback over the body labels otherwise. Both are compared with the reference they
replace (the callback indexing the numpy table), collision by collision and through the
friction force, on the two stacked boxes of test_contact_kernels (two bodies, 3D, friction
sliding branch).
"""

import ipctk
import numpy as np
import pytest
from mpi4py import MPI
from test_contact_kernels import _scene

from diffsolids.contact.energy.friction_table import tangential_collisions


def _reference(surface, x, collisions, barrier, mu_table) -> ipctk.TangentialCollisions:
    T = ipctk.TangentialCollisions()
    labels = surface.body_index.astype(float)

    def blend(a: float, b: float) -> float:
        return float(mu_table[round(a), round(b)])

    T.build(surface.mesh, np.asfortranarray(x), collisions, barrier, labels, labels, blend)
    return T


def _coefficients(T: ipctk.TangentialCollisions) -> np.ndarray:
    groups = (T.vv_collisions, T.ev_collisions, T.ee_collisions, T.fv_collisions)
    return np.array([(c.mu_s, c.mu_k) for g in groups for c in g])


def _force(contact, T, x: np.ndarray, lagged: np.ndarray) -> np.ndarray:
    mesh = contact.surface.mesh
    potential = ipctk.FrictionPotential(0.5)
    return potential.gradient(T, mesh, x - mesh.rest_positions - lagged)


@pytest.mark.parametrize("table", ["uniform", "zero", "per pair"])
def test_tangential_collisions_equal_the_reference(table):
    _, contact, *_ = _scene(3, 1, 1, 0.5, comm=MPI.COMM_SELF)
    surface = contact.surface
    x, C = contact.lagging.lagged_state()
    bodies = int(surface.body_index.max()) + 1
    assert bodies == 2
    mu = {"uniform": np.full((2, 2), 0.4), "zero": np.zeros((2, 2))}.get(
        table, np.array([[0.1, 0.7], [0.7, 0.3]])
    )
    T = tangential_collisions(surface, x, C, contact.barrier, mu)
    R = _reference(surface, x, C, contact.barrier, mu)
    assert len(T) == len(R) > 0
    mine, ref = _coefficients(T), _coefficients(R)
    assert np.array_equal(mine, ref)
    if table == "per pair":  # the boxes touch each other only: the pair's own coefficient
        assert set(mine.ravel()) == {0.7}
    lagged = x - surface.mesh.rest_positions
    xs = x + 1e-3 * np.random.default_rng(0).standard_normal(x.shape)
    # equal coefficients: the forces differ only in ipctk's (threaded) summation order
    mine, ref = _force(contact, T, xs, lagged), _force(contact, R, xs, lagged)
    assert np.abs(mine - ref).max() <= 1e-13 * np.abs(ref).max()
    assert np.abs(ref).max() > 0 or table == "zero"
