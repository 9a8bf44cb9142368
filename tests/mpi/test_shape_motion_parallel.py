"""Run under ``mpiexec -n 2``: mesh motion, Riesz map and remeshing equal their serial runs.

Each test builds the same problem on COMM_WORLD and on COMM_SELF in the same process; all
parameter vectors are in the canonical (partition-independent) order, so they must agree.
"""

import numpy as np
import pytest
import ufl
from mpi4py import MPI

import diffsolids as ds
from diffsolids.mesh import create_rectangle
from diffsolids.objectives import Integral, final_value
from diffsolids.optimize.mesh_motion import MeshMotion, MeshMotionControl
from diffsolids.optimize.remesh import Remesher, gather_mesh
from diffsolids.reduced_functional import ReducedFunctional

WORLD, SELF = MPI.COMM_WORLD, MPI.COMM_SELF
KEYS = ("points", "cells", "cell_values", "facets", "facet_values")
BOTTOM, TOP = 1, 2


def _block(comm):
    return create_rectangle(
        comm,
        [[0, 0], [2, 1]],
        [8, 4],
        facets={BOTTOM: lambda x: np.isclose(x[1], 0.0), TOP: lambda x: np.isclose(x[1], 1.0)},
        bodies={2: lambda x: x[0] > 1.0},
        names={"bottom": BOTTOM, "top": TOP},
    )


def build_block(domain):
    model = ds.Model(domain, ds.LinearElastic(E=100.0, nu=0.3, density=1.0))
    model.add_dirichlet("bottom", 0.0)
    model.add_gravity(1.0)
    sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-12))

    def misfit(f):
        target = 0.55 + 0.1 * ufl.cos(np.pi * f.X[0])
        return (f.X[1] + f.u[1] - target) ** 2 * f.ds(TOP) + 1e-2 * ufl.inner(f.u, f.u) * f.dx

    control = MeshMotionControl(model, "boundary", exclude_facets=["bottom"])
    return ReducedFunctional(sim, final_value(Integral(misfit)), control)


def _agree(a, b, rtol) -> bool:
    """Same verdict on every rank (a failing rank must not leave the other in a collective)."""
    ok = a is None or b is None or np.allclose(a, b, rtol=rtol, atol=rtol * np.abs(b).max())
    return bool(WORLD.allreduce(ok, op=MPI.LAND))


@pytest.mark.parametrize("extension", ["elasticity", "harmonic"])
def test_mesh_motion_and_riesz_map_match_serial(extension):
    rng = np.random.default_rng(11)
    out = {}
    for name, comm in (("world", WORLD), ("self", SELF)):
        P = MeshMotion(_block(comm), "boundary", exclude_facets=[BOTTOM], extension=extension)
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
        rf = build_block(_block(comm))
        q = 0.02 * np.cos(np.arange(rf.size))
        J, g = rf.value_and_gradient(q)
        results.append((np.array([J]), g))
    for a, b in zip(*results, strict=True):
        assert _agree(a, b, 1e-10)


def test_remesh_matches_serial_and_checkpoint_restores(tmp_path):
    path = WORLD.bcast(str(tmp_path), root=0)
    out = {}
    for name, comm in (("world", WORLD), ("self", SELF)):
        domain = _block(comm)
        arrays = gather_mesh(domain)  # collective
        points = comm.bcast(arrays.points if comm.rank == 0 else None, root=0)
        rf = build_block(domain)
        design = rf.controls.controls[0].motion.design
        q = np.zeros((len(design), 2))
        q[:, 1] = -0.4 * points[design, 1] * (1.0 + 0.3 * np.sin(3.0 * points[design, 0]))
        q = q.ravel()  # squash the block
        remesher = Remesher(build_block, threshold=0.9)
        assert remesher.needs_remesh(rf, q)
        new_rf, new_q = remesher.remesh(rf, q)
        arrays = gather_mesh(new_rf.model.domain)
        J = new_rf(new_q)
        out[name] = (arrays, J, remesher.history[0].quality_after, new_rf)
        if name == "world":
            remesher.save_checkpoint(path, new_rf)
            restored = remesher.load_checkpoint(path, build_block(_block(WORLD)))
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
