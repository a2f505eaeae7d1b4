"""An interrupted reconstruction goes on from the step it stopped at, as if it never stopped:
the same bits."""

import dataclasses
import json
import os
import shutil
import signal

import pytest
import torch

from evcap.errors import InputError
from evcap.recon.options import Feedback, ReconstructOptions
from evcap.recon.reconstruct import reconstruct
from evcap.recon.resume import stop_after_step
from evcap.records import ReconstructionFolder
from evcap.sim.scene import load_scene
from evcap.sim.simulate import simulate


@pytest.fixture(scope="module")
def session(tiny_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("session") / "s.h5"
    simulate(load_scene(tiny_scene()), out)
    return out


def gaussians(out):
    return torch.load(out / "checkpoint" / "radiance.pt", weights_only=True)["gaussians"]


def material(out):
    return torch.load(out / "checkpoint" / "material.pt", weights_only=True)["material"]


RUN = ReconstructOptions(preset="tiny", settings={"stage2.iterations": 12})
# stage I alone (stage II's settings are refused with it)
RADIANCE = ReconstructOptions(preset="tiny", stage="radiance")
START_OVER = "go on or start over"  # --force


@pytest.fixture(scope="module")
def uninterrupted(session, tmp_path_factory):
    out = tmp_path_factory.mktemp("whole")
    return out, reconstruct(session, out, RUN)


def test_stage_one_goes_on_from_where_it_stopped(session, uninterrupted, tmp_path, interrupt_at):
    whole, expected = uninterrupted
    # step 40: before the densification at step 50, which then uses the gradients seen before
    first = reconstruct(session, tmp_path, RUN, Feedback(progress=interrupt_at(40, "radiance")))
    assert first.interrupted and first.iterations == 40
    assert ReconstructionFolder(tmp_path).training_state("radiance").exists()
    assert first.material_iterations is None  # stage II did not start
    said = []
    result = reconstruct(session, tmp_path, RUN, Feedback(say=said.append))
    assert said and "going on from step 40 of 150" in said[0]
    assert not result.interrupted and result.iterations == 150
    assert result.gaussians == expected.gaussians
    for name, value in gaussians(whole).items():
        assert torch.equal(gaussians(tmp_path)[name], value), name
    for name, value in material(whole).items():
        assert torch.equal(material(tmp_path)[name], value), name
    assert [h["step"] for h in result.history] == [h["step"] for h in expected.history]
    # the training log goes on too: the rows before the interruption, then the rest
    steps = [x["step"] for x in result.training_log["radiance"]]
    assert steps == [x["step"] for x in expected.training_log["radiance"]]
    assert not ReconstructionFolder(tmp_path).training_state("radiance").exists()
    with pytest.raises(InputError, match="already holds"):  # finished: nothing to go on with
        reconstruct(session, tmp_path, RUN)


def test_stage_two_goes_on_without_running_stage_one_again(
    session, uninterrupted, tmp_path, interrupt_at
):
    whole, expected = uninterrupted
    first = reconstruct(session, tmp_path, RUN, Feedback(progress=interrupt_at(5, "material")))
    assert first.interrupted and first.material_iterations == 5
    said = []
    result = reconstruct(session, tmp_path, RUN, Feedback(say=said.append))
    assert said == [s for s in said if s.startswith("stage II: going on from step 5 of 12")]
    assert not result.interrupted and result.material_iterations == 12
    assert result.iterations == 150  # stage I's figures kept
    assert result.training_log["radiance"] == first.training_log["radiance"]
    steps = [x["step"] for x in result.training_log["material"]]
    assert steps == [x["step"] for x in expected.training_log["material"]]
    for name, value in material(whole).items():
        assert torch.equal(material(tmp_path)[name], value), name
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["base_color_psnr_gain"] == pytest.approx(expected.figures.base_color_psnr_gain)


def test_a_stage_two_state_that_does_not_fit_is_refused_by_name(
    session, uninterrupted, tmp_path, interrupt_at
):
    """A state saved by an evcap whose stage II held other arrays (before the visibility was
    baked per direction) names the problem and the way out, not a PyTorch traceback."""
    whole, _ = uninterrupted
    (tmp_path / "checkpoint").mkdir()
    shutil.copy(whole / "checkpoint" / "radiance.pt", tmp_path / "checkpoint" / "radiance.pt")
    settings = {"stage2.iterations": 12, "stage2.visibility": "on"}
    run = dataclasses.replace(RUN, stage="material", settings=settings)
    reconstruct(session, tmp_path, run, Feedback(progress=interrupt_at(3, "material")))
    path = ReconstructionFolder(tmp_path).training_state("material")
    state = torch.load(path, weights_only=True)
    state["material"]["visibility_sh"] = state["material"].pop("visibility")
    torch.save(state, path)
    with pytest.raises(InputError, match="does not hold what this evcap's stage II holds.*--force"):
        reconstruct(session, tmp_path, run)


def test_a_stage_two_state_from_another_stage_one_is_refused_or_started_over(
    session, tmp_path, interrupt_at
):
    """Stage I beside it changed after stage II was interrupted: refused by name, and with
    --force (as the demo runs it) said and started over."""
    reconstruct(session, tmp_path, RUN, Feedback(progress=interrupt_at(5, "material")))
    path = tmp_path / "checkpoint" / "radiance.pt"
    checkpoint = torch.load(path, weights_only=True)
    checkpoint["gaussians"]["means"][0] += 0.01
    torch.save(checkpoint, path)
    with pytest.raises(InputError, match="stage II that cannot .*another stage I.*--force"):
        reconstruct(session, tmp_path, RUN)
    said = []
    forced = dataclasses.replace(RUN, resume=START_OVER)
    result = reconstruct(session, tmp_path, forced, Feedback(say=said.append))
    assert said and said[0].startswith("stage II: starting over; the state it saved cannot")
    assert not result.interrupted and result.material_iterations == 12


def test_other_settings_are_refused_or_started_over(session, tmp_path, interrupt_at):
    reconstruct(session, tmp_path, RADIANCE, Feedback(progress=interrupt_at(20, "radiance")))
    with pytest.raises(InputError, match="stage I .* other settings: seed 0 [(]now 1[)]"):
        reconstruct(session, tmp_path, dataclasses.replace(RADIANCE, seed=1))
    assert ReconstructionFolder(tmp_path).training_state("radiance").exists()  # the refusal kept it
    said = []
    forced = dataclasses.replace(RADIANCE, seed=1, resume=START_OVER)
    result = reconstruct(session, tmp_path, forced, Feedback(say=said.append))
    assert said == [
        "stage I: starting over; the state it saved cannot be gone on with (it was started "
        "with other settings: seed 0 (now 1))"
    ]
    assert result.iterations == 150 and not result.interrupted


def test_a_state_another_version_saved_is_refused_by_name(session, tmp_path, interrupt_at):
    reconstruct(session, tmp_path, RADIANCE, Feedback(progress=interrupt_at(20, "radiance")))
    path = ReconstructionFolder(tmp_path).training_state("radiance")
    state = torch.load(path, weights_only=True)
    del state["format"], state["evcap"], state["data"]  # as the evcap before format 2 saved it
    torch.save(state, path)
    expected = "another version of evcap saved it .*state format 1.*pass --force to start over"
    with pytest.raises(InputError, match=expected):
        reconstruct(session, tmp_path, RADIANCE)
    said = []
    forced = dataclasses.replace(RADIANCE, resume=START_OVER)
    reconstruct(session, tmp_path, forced, Feedback(say=said.append))
    assert len(said) == 1 and said[0].startswith("stage I: starting over; the state it saved")


def test_a_step_cut_in_two_is_not_saved(session, tmp_path, monkeypatch):
    from evcap.recon.radiance import densify

    def cut(*args, **kwargs):
        raise KeyboardInterrupt  # a second Ctrl-C, in the middle of a step

    monkeypatch.setattr(densify.DefaultStrategy, "densify", cut)
    result = reconstruct(session, tmp_path, RADIANCE)
    assert (
        result.interrupted
        and not ReconstructionFolder(tmp_path).training_state("radiance").exists()
    )


def test_ctrl_c_asks_to_stop_and_a_second_one_interrupts():
    before = signal.getsignal(signal.SIGINT)
    with stop_after_step() as requested:
        assert not requested()
        os.kill(os.getpid(), signal.SIGINT)
        assert requested()
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
    assert signal.getsignal(signal.SIGINT) is before
