"""`evcap reconstruct` end to end on a tiny simulated scene (color and MONO)."""

import dataclasses
import json
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import torch

from evcap.errors import InputError
from evcap.recon.config import PRESET_NAMES
from evcap.recon.export import read_ply_header
from evcap.recon.options import ReconstructOptions
from evcap.recon.presets import preset
from evcap.recon.radiance.stage import RadianceField, load_training_data, new_field, train_radiance
from evcap.recon.raster.rasterize import gaussian_normals
from evcap.recon.reconstruct import reconstruct
from evcap.recon.scene.support_plane import Plane
from evcap.records import Calibration, GroundTruth, ReconstructionFolder
from evcap.session import Session, SessionWriter
from evcap.sim.scene import load_scene
from evcap.sim.simulate import simulate

# the camera rises and falls while it circles an off-centre sphere: its outline moves
TRAJECTORY = """kind = "orbit"
radius = 2.2
height = 0.8
height_swing = 0.4
swings = 1
degrees = 60.0
duration_s = 0.5"""

SPHERE = """[[objects]]
type = "sphere"
center = [0.25, 0.0, 0.0]
radius = 0.6
material = "paint"
"""


def simulated(tiny_scene, tmp_path_factory, color_filter):
    scene = tiny_scene(color_filter=color_filter, trajectory=TRAJECTORY, objects=SPHERE)
    out = tmp_path_factory.mktemp("session") / f"{color_filter}.h5"
    simulate(load_scene(scene), out)
    return out


@pytest.fixture(scope="module")
def color_session(tiny_scene, tmp_path_factory):
    return simulated(tiny_scene, tmp_path_factory, "RGBG")


@pytest.fixture(scope="module")
def environment(tmp_path_factory):
    """A latitude-longitude environment: warm above, dark below."""
    v = np.linspace(1, 0, 16)[:, None, None] * np.ones((16, 32, 3))
    path = tmp_path_factory.mktemp("env") / "env.png"
    cv2.imwrite(str(path), (v * [60, 160, 250]).astype(np.uint8))
    return path


@pytest.fixture(scope="module")
def color_result(color_session, environment, tmp_path_factory):
    out = tmp_path_factory.mktemp("recon")
    settings = {"stage1.resolution": 1.0, "stage1.iterations": 30, "stage2.iterations": 8}
    options = ReconstructOptions(preset="tiny", settings=settings, relight=str(environment))
    result = reconstruct(color_session, out, options)
    return out, result


