"""Going on with an interrupted stage on another number of threads (as on another machine):
what the stage derived at its start comes from its saved state, never built again, and what it
derives is the same on any number of threads."""

from __future__ import annotations

import subprocess
import sys
from contextlib import contextmanager

import numba
import pytest
import torch

from evcap.recon.export import load_checkpoint
from evcap.recon.material import stage as material
from evcap.recon.options import Feedback, ReconstructOptions
from evcap.recon.presets import preset
from evcap.recon.radiance import stage as radiance
from evcap.recon.reconstruct import reconstruct
from evcap.recon.resume import digest
from evcap.records import Poses
from evcap.session import Session
from evcap.sim.scene import load_scene
from evcap.sim.simulate import simulate

# the poses refined: stage II goes on the path stage I refined (OUT/poses.h5); visibility and
# the light's bounces baked at stage II's start
SETTINGS = {"stage2.iterations": 12, "stage1.poses.refine": "on"}
SETTINGS |= {"stage2.visibility": "on", "stage2.indirect": "on"}
RUN = ReconstructOptions(preset="tiny", settings=SETTINGS)
# what each stage builds at its start: going on, it must take all of it from its state
BUILDERS = {
    "radiance": [(radiance, "new_field"), (radiance, "scene_volume"), (radiance, "render_grid")],
    "material": [
        (material, "start_stage_two"),
        (material, "new_material_field"),
        (material, "bake_occlusion"),
        (material, "plane_normals"),
        (material, "edge_maps"),
    ],
}


@contextmanager
def threads(count: int, kernels_parallel: bool = True):
    """torch on ``count`` threads, the compiled kernels' parallel loops on (as many threads)
    or off (one thread)."""
    before, limit = torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS
    set_threads(count, kernels_parallel, limit)
    try:
        yield
    finally:
        torch.set_num_threads(before)
        numba.config.NUMBA_NUM_THREADS = limit


def set_threads(count: int, kernels_parallel: bool, limit: int) -> None:
    torch.set_num_threads(count)
    # follow_torch_threads keeps within it
    numba.config.NUMBA_NUM_THREADS = limit if kernels_parallel else 1


# where the runs below stop and go on, and on which threads they go on: stage I is cut after
# its step 40 on two threads and goes on on one; stage II is cut after its step 5 there and
# goes on on two, the kernels' loops serial
START = (2, True)
CUTS = [("radiance", 40, (1, True)), ("material", 5, (2, False))]


def saved(out, name: str) -> dict:
    return torch.load(out / "checkpoint" / f"{name}.pt", weights_only=True)


