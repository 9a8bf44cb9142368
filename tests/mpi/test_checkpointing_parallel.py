"""Run under ``mpiexec -n 2``: checkpointed gradients on 2 ranks equal the all-in-memory ones.

The scenes of test_checkpointing.py on COMM_WORLD: the damped bar (BDF2, 30 steps, shape and E)
and the friction incline (BDF2, 8 steps, shape, damping and friction). Revolve with 3 and 1
checkpoints, every state on disk and multistage disk checkpoints (each rank its own files) must
give the value and gradient of ``Checkpointing("all")`` on the same ranks to 1e-12.
"""

import numpy as np
import pytest
from mpi4py import MPI
from test_checkpointing import (
    RTOL,
    _records,
    _relative,
    beam,
    incline,
    reduced_functional,
    reference,
)

from diffsolids.adjoint.checkpointing import Checkpointing
from diffsolids.parallel import collective_comm

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size < 2, reason="needs mpiexec -n 2")


@pytest.mark.parametrize(
    ("scene", "policy"),
    [
        ("beam", Checkpointing("memory", snaps=3)),
        ("beam", Checkpointing("disk")),
        ("incline", Checkpointing("memory", snaps=1)),
        ("incline", Checkpointing("disk", snaps=2)),
    ],
    ids=["beam-revolve-3", "beam-disk", "incline-revolve-1", "incline-disk-2"],
)
def test_checkpointed_gradient_on_two_ranks(scene, policy):
    comm = MPI.COMM_WORLD
    q, J_ref, g_ref, records = reference(scene)
    objects = beam() if scene == "beam" else incline()
    rf = reduced_functional(objects, policy)
    J, g = rf.value_and_gradient(q)
    assert rf.trajectory.run.stats["forward_steps"] > 0
    assert pytest.approx(J_ref, rel=RTOL, abs=0) == J
    assert _relative(g, g_ref) <= RTOL
    # the same on every rank (the parameters are global)
    assert collective_comm(comm).allreduce(_relative(g, g_ref), op=MPI.MAX) <= RTOL
    assert _records(objects) == records
    assert np.isfinite(g).all()