def test_writes_every_output(color_result):
    out, result = color_result
    for name in (
        "gaussians.ply",
        "config.toml",
        "metrics.json",
        "checkpoint/radiance.pt",
        "checkpoint/material.pt",
        "environment.png",
    ):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics == result.to_json()
    for key in (
        "object_psnr_gain",
        "object_ssim_gain",
        "object_psnr_constant",
        "blur_psnr",
        "depth_rel_err",
        "render_psnr",
        "render_ssim",
        "render_psnr_gain",
        "render_ssim_gain",
        "depth_abs_err",
        "normal_mae_deg",
        "seconds",
        "iterations",
        "gaussians",
        "device",
        "base_color_psnr",
        "base_color_ssim",
        "base_color_psnr_gain",
        "base_color_ssim_gain",
        "roughness_mae",
        "pbr_render_psnr_gain",
        "radiance_normal_mae_deg",
    ):
        assert key in metrics, key
        assert isinstance(metrics[key], str) or np.isfinite(metrics[key]), key
    assert metrics["iterations"] == 30 and metrics["device"] == "cpu"
    assert metrics["material_iterations"] == 8
    # the training losses, for the report: a row every 10 steps and the last
    log = metrics["training_log"]
    assert [x["step"] for x in log["radiance"]] == [10, 20, 30]
    assert [x["step"] for x in log["material"]] == [8]
    assert log["radiance"][-1].keys() == {
        "step",
        "loss",
        "event",
        "anchor",
        "normal",
        "gaussians",
        "seconds",
    }
    assert log["material"][-1].keys() == {
        "step",
        "loss",
        "event",
        "distill",
        "anchor",
        "tv",
        "seconds",
    }
    # the accuracy-versus-time curve: held-out PSNR at evenly spaced steps, the last one's
    history = metrics["history"]
    assert [h["step"] for h in history] == [5, 10, 15, 20, 25, 30]
    assert all(np.diff([h["seconds"] for h in history]) > 0)
    for key in ("render_psnr_gain", "object_psnr_gain", "object_psnr_constant", "normal_mae_deg"):
        assert all(np.isfinite(h[key]) for h in history), key
    # an isolated sphere: nothing to shadow it, nothing to bleed onto it
    assert metrics["effects"] == {
        "visibility": False,
        "indirect": False,
        "anchor": True,
        "tv": True,
        "distill": True,
    }
    # chosen by `auto`: the starting base color varied least with neither
    variation = metrics["effect_variation"]
    assert variation.keys() == {"neither", "visibility+indirect"}
    assert min(variation, key=variation.get) == "neither"
    renders = sorted(p.name for p in (out / "renders").iterdir())
    for kind in ("radiance", "radiance_gain", "depth", "normal"):
        assert any(kind in name and name.endswith(".png") for name in renders), kind
    material = sorted(p.name for p in (out / "renders" / "material").iterdir())
    for kind in ("radiance", "base_color", "roughness", "normal", "depth"):
        assert any(kind in name and name.endswith(".png") for name in material), kind
    relit = sorted((out / "renders" / "relit").glob("test_*.png"))
    assert len(relit) == len(list((out / "renders").glob("test_*_radiance.png")))
    config = tomllib.loads((out / "config.toml").read_text())
    assert config["stage1"]["iterations"] == 30 and config["stage2"]["iterations"] == 8


def test_relit_views_follow_the_new_light(color_result):
    out, _ = color_result
    views = np.load(out / "renders" / "material" / "test.npz")
    relit = cv2.imread(str(sorted((out / "renders" / "relit").glob("test_*.png"))[0]))
    lit = cv2.imread(str(sorted((out / "renders" / "material").glob("test_*_radiance.png"))[0]))
    assert relit.shape == lit.shape and np.abs(relit.astype(int) - lit).mean() > 2
    assert np.isfinite(views["base_color"]).all()


def test_material_stage_resumes_from_the_checkpoint(color_session, color_result, tmp_path):
    out, first = color_result
    again = tmp_path / "again"
    shutil.copytree(out, again)
    options = ReconstructOptions(
        preset="tiny",
        stage="material",
        settings={"stage2.iterations": 4},
        resume="go on or start over",
    )
    result = reconstruct(color_session, again, options)
    assert result.material_iterations == 4
    assert result.gaussians == first.gaussians  # stage I untouched
    assert result.training_log["radiance"] == first.training_log["radiance"]
    assert [x["step"] for x in result.training_log["material"]] == [4]
    # without --relight, the held-out views are relit by the truth's second light and scored
    figures = result.figures
    assert first.figures.relit_psnr is None and np.isfinite(figures.relit_object_psnr_gain)
    # beside them, what no decomposition and no relighting reach
    assert np.isfinite(figures.relit_object_psnr_gain_baseline)
    assert np.isfinite(figures.base_color_psnr_gain_baseline)
    options = ReconstructOptions(preset="tiny", stage="material")
    with pytest.raises(InputError, match="no stage-I checkpoint"):
        reconstruct(color_session, tmp_path / "empty", options)


def least_squares_gain(fit_on: np.ndarray, fit_to: np.ndarray) -> np.ndarray:
    """[3] the gain per channel of pixels [P, 3] onto others, by least squares, computed here
    without recon/evaluate/metrics.py."""
    p, t = fit_on.astype(np.float64), fit_to.astype(np.float64)
    return np.array([np.linalg.lstsq(p[:, [c]], t[:, c], rcond=None)[0][0] for c in range(3)])


def srgb_psnr(pred: np.ndarray, truth: np.ndarray) -> float:
    def encode(x):
        x = np.clip(x, 0, 1)
        return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)

    return float(10 * np.log10(1 / np.mean((encode(pred) - encode(truth)) ** 2)))


