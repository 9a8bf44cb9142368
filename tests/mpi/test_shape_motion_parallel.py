"""Run under ``mpiexec -n 2``: mesh motion, Riesz map and remeshing equal their serial runs.

Each test builds the same problem on COMM_WORLD and on COMM_SELF in the same process; all
parameter vectors are in the canonical (partition-independent) order, so they must agree.
"""

import numpy as np
import pytest
from mpi4py import MPI
from test_remesh import BOTTOM, block_domain, build_block

from diffsolids.mesh import Domain
from diffsolids.optimize.mesh_motion import MeshMotion
from diffsolids.optimize.remesh import Remesher, gather_mesh
from diffsolids.reduced_functional import ReducedFunctional

WORLD, SELF = MPI.COMM_WORLD, MPI.COMM_SELF
KEYS = ("points", "cells", "cell_values", "facets", "facet_values")


def _build_block(domain: Domain) -> ReducedFunctional:
    return build_block(domain, displacement_weight=1e-2)


def _agree(a, b, rtol) -> bool:
    """Same verdict on every rank (a failing rank must not leave the other in a collective)."""
    ok = a is None or b is None or np.allclose(a, b, rtol=rtol, atol=rtol * np.abs(b).max())
    return bool(WORLD.allreduce(ok, op=MPI.LAND))


@pytest.mark.parametrize("extension", ["elasticity", "harmonic"])
def test_mesh_motion_and_riesz_map_match_serial(extension):
    rng = np.random.default_rng(11)
    out = {}
    for name, comm in (("world", WORLD), ("self", SELF)):
        P = MeshMotion(block_domain(comm), "boundary", exclude_facets=[BOTTOM], extension=extension)
        q = rng.standard_normal(P.shape[1]) if name == "world" else out["q"]
        g = rng.standard_normal(P.shape[0]) if name == "world" else out["g"]
        if name == "world":
            q, g = WORLD.bcast((q, g), root=0)
            out["q"], out["g"] = q, g
        out[name] = (P @ q, P.T @ g, P.riesz_map()(g[: P.shape[1]]))
    for a, b in zip(out["world"], out["self"], strict=True):
        assert _agree(a, b, 1e-12)


def test_mesh_motion_gradient_matches_serial():
    results = []
    for comm in (WORLD, SELF):
        rf = _build_block(block_domain(comm))
        q = 0.02 * np.cos(np.arange(rf.size))
        J, g = rf.value_and_gradient(q)
        results.append((np.array([J]), g))
    for a, b in zip(*results, strict=True):
        assert _agree(a, b, 1e-10)


def test_remesh_matches_serial_and_checkpoint_restores(tmp_path):
    path = WORLD.bcast(str(tmp_path), root=0)
    out = {}
    for name, comm in (("world", WORLD), ("self", SELF)):
        domain = block_domain(comm)
        arrays = gather_mesh(domain)  # collective
        points = comm.bcast(arrays.points if comm.rank == 0 else None, root=0)
        rf = _build_block(domain)
        design = rf.controls.controls[0].motion.design
        q = np.zeros((len(design), 2))
        q[:, 1] = -0.4 * points[design, 1] * (1.0 + 0.3 * np.sin(3.0 * points[design, 0]))
        q = q.ravel()  # squash the block
        remesher = Remesher(_build_block, threshold=0.9)
        assert remesher.needs_remesh(rf, q)
        new_rf, new_q = remesher.remesh(rf, q)
        arrays = gather_mesh(new_rf.model.domain)
        J = new_rf(new_q)
        out[name] = (arrays, J, remesher.history[0].quality_after, new_rf)
        if name == "world":
            remesher.save_checkpoint(path, new_rf)
            restored = remesher.load_checkpoint(path, _build_block(block_domain(WORLD)))
            assert restored.size == new_rf.size
            assert restored(new_q) == pytest.approx(J, rel=1e-12)
    (a_world, J_world, q_world, _), (a_self, J_self, q_self, _) = out["world"], out["self"]
    assert J_world == pytest.approx(J_self, rel=1e-10)
    assert q_world == pytest.approx(q_self, rel=1e-12)
    same = None
    if WORLD.rank == 0:  # the boundary comes from parallel solves: equal up to round-off
        same = {k: np.array_equal(getattr(a_world, k), getattr(a_self, k)) for k in KEYS}
        same["points"] = np.allclose(a_world.points, a_self.points, rtol=0.0, atol=1e-13)
        print(same)
    assert all(WORLD.bcast(same, root=0).values())