@pytest.fixture(scope="module")
def session(tiny_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("session") / "s.h5"
    simulate(load_scene(tiny_scene()), out)
    return out


@pytest.fixture(scope="module")
def uninterrupted(session, tmp_path_factory):
    """The run that never stopped, its threads changed after the steps where the cut runs
    stop: torch's training steps give other bits on other numbers of threads (measured on a
    CI machine at this size, docs/reconstruction.md), what was saved must not."""
    out = tmp_path_factory.mktemp("whole")
    limit = numba.config.NUMBA_NUM_THREADS

    def change_threads(done: int, total: int, status: str = "") -> None:
        for stage, at, after in CUTS:
            if done == at and status.startswith("material") == (stage == "material"):
                set_threads(*after, limit)

    with threads(*START):
        reconstruct(session, out, RUN, Feedback(progress=change_threads))
    return out


def test_each_stage_goes_on_on_other_threads_from_what_it_saved(
    session, uninterrupted, tmp_path, monkeypatch, metrics_without_times, interrupt_at
):
    """Stage I interrupted on two threads and gone on with on one, stage II then interrupted
    and gone on with on two (the kernels' loops serial), every builder of a stage's start
    made to fail when it goes on: each takes what it derived from its state, and the run ends
    bit for bit where the run that never stopped (on the same threads) ended."""
    (first, at_first, _), (second, at_second, _) = CUTS
    with threads(*START):
        cut = reconstruct(session, tmp_path, RUN, Feedback(progress=interrupt_at(at_first, first)))
    assert cut.interrupted
    for stage, at, after in CUTS:
        for module, name in BUILDERS[stage]:

            def built_again(*args, name=name, **kwargs):
                raise AssertionError(f"{name} ran again: the saved state has what it builds")

            monkeypatch.setattr(module, name, built_again)
        said = []
        stop = interrupt_at(at_second, second) if stage == first else None
        with threads(*after):
            result = reconstruct(session, tmp_path, RUN, Feedback(say=said.append, progress=stop))
        which = "I" if stage == "radiance" else "II"
        assert said == [s for s in said if s.startswith(f"stage {which}: going on from step {at}")]
        assert said and result.interrupted == (stage == first)
    assert len(saved(tmp_path, "material")["material"]["bounce_receivers"]) > 0
    for name in ("radiance", "material"):
        whole, resumed = saved(uninterrupted, name), saved(tmp_path, name)
        key = "gaussians" if name == "radiance" else "material"
        assert whole[key].keys() == resumed[key].keys()
        for k, value in whole[key].items():
            assert torch.equal(resumed[key][k], value), f"{name} {k}"
    assert metrics_without_times(tmp_path) == metrics_without_times(uninterrupted)


def big_field(out, copies: int) -> radiance.RadianceField:
    """The stage-I field of ``out``, each Gaussian ``copies`` times, moved a little: enough
    Gaussians for torch to share its operations among threads."""
    field, _ = load_checkpoint(out / "checkpoint" / "radiance.pt")
    g = field.gaussians
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest"):
            p = getattr(g, name)
            p.data = p.data.repeat(copies, *([1] * (p.dim() - 1)))
        g.means.data += 0.01 * torch.randn(g.means.shape, generator=generator)
    return field


def test_what_the_stages_derive_at_their_start_is_the_same_on_any_threads(session, uninterrupted):
    """Stage I's data and first Gaussians, stage II's start (normals from planes, visibility,
    light bounces, the effects chosen, edge maps, distillation targets) over 40,000
    Gaussians, on one and two threads, the compiled kernels' loops parallel or not: the same
    bits (torch alone gives other values on two threads there; recon/_threads.py)."""
    field = big_field(uninterrupted, 40_000 // 1500 + 1)
    assert len(field.gaussians) > 40_000
    settings = preset(
        "tiny",
        {
            "stage1.init.gaussians": 40_000,
            "stage2.visibility": "auto",
            "stage2.indirect": "auto",
            "stage2.edges.frames": 6,
        },
    )
    stage1, mconfig = settings.stage1, settings.stage2
    found = []
    for count, parallel in ((1, True), (2, True), (2, False)):
        with threads(count, parallel), Session.open(session) as s:
            data = radiance.load_training_data(s, stage1, "cpu")
            first = radiance.new_field(data, stage1, 0, "cpu", "cpu")
            data.track = Poses.read_file(uninterrupted / "poses.h5")  # as stage II has it
            start_field, start = material.start_stage_two(field, data, s, mconfig, "cpu")
        stage_one = [data.derived(), first.state_dict()]
        stage_two = [start, start_field.state_dict(), start_field.start_variation]
        found.append(digest(*flat(stage_one), *flat(stage_two)))
        assert len(start_field.start_variation) == 2  # both choices baked and rendered
    assert found[0] == found[1] == found[2]


def flat(x) -> list:
    """The values of nested dicts and lists, in order."""
    if isinstance(x, dict):
        return [v for k in sorted(x) for v in flat(x[k])]
    if isinstance(x, list | tuple):
        return [v for item in x for v in flat(item)]
    return [x]


def test_a_reconstruction_keeps_to_the_threads_torch_was_set_to(session, tmp_path):
    """In a fresh process set to one thread: numba's OpenMP pool, started by the first
    compiled kernel (a cube-map lookup of the background, before any render), put torch and
    the kernels on every core."""
    script = f"""
import torch
torch.set_num_threads(1)
import numba
from evcap.recon.options import ReconstructOptions
from evcap.recon.reconstruct import reconstruct
options = ReconstructOptions(preset="tiny", stage="radiance", settings={{"stage1.iterations": 3}})
reconstruct({str(session)!r}, {str(tmp_path)!r}, options)
print(torch.get_num_threads(), numba.get_num_threads())
"""
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["1", "1"]