def test_the_corrected_figures_are_one_gain_per_channel_over_all_views(
    color_session, color_result, tmp_path
):
    """metrics.json's corrected object, base color and relit figures: one gain per channel
    fitted once over the scored pixels of all held-out views; the relit views under the new
    light brought into the model's units by the gain of the render under the first light,
    and taken back by it."""
    from evcap.recon.evaluate.views import render_views
    from evcap.recon.export import load_material_checkpoint
    from evcap.recon.material.stage import light_from_image
    from evcap.recon.scene.optics import SensorOptics

    out = tmp_path / "again"
    shutil.copytree(color_result[0], out)
    options = ReconstructOptions(preset="tiny", stage="material", resume="go on or start over")
    reconstruct(color_session, out, options)
    metrics = json.loads((out / "metrics.json").read_text())
    with Session.open(color_session) as s:
        gt = GroundTruth.read(s)
        optics = SensorOptics.from_session(s)
    truth = gt.held_out_views()
    obj, surface = truth.object_mask(), np.linalg.norm(truth.normal, axis=-1) > 0.5
    folder = ReconstructionFolder(out)
    stage_1 = np.load(folder.views_values("radiance", "test"))["radiance"][obj]
    stage_2 = np.load(folder.views_values("material", "test"))
    seen, base, true_base = (
        truth.radiance[obj],
        stage_2["base_color"][surface],
        truth.base_color[surface],
    )
    gain = least_squares_gain(stage_2["radiance"][obj], seen)
    field = load_material_checkpoint(folder.checkpoint("material"))
    light = light_from_image(gt.relight_environment, field.light.faces.shape[-1])
    k = torch.as_tensor(gain, dtype=torch.float32)[None, :, None, None]
    relit = render_views(field, truth.T_world_cam, optics, light=[f / k for f in light])
    expected = {
        "object_psnr_gain": srgb_psnr(stage_1 * least_squares_gain(stage_1, seen), seen),
        "base_color_psnr_gain": srgb_psnr(base * least_squares_gain(base, true_base), true_base),
        "relit_object_psnr_gain": srgb_psnr(
            relit["radiance"][obj] * gain, truth.relit_radiance[obj]
        ),
        "relit_object_psnr_gain_baseline": srgb_psnr(
            stage_1 * least_squares_gain(stage_1, seen), truth.relit_radiance[obj]
        ),
    }
    for key, value in expected.items():
        assert metrics[key] == pytest.approx(value, abs=1e-3), key
    assert metrics["object_psnr"] < metrics["object_psnr_gain"]  # raw first, and not the same


def test_a_known_background_is_held_in_both_stages_and_kept(color_session, tmp_path):
    """known_background: both stages see that radiance wherever the Gaussians leave light
    through, in training, in the written views and after a reload of their checkpoints."""
    from evcap.recon.evaluate.views import render_views
    from evcap.recon.export import load_checkpoint, load_material_checkpoint
    from evcap.recon.scene.optics import SensorOptics

    grey = (0.3, 0.5, 0.7)
    settings = {"stage1.iterations": 20, "stage2.iterations": 4, "stage1.background.known": grey}
    reconstruct(color_session, tmp_path, ReconstructOptions(preset="tiny", settings=settings))
    folder = ReconstructionFolder(tmp_path)
    assert folder.settings("stage1")["background"]["known"] == list(grey)
    field, config = load_checkpoint(folder.checkpoint("radiance"))
    assert config.background.known == grey
    material = load_material_checkpoint(folder.checkpoint("material"))
    with Session.open(color_session) as s:
        optics = SensorOptics.from_session(s)
        pose = GroundTruth.read(s).held_out_views().T_world_cam[:1]
    away = pose @ np.diag([-1.0, 1.0, -1.0, 1.0])  # turned round: nothing but the backdrop
    for f in (field, material):
        seen = render_views(f, away, optics)
        assert seen["alpha"].max() < 1e-3
        np.testing.assert_allclose(seen["radiance"].reshape(-1, 3).mean(0), grey, atol=1e-3)
    with pytest.raises(InputError, match="background.known"):
        preset("tiny", {"stage1.background.known": (1.0, 0.0, 1.0)})


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("backend", ["torch", "gsplat"])
def test_both_stages_run_on_a_cuda_gpu(color_session, environment, tmp_path, backend):
    # on a GPU, the densification's statistics and the PLY export once took CPU tensors
    if backend == "gsplat":
        from evcap.recon.raster import _gsplat as _raster_gsplat

        if not _raster_gsplat.available():
            pytest.skip("gsplat is not installed or cannot build its kernels")
    settings = {"stage1.resolution": 1.0, "stage1.iterations": 30, "stage2.iterations": 8}
    settings["stage1.densify.every"] = 10
    options = ReconstructOptions(
        preset="tiny",
        device="cuda",
        backend=backend,
        settings=settings,
        relight=str(environment),
    )
    result = reconstruct(color_session, tmp_path, options)
    assert (result.device, result.backend) == ("cuda", backend)
    assert read_ply_header(tmp_path / "gaussians.ply")[0] == result.gaussians
    assert np.isfinite(result.figures.object_psnr_gain)
    assert np.isfinite(result.figures.base_color_psnr_gain)
    assert len(list((tmp_path / "renders" / "relit").glob("test_*.png"))) > 0


