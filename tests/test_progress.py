"""Progress bars of long runs: the forward steps and the adjoint sweep, checkpointed or not."""

import pytest
from gradient_scenes import scene_model

import diffsolids as ds
from diffsolids.controls import ParameterControl
from diffsolids.objectives import center_of_mass, final_value


@pytest.mark.parametrize("policy", ["all", "memory"])
def test_forward_and_adjoint_show_progress(policy, capsys):
    model = scene_model("2d-p1-nh-damped")
    sim = ds.Simulation(model, ds.BDF(2, 0.05, 4), ds.SolverOptions(rtol=1e-10), progress=True)
    checkpointing = ds.Checkpointing(policy, snaps=2 if policy == "memory" else None)
    J = final_value(center_of_mass(model)[1])
    control = ParameterControl(model, "E", "bodies", log=True)
    rf = ds.ReducedFunctional(sim, J, control, checkpointing=checkpointing)
    rf.gradient(rf.initial_parameters())
    err = capsys.readouterr().err
    assert "steps:" in err
    assert "adjoint:" in err


def test_no_progress_when_disabled(capsys):
    model = scene_model("2d-p1-nh-damped")
    sim = ds.Simulation(model, ds.BDF(1, 0.05, 2), progress=False)
    rf = ds.ReducedFunctional(
        sim, final_value(center_of_mass(model)[1]), ParameterControl(model, "E", "bodies")
    )
    rf.gradient(rf.initial_parameters())
    assert "adjoint" not in capsys.readouterr().err
