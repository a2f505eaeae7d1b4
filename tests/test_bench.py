"""The benchmarks under bench/ run at a tiny size, so that none breaks unseen: each one's main
path through its own command line, on tiny scenes, its figures written as a bench writes them."""

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from evcap.sim.scene import load_scene
from evcap.sim.simulate import simulate

BENCH = Path(__file__).resolve().parent.parent / "bench"
sys.path.insert(0, str(BENCH))


@pytest.fixture(scope="module")
def scene(tiny_scene):
    return tiny_scene()


@pytest.fixture(scope="module")
def session(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "session.h5"
    simulate(load_scene(scene), out)
    return out


# Every bench and the arguments of its tiny run: {scene} a tiny scene, {session} its session,
# {board} the calibration tests' board recording, {sample} the real DAVIS346 recording,
# {surface} a reconstruction folder of the tiny scene's true surface. steps
# and paper_table have tests of their own below.
TINY = {
    "ablation": ["--scenes", "{session}", "--iterations", "5", "--material-iterations", "2"]
    + ["--variants", "full", "no edge TV", "no normal loss"],
    "batch": ["--recordings", "1", "--scene", "{scene}", "--ray-workers"],
    "calibration": ["--scene", "{board}", "--board", "charuco:5x4:0.04:0.03:DICT_4X4_50"]
    + ["--real", "{sample}"],
    "cli_startup": ["--runs", "1"],
    "decode_throughput": ["--seconds", "0.02", "--rounds", "1"],
    "geometry": ["--scenes", "{session}", "--preset", "tiny", "--iterations", "5"]
    + ["--variants", "base", "binary", "--seeds", "0", "1"],
    "gpu": ["{session}", "--backends", "cpu", "--iterations", "5", "--material-iterations", "2"],
    "import_throughput": ["--events", "20000", "--warm-events", "2000", "--rounds", "1"],
    "mesh": ["{surface}", "--views", "8", "--texture-size", "128", "--resolution", "0.03"]
    + ["--samples", "20000"],
    "poses": ["--scenes", "{board}"],
    "robustness": ["--scenes", "{scene}", "--preset", "tiny", "--iterations", "5"]
    + ["--material-iterations", "2", "--rows", "davis346, uncalibrated"]
    + ["davis346, bound and noise rates", "pose noise 2 deg", "dim light, noise filter 5 ms"],
    "recon_pareto": ["--scenes", "{session}", "--presets", "tiny", "--iterations", "5"]
    + ["--resolutions", "0.5", "--seeds", "1"],
    "record_throughput": ["--seconds", "0.05"],
    "session_io": ["--events", "20000", "--batch", "5000"],
    "sim_throughput": ["--seconds", "0.02", "--size", "48x36", "--scenes", "single_object"],
    "tui_refresh": ["--seconds", "0.3", "--size", "80x24"],
}
OWN_TESTS = {"steps", "paper_table", "rasterizer"}


def test_every_bench_has_a_tiny_run():
    benches = {p.stem for p in BENCH.glob("*.py") if not p.stem.startswith("_")}
    assert benches == set(TINY) | OWN_TESTS


@pytest.mark.parametrize("name", sorted(TINY))
def test_bench_runs_at_a_tiny_size(name, request, monkeypatch, tmp_path):
    import importlib

    import _common

    fixtures = {"session": "session", "board": "board_session", "sample": "sample_aedat4"}
    fixtures["scene"] = "scene"
    fixtures["surface"] = "surface_reconstruction"
    args = " ".join(TINY[name])
    paths = {k: request.getfixturevalue(f) for k, f in fixtures.items() if f"{{{k}}}" in args}

    module = importlib.import_module(name)
    results = tmp_path / "results"
    monkeypatch.setattr(_common, "RESULTS", results)
    if hasattr(module, "RESULTS"):
        monkeypatch.setattr(module, "RESULTS", results)
    module.main([arg.format(**paths) for arg in TINY[name]])
    written = [json.loads(p.read_text()) for p in results.glob("*.json")]
    assert written, f"{name} wrote no figures"
    assert all(doc.get("machine") for doc in written)


def test_ablation_shares_a_kept_stage_one(session, monkeypatch, tmp_path):
    """--stage-one: the variants start from a stage I kept by an earlier run, not a new one."""
    import _common
    import ablation

    monkeypatch.setattr(_common, "RESULTS", tmp_path)
    monkeypatch.setattr(ablation, "RESULTS", tmp_path)
    tiny = ["--scenes", str(session), "--iterations", "5", "--material-iterations", "2"]
    ablation.main([*tiny, "--variants", "full", "--work", str(tmp_path / "first")])
    kept = tmp_path / "first" / session.stem
    calls = []
    original = ablation.reconstruct

    def counted(recording, out, options, *args):
        calls.append(options.stage)
        return original(recording, out, options, *args)

    monkeypatch.setattr(ablation, "reconstruct", counted)
    ablation.main([*tiny, "--variants", "full", "no edge TV", "--stage-one", str(kept)])
    assert calls == ["material", "material"]  # no stage I fitted
    written = json.loads((tmp_path / "ablation.json").read_text())
    first = json.loads((kept / "metrics.json").read_text())
    assert written["stage_one"][session.stem]["object_psnr_gain"] == first["object_psnr_gain"]
    assert [r["variant"] for r in written["runs"]] == ["full", "no edge TV"]


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
    assert figures["object_psnr_gain"] > 0 and figures["object_psnr_constant"] > 0


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


def test_rasterizer_times_another_checkout_beside_this_one(session, monkeypatch, tmp_path):
    """The rasterizer bench at a tiny size, with `--baseline`: another checkout's compiled
    rasterizer in a process of its own, taking its turn in every round (here this checkout's
    own tree, as an exported commit's would be)."""
    import _common
    import rasterizer

    monkeypatch.setattr(_common, "RESULTS", tmp_path)
    monkeypatch.setattr(rasterizer, "RESULTS", tmp_path)
    args = ["--quick", "--repeats", "1", "--scene", str(session), "--preset", "tiny"]
    args += ["--iterations", "5", "--scale", "0.25", "--baseline-code", str(BENCH.parent)]
    rasterizer.main(args)
    doc = json.loads((tmp_path / "rasterizer.json").read_text())
    assert doc["machine"]
    ratios = [v for k, v in doc.items() if k.endswith("_cpu_vs_baseline_2_threads")]
    assert ratios and all(r > 0 for r in ratios)
    before = [r for r in doc["rows"] if r["backend"] == rasterizer.BASELINE]
    this = [r for r in doc["rows"] if r["backend"] == "cpu"]
    assert len(before) == len(this) == 6  # 3 configurations, 1 and 2 threads
    # the same code on the same view: the same picture
    assert [r["mean_alpha"] for r in before] == [r["mean_alpha"] for r in this]


def test_paper_table_scores_both_stages_on_every_held_out_view(nerf_scene, monkeypatch, tmp_path):
    import paper_table

    monkeypatch.setattr(paper_table, "RESULTS", tmp_path)
    args = [str(nerf_scene), "--preset", "tiny", "--iterations", "20"]
    args += ["--material-iterations", "5", "--seeds", "0", "1"]
    doc = paper_table.main(args)
    figures = doc["figures"]
    assert figures["views"]["values"] == [10, 10]  # every view of transforms_train.json
    for key in ("render_psnr", "render_psnr_gain", "render_ssim", "radiance_psnr_gain"):
        assert 0 < figures[key]["mean"] < 60 and figures[key]["std"] is not None, key
    for key in ("normal_mae_deg", "radiance_normal_mae_deg", "depth_rel_err", "object_psnr"):
        assert np.isfinite(figures[key]["mean"]), key
    for key in ("render_object_psnr", "render_object_psnr_gain", "object_psnr_constant"):
        assert np.isfinite(figures[key]["mean"]), key
    for key in ("silhouette_iou", "background_clear"):
        assert 0 <= figures[key]["mean"] <= 1, key
    assert figures["render_lpips"]["mean"] == paper_table.NO_LPIPS
    assert figures["base_color_psnr"]["mean"] == paper_table.NO_ALBEDO
    # the gain is fitted once over all views: it can only bring the pixels closer in linear
    # terms, so its sRGB PSNR is not far below the raw one
    assert figures["render_psnr_gain"]["mean"] > figures["render_psnr"]["mean"] - 3
    table = (tmp_path / "paper_table-sphere-white.md").read_text()
    assert "evcap, sphere, tiny, background white" in table and "method, 7-scene mean" in table
    assert "seeds 0 1" in table and "silhouette (alpha >= 0.5) against the truth's" in table
    sheet = cv2.imread(str(tmp_path / "paper_table" / "sphere-tiny-x1-white-seed0.png"))
    assert sheet.shape == (4 * 36, 5 * 48, 3)  # four views, each beside its truth
    again = paper_table.main(args[:-1])  # seed 0 is read back, not run again
    assert again["runs"][0] == doc["runs"][0]
    rescored = paper_table.main([*args[:-1], "--rescore"])["runs"][0]
    assert rescored["figures"] == doc["runs"][0]["figures"]  # the same fields, the same truth


def test_paper_table_on_mic_scores_the_known_background_raw_and_after_one_gain(
    nerf_synthetic_mic, monkeypatch, tmp_path, capsys
):
    """NeRF-Synthetic's mic at a tenth of its size: both stages over the release's known
    white, the table's rows raw and after one gain per channel, the background stated."""
    import paper_table

    mic = nerf_synthetic_mic
    monkeypatch.setattr(paper_table, "RESULTS", tmp_path)
    args = [str(mic), "--scale", "0.1", "--preset", "tiny", "--iterations", "30"]
    doc = paper_table.main([*args, "--material-iterations", "5"])
    printed = capsys.readouterr().out
    assert "evcap, mic, tiny, background white, 80 x 80" in printed
    raw = next(line for line in printed.splitlines() if ": raw |" in line)
    gain = next(line for line in printed.splitlines() if "after one gain per channel" in line)
    assert raw.count("|") == gain.count("|") and raw != gain
    figures = doc["figures"]
    assert figures["views"]["values"] == [100]  # every view of transforms_train.json
    for key in ("render_psnr", "render_psnr_gain", "render_object_psnr_gain"):
        assert 5 < figures[key]["mean"] < 60, key


def test_geometry_gives_each_figures_mean_and_spread_over_the_seeds():
    import geometry

    rows = [
        {"scene": "s", "variant": "base", "iterations": 9, "seed": k, "normal_mae_deg": v}
        for k, v in ((0, 5.0), (1, 9.0), (2, 7.0))
    ]
    rows.append(
        {"scene": "s", "variant": "alpha", "iterations": 9, "seed": 0, "normal_mae_deg": 3.0}
    )
    base, alpha = geometry.over_seeds(rows)
    assert base["seeds"] == "0 1 2" and alpha["seeds"] == "0"
    assert base["normal_mae_deg mean"] == 7.0 and base["normal_mae_deg spread"] == 4.0
    assert alpha["normal_mae_deg spread"] == 0.0 and "depth_rel_err mean" not in base