def test_ply_is_the_common_3dgs_layout(color_result):
    out, result = color_result
    count, names = read_ply_header(out / "gaussians.ply")
    assert count == result.gaussians
    expected = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[: len(expected)] == expected
    assert names[-8:] == [
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
    ]
    body = (out / "gaussians.ply").read_bytes()
    body = body[body.index(b"end_header\n") + len(b"end_header\n") :]
    values = np.frombuffer(body, "<f4").reshape(count, len(names))
    assert np.isfinite(values).all()


def test_learns_the_scene_from_events_alone(color_session, tmp_path):
    settings = {"stage1.resolution": 1.0}
    options = ReconstructOptions(preset="tiny", stage="radiance", settings=settings)
    result = reconstruct(color_session, tmp_path, options)
    # the best constant image scores 16.1 dB after color correction on this scene; this run
    # scored 19.0 dB (depth error 0.197, at about 2.2 units) when it was written
    assert result.figures.render_psnr_gain > 18
    assert result.figures.depth_abs_err < 0.25


def test_checkpoint_holds_the_field(color_result):
    out, result = color_result
    state = torch.load(out / "checkpoint" / "radiance.pt", weights_only=False)
    assert state["gaussians"]["means"].shape == (result.gaussians, 3)


def test_stage_two_checkpoint_reads_back_the_field_that_was_scored(color_session, color_result):
    """The material field read from its checkpoint renders the held-out views as the trained
    one did: its shaded render scores what metrics.json says, to the bit."""
    from evcap.recon.evaluate.views import material_metrics, render_views
    from evcap.recon.export import load_material_checkpoint
    from evcap.recon.scene.optics import SensorOptics

    out, result = color_result
    field = load_material_checkpoint(out / "checkpoint" / "material.pt")
    assert field.effects.items() <= result.effects.items()
    with Session.open(color_session) as s:
        truth = GroundTruth.read(s).held_out_views()
        optics = SensorOptics.from_session(s)
    views = render_views(field, truth.T_world_cam, optics)
    figures = material_metrics(views, truth)
    assert figures["pbr_render_psnr"] == result.figures.pbr_render_psnr
    assert figures["base_color_psnr"] == result.figures.base_color_psnr
    with pytest.raises(InputError, match="no stage-II checkpoint"):
        load_material_checkpoint(out / "checkpoint" / "absent.pt")


def test_refuses_to_overwrite(color_session, color_result):
    out, _ = color_result
    with pytest.raises(InputError, match="--force"):
        reconstruct(color_session, out, ReconstructOptions(preset="tiny"))


def test_mono_session(tiny_scene, tmp_path_factory):
    session = simulated(tiny_scene, tmp_path_factory, "MONO")
    out = tmp_path_factory.mktemp("mono")
    settings = {"stage1.iterations": 40, "stage2.iterations": 5}
    result = reconstruct(session, out, ReconstructOptions(preset="tiny", settings=settings))
    assert result.iterations == 40 and np.isfinite(result.figures.render_psnr_gain)
    assert np.isfinite(result.figures.base_color_psnr_gain)


