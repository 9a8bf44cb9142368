"""Run under ``mpiexec -n 2``: the optimiser's and the output's robustness on 2 ranks.

A trial with an overflowing field is rejected and the run goes on; a refused parameter point
leaves every field and control as they were on every rank; a failed remesh ends the run
at the accepted point; a folded boundary is refused on every rank; each trajectory is written
on its own rest shape; a checkpoint directory that is a file is an error on every rank.
"""

import numpy as np
import pytest
import test_materials_and_errors as materials  # its tests, run here on 2 ranks
import test_optimize as serial  # its tests, run here on 2 ranks (not collected again)
from mpi4py import MPI

import diffsolids as ds
from diffsolids.controls import ShapeControl
from diffsolids.io import write_trajectory
from diffsolids.mesh import create_rectangle
from diffsolids.optimize import OptimizationError
from diffsolids.optimize.checkpoint import Checkpoint

COMM = MPI.COMM_WORLD


def test_optimiser_robustness_on_two_ranks():
    assert COMM.size > 1, "run with mpiexec -n 2"
    serial.test_a_trial_with_an_overflowing_field_is_rejected_and_the_run_goes_on()
    serial.test_a_failed_remesh_ends_the_run_at_the_accepted_point()
    serial.test_shape_control_refuses_a_boundary_folded_into_another_body()


def test_a_refused_parameter_point_on_two_ranks():
    assert COMM.size > 1, "run with mpiexec -n 2"
    square = materials.square.__wrapped__()
    materials.test_a_refused_parameter_point_leaves_the_model_as_it_was(square)
    materials.test_a_refused_point_puts_every_control_back(square)
    materials.test_a_refused_point_puts_the_friction_coefficients_back()


def test_trajectories_on_their_own_rest_shapes_on_two_ranks(tmp_path_factory):
    from output_checks import read_vtx

    folder = COMM.bcast(str(tmp_path_factory.mktemp("rest")) if COMM.rank == 0 else None)
    facets = {1: lambda x: np.isclose(x[0], 0.0)}
    domain = create_rectangle(COMM, [[0, 0], [2, 1]], [4, 2], facets=facets)
    model = ds.Model(domain, ds.LinearElastic(E=1e3, nu=0.3))
    model.add_gravity(1.0)
    model.add_dirichlet(1, 0.0)
    sim = ds.Simulation(model, ds.Static(), progress=False)
    control = ShapeControl(model)
    before = sim.run()
    control.assign(0.1 * np.ones(control.size))
    after = sim.run()
    write_trajectory(model, before, f"{folder}/initial.bp")
    write_trajectory(model, after, f"{folder}/final.bp")
    if COMM.rank == 0:
        initial = read_vtx(f"{folder}/initial.bp")["steps"][0]["geometry"]
        final = read_vtx(f"{folder}/final.bp")["steps"][0]["geometry"]
        assert np.allclose(np.unique(initial[:, 0].round(12)), [0.0, 0.5, 1.0, 1.5, 2.0])
        assert np.allclose(np.unique(final[:, 0].round(12)), [0.1, 0.6, 1.1, 1.6, 2.1])


def test_a_checkpoint_directory_that_is_a_file_fails_on_every_rank(tmp_path_factory):
    path = COMM.bcast(str(tmp_path_factory.mktemp("ckpt") / "taken") if COMM.rank == 0 else None)
    if COMM.rank == 0:
        with open(path, "w") as f:
            f.write("a file\n")
    COMM.barrier()
    with pytest.raises(OptimizationError, match="is a file"):
        Checkpoint(path, COMM)
