"""Run under ``mpiexec -n 2``: a PolyFEM scene with a moving obstacle (displacement
expressions of x, y, z, t) gives the serial trajectory facts, value and velocity gradient."""

from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI
from test_polyfem_moving_obstacles import build, motion_numpy, velocity_functional, write_scene

from diffsolids.optimize.invariants import check_trajectories

COMM = MPI.COMM_WORLD


def _shared_folder(tmp_path: Path) -> Path:
    """Rank 0's tmp_path, written by rank 0 only (the ranks' pytest folders may coincide)."""
    folder = Path(COMM.bcast(str(tmp_path) if COMM.rank == 0 else None, root=0))
    if COMM.rank == 0:
        write_scene(folder)
    COMM.Barrier()
    return folder


def test_moving_obstacle_scene_world_equals_self(tmp_path):
    assert COMM.size > 1, "run with mpiexec -n 2"
    folder = _shared_folder(tmp_path)
    out, gaps = [], []
    for comm in (COMM, MPI.COMM_SELF):
        setup = build(folder / "scene.json", comm)
        contact, sim = setup.contact, setup.simulation
        traj = sim.run()
        (obstacle,) = contact.obstacles
        for t in traj.times:
            assert np.allclose(obstacle.displacement(t), motion_numpy(obstacle.rest_positions, t))
        checks = check_trajectories(sim, [traj], contact)
        assert checks.intersecting == 0 and checks.min_distance > 0
        gaps.append([r.min_distance for r in contact.records])
        rf, q = velocity_functional(folder, comm)
        out.append(rf.value_and_gradient(q))
    assert np.allclose(gaps[0], gaps[1], rtol=1e-9, atol=0, equal_nan=True)
    (J_par, g_par), (J_ser, g_ser) = out
    assert J_par == pytest.approx(J_ser, rel=1e-9)
    assert np.allclose(g_par, g_ser, rtol=1e-7, atol=0)