def test_cli_uncalibrated_session_is_a_clear_error(tmp_path, sample_aedat4):
    session = tmp_path / "s.h5"
    run = [sys.executable, "-m", "evcap"]
    subprocess.run([*run, "import", str(sample_aedat4), "-o", str(session)], check=True)
    r = subprocess.run(
        [*run, "reconstruct", str(session), "-o", str(tmp_path / "out")],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2
    assert "no calibration" in r.stderr and "evcap calibrate" in r.stderr


def test_missing_poses_is_a_clear_error(color_session, tmp_path):
    session = tmp_path / "no-poses.h5"
    shutil.copy(color_session, session)
    with h5py.File(session, "a") as f:
        del f["poses"]
    with pytest.raises(InputError, match="no camera poses.*evcap poses"):
        reconstruct(session, tmp_path / "out", ReconstructOptions(preset="tiny"))


@pytest.mark.parametrize("n", [0, 100])
def test_too_few_events_are_refused_at_once(color_session, tmp_path, n):
    session = tmp_path / "few.h5"
    with Session.open(color_session) as s:
        sensor, events = s.sensor, s.events()
    with SessionWriter(session, sensor) as w:
        keep = np.zeros(len(events), bool)
        keep[np.linspace(0, len(events) - 1, n).astype(int)] = True  # over the whole path
        w.append_events(events.select(keep))
    with h5py.File(color_session, "r") as src, h5py.File(session, "a") as dst:
        for group in ("poses", "calibration"):
            src.copy(src[group], dst, group)
    r = subprocess.run(
        [sys.executable, "-m", "evcap", "reconstruct", str(session), "-o", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert ("no events" if n == 0 else "needs at least 500") in r.stderr, r.stderr
    assert not (tmp_path / "o").exists()


def with_refractory(session: Path, us: float, folder: Path) -> Path:
    """A copy of ``session`` whose calibration holds a refractory period of ``us``."""
    copy = Path(shutil.copy(session, folder / "refractory.h5"))
    with Session.open(copy) as s:
        calibration = Calibration.read(s)
    dataclasses.replace(calibration, refractory_period_us=us).write(copy)
    return copy


def test_cli_writes_a_reconstruction(color_session, tmp_path):
    out = tmp_path / "out"
    session = with_refractory(color_session, 500.0, tmp_path)
    args = ["reconstruct", str(session), "-o", str(out), "--preset", "tiny"]
    args += ["--iterations", "5", "--resolution", "1", "--seed", "2"]
    args += ["--material-iterations", "3", "--without", "edge-tv", "--without", "anchor"]
    args += ["--refractory-bound", "--noise-filter", "5"]
    r = subprocess.run([sys.executable, "-m", "evcap", *args], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["iterations"] == 5 and metrics["seed"] == 2
    windows = tomllib.loads((out / "config.toml").read_text())["stage1"]["windows"]
    assert windows["refractory_bound"] and windows["noise_filter_ms"] == 5
    assert not metrics["effects"]["tv"] and not metrics["effects"]["anchor"]
    assert metrics["effects"]["distill"]
    assert "render_psnr_gain" in r.stdout and "base_color_psnr_gain" in r.stdout


def papers_run(session: Path, out: Path, *flags: str) -> tuple[dict, dict]:
    """`evcap reconstruct --preset paper` as a user runs it, its 30,000 + 10,000 steps cut to
    20 + 10: (metrics.json, config.toml)."""
    args = ["reconstruct", str(session), "-o", str(out), "--preset", "paper"]
    args += ["--iterations", "20", "--material-iterations", "10", *flags]
    r = subprocess.run([sys.executable, "-m", "evcap", *args], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["preset"] == "paper" and metrics["iterations"] == 20
    assert metrics["material_iterations"] == 10 and not metrics["interrupted"]
    assert np.isfinite(metrics["base_color_psnr_gain"])
    config = tomllib.loads((out / "config.toml").read_text())
    assert config["stage1"]["sh_degree"] == 3 and config["stage2"]["edges"]["frames"] == 200
    return metrics, config


def test_the_papers_run_completes_both_stages_at_a_tiny_size(color_session, tmp_path):
    """The paper preset's own settings through both stages, on 2,000 Gaussians at a quarter
    of the scale (its full size is the slow test below)."""
    flags = ["--resolution", "0.25", "--set", "stage1.init.gaussians=2000"]
    metrics, config = papers_run(color_session, tmp_path / "paper", *flags)
    assert config["stage1"]["init"]["gaussians"] == 2000 and metrics["gaussians"] > 1000


@pytest.mark.slow
def test_the_papers_run_completes_both_stages(color_session, tmp_path):
    """100,000 Gaussians, degree-3 harmonics, the full scale, both stages, on the CPU."""
    metrics, _ = papers_run(color_session, tmp_path / "paper")
    assert metrics["gaussians"] > 50_000  # the paper's start, not pruned away in 20 steps


def test_stage_one_settings_over_the_preset(color_session, tmp_path):
    settings = (
        ("stage1.event_loss.zero_events", "bound"),
        ("stage1.loss.spread.weight", 10.0),
        ("stage1.iterations", 9),
        ("stage1.iterations", 2),  # a setting named again goes over what it was given before
    )
    options = ReconstructOptions(preset="tiny", stage="radiance", settings=settings)
    reconstruct(color_session, tmp_path, options)
    config = tomllib.loads((tmp_path / "config.toml").read_text())["stage1"]
    assert config["event_loss"]["zero_events"] == "bound"
    assert config["loss"]["spread"]["weight"] == 10.0
    assert config["iterations"] == 2


def test_the_background_alone_first_then_the_gaussians_with_fasts_terms(color_session):
    terms = {"spread": 10.0, "smooth": 0.3, "curvature": 1.0, "alpha": 0.03, "background_tv": 1.0}
    settings = {f"stage1.loss.{term}.weight": weight for term, weight in terms.items()}
    settings |= {"stage1.iterations": 4, "stage1.background.first": 0.5}
    config = preset("tiny", settings).stage1
    with Session.open(color_session) as session:
        data = load_training_data(session, config, "cpu")
    seen: list[tuple[torch.Tensor, torch.Tensor]] = []

    def record(field) -> dict:
        seen.append(
            (field.gaussians.means.detach().clone(), field.background.faces.detach().clone())
        )
        return {}

    fit = train_radiance(data, config, evaluate=record, evaluations=4)
    (means1, faces1), (means2, faces2), _, (means4, _) = seen
    assert torch.equal(means1, means2) and not torch.equal(faces1, faces2)  # hidden: bg only
    assert not torch.equal(means2, means4)  # then the Gaussians learn, every term finite
    assert np.isfinite([x.loss for x in fit.log]).all()


def test_coarse_to_fine_renders_the_first_part_of_the_run_small(color_session, monkeypatch):
    settings = {"stage1.iterations": 4, "stage1.coarse.until": 0.5}
    config = preset("tiny", settings | {"stage1.coarse.resolution": 0.125}).stage1
    with Session.open(color_session) as session:
        data = load_training_data(session, config, "cpu")
    widths: list[int] = []
    render = RadianceField.render_view

    def spy(self, viewmat, grid, *args, **kwargs):
        widths.append(grid.width)
        return render(self, viewmat, grid, *args, **kwargs)

    monkeypatch.setattr(RadianceField, "render_view", spy)
    train_radiance(data, config)
    half = 2 * config.windows.views_per_step  # the renders of the first two of four steps
    assert data.coarse_grid.width < data.grid.width
    assert widths == [data.coarse_grid.width] * half + [data.grid.width] * half
    with pytest.raises(InputError, match="coarse.until"):
        preset("tiny", {"stage1.coarse.until": 2.0})
    with pytest.raises(InputError, match="coarse.resolution"):
        preset("tiny", {"stage1.coarse.resolution": 0.0})


def test_the_refractory_bound_counts_the_crowded_events(color_session, tmp_path):
    """With the calibration's refractory period and the bound asked for, the events within
    twice the period of their pixel's previous one are counted again, apart; not otherwise.
    Asked for without the period, a clear error."""
    bound = preset("tiny", {"stage1.windows.refractory_bound": True}).stage1
    with Session.open(color_session) as s, pytest.raises(InputError, match="evcap calibrate"):
        load_training_data(s, bound, "cpu")
    with Session.open(with_refractory(color_session, 2000.0, tmp_path)) as s:
        crowded = load_training_data(s, bound, "cpu").windows.crowded
        plain = load_training_data(s, preset("tiny").stage1, "cpu").windows
    assert plain.crowded is None and crowded is not None
    assert 0 < crowded.events < plain.events


def test_gaussians_start_on_the_poses_points_when_asked(color_session, tmp_path):
    session = shutil.copy(color_session, tmp_path / "s.h5")
    with Session.open(session) as s:
        data = load_training_data(s, preset("tiny").stage1, "cpu")
    centre, radius = data.volume.center, data.volume.radius
    rng = np.random.default_rng(0)
    inside = centre + rng.normal(0, 0.3 * radius, (50, 3))
    far = centre + np.array([10 * radius, 0, 0])  # an outlier of structure from motion
    with h5py.File(session, "r+") as f:
        f["poses"].create_dataset("points_xyz", data=np.vstack([inside, far]))
    config = preset("tiny", {"stage1.init.gaussians": 200, "stage1.init.on_points": 0.5}).stage1
    with Session.open(session) as s:
        data = load_training_data(s, config, "cpu")
    means = new_field(data, config, 0, "cpu", "torch").gaussians.means.detach().numpy()
    assert len(means) == 200
    # the 50 points inside the volume's (doubled) ball, the outlier left out, then random ones
    on = means[:50].astype(np.float64)
    assert np.abs(np.sort(on, axis=0) - np.sort(inside, axis=0)).max() < 1e-5
    assert not np.isclose(means[50:], far.astype(np.float32)).all(axis=1).any()
    without = preset("tiny", {"stage1.init.gaussians": 200}).stage1
    random = new_field(data, without, 0, "cpu", "torch").gaussians.means.detach().numpy()
    assert not np.isin(random, on.astype(np.float32)).all(axis=1).any()
    with pytest.raises(InputError, match="init.on_points"):
        preset("tiny", {"stage1.init.on_points": 1.5})


def test_gaussians_start_on_the_events_structure_when_asked(color_session):
    """Every starting Gaussian on a point the events' stereo found (none random); half of
    them when half is asked; none found, a clear error."""
    config = preset("tiny", {"stage1.init.on_events": 1.0}).stage1
    with Session.open(color_session) as s:
        data = load_training_data(s, config, "cpu")
    assert data.structure is not None and len(data.structure) > 20  # a 48 x 36 sensor's
    means = new_field(data, config, 0, "cpu", "torch").gaussians.means.detach().numpy()
    assert len(means) == min(config.init.gaussians, len(data.structure))
    found = data.structure.astype(np.float32)
    assert np.isin(means, found).all(axis=1).all()
    half = preset("tiny", {"stage1.init.on_events": 0.5, "stage1.init.gaussians": 40}).stage1
    means = new_field(data, half, 0, "cpu", "torch").gaussians.means.detach().numpy()
    assert len(means) == half.init.gaussians
    assert np.isin(means, found).all(axis=1).sum() == round(0.5 * half.init.gaussians)
    data.structure = np.zeros((0, 3))
    with pytest.raises(InputError, match="stereo found no structure"):
        new_field(data, config, 0, "cpu", "torch")


def test_a_share_starts_as_flat_discs_on_the_support_plane(color_session):
    """init.on_support: that share of the Gaussians flat on the plane the structure stands
    on, facing along its normal, inside the foreground's ball; the plane kept with what a
    training saves."""
    config = preset(
        "tiny",
        {"stage1.init.on_events": 1.0, "stage1.init.on_support": 0.25, "stage1.init.gaussians": 40},
    ).stage1
    with Session.open(color_session) as s:
        data = load_training_data(s, config, "cpu")
    # the tiny scene stands on nothing: a plane through its ball's centre, given
    data.support = Plane((0.0, 0.0, 1.0), float(data.bound.center[2]))
    field = new_field(data, config, 0, "cpu", "torch")
    g = field.gaussians
    on = np.abs(g.means.detach().numpy()[:, 2] - data.support.offset) < 1e-6
    assert on.sum() == 10 and len(g.means) <= 40
    normals = gaussian_normals(g.quats[on], g.log_scales[on].exp()).detach().numpy()
    assert np.allclose(np.abs(normals[:, 2]), 1, atol=1e-5)
    reach = np.linalg.norm(g.means.detach().numpy()[on] - data.bound.center, axis=1)
    assert (reach <= data.bound.radius).all()
    with Session.open(color_session) as s:
        again = load_training_data(s, config, "cpu", data.derived())
    assert again.support == data.support


def test_no_support_is_sought_before_a_known_backdrop(color_session, monkeypatch):
    """A known backdrop is seen wherever the object is not: no floor is sought before it, where
    a learnt background gets the plane the stereo's points stand on."""
    import evcap.recon.radiance.stage as stage

    floor = Plane((0.0, 0.0, 1.0), 0.0)
    monkeypatch.setattr(stage, "support_plane", lambda *args: floor)
    settings = {"stage1.init.on_events": 1.0, "stage1.init.on_support": 0.25}
    learnt = preset("tiny", settings).stage1
    known = preset("tiny", {**settings, "stage1.background.known": (1.0, 1.0, 1.0)}).stage1
    with Session.open(color_session) as s:
        assert load_training_data(s, learnt, "cpu").support == floor
        assert load_training_data(s, known, "cpu").support is None


# every preset runs at a tiny size in the default run: tiny in most tests here, paper above,
# small (the demo's) in tests/test_demo.py at 150 steps, fast here
RUN_ELSEWHERE = {"tiny", "paper", "small"}


@pytest.mark.parametrize("name", sorted(set(PRESET_NAMES) - RUN_ELSEWHERE))
def test_a_preset_runs_both_stages_at_a_tiny_size(color_session, tmp_path, name):
    settings = {"stage1.iterations": 6, "stage2.iterations": 2, "stage1.resolution": 0.25}
    options = ReconstructOptions(preset=name, settings=settings)
    result = reconstruct(color_session, tmp_path / name, options)
    assert result.preset == name and result.iterations == 6
    assert result.material_iterations == 2 and not result.interrupted


def test_every_preset_has_a_tiny_run():
    assert set(PRESET_NAMES) >= RUN_ELSEWHERE


def test_surfels_run_both_stages_and_read_back_as_surfels(color_session, tmp_path):
    """stage1.surfels: stage I's discs start flat (the third scale a hundredth of the others),
    both stages render them as discs, and each checkpoint reads back rendering the same."""
    from evcap.recon.evaluate.views import render_views
    from evcap.recon.export import load_checkpoint, load_material_checkpoint
    from evcap.recon.scene.optics import SensorOptics

    config = preset("tiny", {"stage1.surfels": True}).stage1
    with Session.open(color_session) as s:
        data = load_training_data(s, config, "cpu")
        optics = SensorOptics.from_session(s)
        pose = GroundTruth.read(s).held_out_views().T_world_cam[:1]
    start = new_field(data, config, 0, "cpu", "cpu")
    s = start.gaussians.log_scales.detach()
    assert start.surfels and torch.allclose(s[:, 2], s[:, :2].min(1).values + np.log(0.01))
    settings = {"stage1.surfels": True, "stage1.iterations": 20, "stage2.iterations": 4}
    reconstruct(color_session, tmp_path, ReconstructOptions(preset="tiny", settings=settings))
    folder = ReconstructionFolder(tmp_path)
    field, config = load_checkpoint(folder.checkpoint("radiance"))
    material = load_material_checkpoint(folder.checkpoint("material"))
    assert config.surfels and field.surfels and material.surfels
    seen = render_views(field, pose, optics)["depth"]
    field.surfels = False  # the same Gaussians as 3D Gaussians render otherwise
    assert not np.allclose(render_views(field, pose, optics)["depth"], seen)
