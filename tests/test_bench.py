"""The benchmarks under bench/ run at a tiny size, so that none breaks unseen."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from evcap.sim.scene import load_scene
from evcap.sim.simulate import simulate

BENCH = Path(__file__).resolve().parent.parent / "bench"
sys.path.insert(0, str(BENCH))


@pytest.fixture(scope="module")
def session(tiny_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "session.h5"
    simulate(load_scene(tiny_scene()), out)
    return out


TINY_STEPS = ["--preset", "tiny", "--from", "2", "--steps", "3"]
TINY_STEPS += ["--material-from", "1", "--material-steps", "2"]


def test_steps_measures_each_stage_and_its_parts(session, monkeypatch, tmp_path):
    import _common
    import steps

    monkeypatch.setattr(_common, "RESULTS", tmp_path)
    figures = steps.main([str(session), *TINY_STEPS, "--name", "steps_tiny"])
    for stage in (1, 2):
        assert figures[f"stage_{stage}_steps_per_s"] > 0
        shares = {k: v for k, v in figures.items() if k.startswith(f"stage_{stage}_share_")}
        assert {"stage_1_share_render", "stage_1_share_events"} <= set(shares) or stage == 2
        assert sum(shares.values()) == pytest.approx(1.0)
    written = json.loads((tmp_path / "steps_tiny.json").read_text())
    assert written["stage_1_steps_per_s"] == figures["stage_1_steps_per_s"]


def test_steps_full_runs_the_whole_stage_and_scores_it(session, monkeypatch, tmp_path):
    import _common
    import steps

    monkeypatch.setattr(_common, "RESULTS", tmp_path)
    args = [str(session), "--preset", "tiny", "--resolution", "0.2", "--full", "--name", "full"]
    figures = steps.main(args)
    assert figures["resolution"] == 0.2
    assert figures["stage_1_steps_per_min"] > 0
    assert figures["stage_1_training_steps_per_min"] >= figures["stage_1_steps_per_min"]
    assert figures["object_psnr_cc"] > 0 and figures["object_psnr_constant"] > 0


def test_steps_runs_another_checkout_in_a_process_of_its_own(session):
    """`--baseline` measures another commit's tree with its own code: here this checkout's own
    tree, imported from its folders as an exported commit's would be."""
    root = BENCH.parent
    command = [sys.executable, str(BENCH / "steps.py"), "--code", str(root), "--json-only"]
    command += [str(session), *TINY_STEPS[:6], "--material-steps", "0"]
    done = subprocess.run(command, capture_output=True, text=True, cwd=root)
    assert done.returncode == 0, done.stderr
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    assert figures["stage_1_steps_per_s"] > 0 and "stage_2_steps_per_s" not in figures
    assert figures["code"] == str(root)  # the tree's recon/, as its pyproject.toml maps it
