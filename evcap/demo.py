"""`evcap demo`: the whole of evcap on a bundled capture, with no camera.

Two hardware-replay fixtures (evcap/demo_data/demo-scene and demo-calibration, made by the
simulator) are recorded through the real driver, the calibration recording calibrates the
scene's, the poses come from the scene's events, the reconstruction runs both stages and the
report shows it all. Each step is saved as it ends (DIR/demo.json), so a second run goes on
from the first step not yet done.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evcap.errors import InputError, OutputExistsError
from evcap.recon.config import PRESETS as RADIANCE_PRESETS

FIXTURES = Path(__file__).resolve().parent / "demo_data"  # package data: in the wheel too
SCENE, CALIBRATION = "demo-scene", "demo-calibration"
PRESETS = ("tiny", "fast")
# stage I of the demo's tiny: tiny's Gaussians for 1,000 steps at half scale (about a minute
# here), with fast's geometry terms, view dependence of degree 1, and half the starting
# Gaussians on the points structure from motion triangulated. Measured on the demo's capture
# (its estimated poses, two seeds each; object PSNR on the held-out views, constant color 17.2):
# tiny's own 150 steps 17.2 dB, normals 53 deg; 1,000 steps 18.8 dB (three seeds, 18.3 to
# 19.8), 31 deg, depth 13 %; with the points 19.2 dB, 22 deg, 5 %
STAGE_I = {
    "tiny": {
        "iterations": 1000,
        "resolution": 0.5,
        "sh_degree": 1,
        **{
            k: getattr(RADIANCE_PRESETS["fast"], k)
            for k in ("spread_weight", "background_first", "smooth_weight")
        },
        "init_on_points": 0.5,
    },
    "fast": {},
}
STATE = "demo.json"


class DemoInterrupted(KeyboardInterrupt):
    """A step was stopped (Ctrl-C); what the steps before it made is kept."""


@dataclass
class Step:
    name: str
    output: str  # what it makes, inside DIR
    run: Callable[[], str]  # returns a line saying what came out


@dataclass
class DemoContext:
    out: Path
    fixtures: Path
    preset: str
    progress: Callable[[str], object]  # a description -> a context manager giving update()
    say: Callable[[str], None] = print

    @property
    def scene(self) -> Path:
        return self.out / "scene.h5"

    @property
    def calibration(self) -> Path:
        return self.out / "calibration.h5"

    @property
    def reconstruction(self) -> Path:
        return self.out / "reconstruction"


def run_demo(
    out: str | Path,
    *,
    preset: str = "tiny",
    fixtures: str | Path | None = None,
    force: bool = False,
    say: Callable[[str], None] = print,
    progress: Callable[[str], object] | None = None,
) -> Path:
    """Run (or go on with) the demo into ``out``; returns the report's path."""
    from evcap._progress import progress_bar

    if preset not in PRESETS:
        raise InputError(f"unknown preset {preset!r}; expected one of {', '.join(PRESETS)}")
    out = Path(out)
    fixtures = Path(fixtures) if fixtures is not None else FIXTURES
    for name in (SCENE, CALIBRATION):
        if not (fixtures / name / "bulk.bin").exists():
            raise InputError(
                f"the demo's capture {fixtures / name} is missing: it ships with evcap "
                "(evcap/demo_data/); reinstall evcap, or name the folder with --fixtures"
            )
    state = _read_state(out, preset, force)
    ctx = DemoContext(out, fixtures, preset, progress or progress_bar, say)
    steps = demo_steps(ctx)
    started = time.perf_counter()
    redo = False
    for i, step in enumerate(steps, 1):
        head = f"[{i}/{len(steps)}] {step.name}"
        done = state["done"].get(step.name)
        if done and not redo and (out / step.output).exists():
            say(f"{head}: done before ({done['seconds']:.1f} s): {done['summary']}")
            continue
        if not redo:  # what follows a step that runs again is made again too
            redo = True
            for later in steps[i - 1 :]:
                state["done"].pop(later.name, None)
        say(f"{head} ...")
        t0 = time.perf_counter()
        try:
            summary = step.run()
        except KeyboardInterrupt:
            raise DemoInterrupted(
                f"stopped during '{step.name}'; run the same command again to go on from there"
            ) from None
        seconds = time.perf_counter() - t0
        state["done"][step.name] = {"seconds": seconds, "summary": summary}
        _write_state(out, state)
        say(f"{head}: {seconds:.1f} s: {summary}")
    report = out / "report.html"
    say(f"the demo took {time.perf_counter() - started:.0f} s here; open {report}")
    return report


def demo_steps(ctx: DemoContext) -> list[Step]:
    return [
        Step(
            "record the calibration recording (replayed through the driver)",
            "calibration.h5",
            lambda: _record(ctx, CALIBRATION, ctx.calibration),
        ),
        Step(
            "record the scene (replayed through the driver)",
            "scene.h5",
            lambda: _record(ctx, SCENE, ctx.scene),
        ),
        Step("calibrate", "calibration.h5", lambda: _calibrate(ctx)),
        Step("poses from the events", "scene.h5", lambda: _poses(ctx)),
        Step("register the poses to the simulator's truth", "scene.h5", lambda: _register(ctx)),
        Step(
            f"reconstruct, stage I: radiance ({ctx.preset})",
            "reconstruction/checkpoint/radiance.pt",
            lambda: _reconstruct(ctx, "radiance"),
        ),
        Step(
            f"reconstruct, stage II: material ({ctx.preset})",
            "reconstruction/checkpoint/material.pt",
            lambda: _reconstruct(ctx, "material"),
        ),
        Step("report", "report.html", lambda: _report(ctx)),
    ]


def _read_state(out: Path, preset: str, force: bool) -> dict:
    path = out / STATE
    if force and out.exists():
        if not path.exists() and any(out.iterdir()):
            raise OutputExistsError(
                f"{out} is not empty and holds no demo: --force only starts a demo folder over"
            )
        shutil.rmtree(out)
    fresh = {"preset": preset, "done": {}}
    if not path.exists():
        if out.exists() and any(out.iterdir()):
            raise OutputExistsError(f"{out} is not empty and holds no demo; choose another -o")
        out.mkdir(parents=True, exist_ok=True)
        return fresh
    try:
        state = json.loads(path.read_text())
        done = state["done"]
    except (ValueError, KeyError, TypeError):
        raise InputError(f"{path} is damaged; pass --force to start the demo over") from None
    if state.get("preset") != preset:
        raise InputError(
            f"{out} holds a demo made with --preset {state.get('preset')}; choose another -o, "
            "or pass --force to start over"
        )
    return {"preset": preset, "done": done}


def _write_state(out: Path, state: dict) -> None:
    tmp = out / (STATE + ".tmp")
    tmp.write_text(json.dumps(state, indent=1))
    tmp.replace(out / STATE)


def _record(ctx: DemoContext, fixture: str, path: Path) -> str:
    from evcap.acquire.device import Davis346
    from evcap.acquire.recorder import Recorder, RecordOptions

    with Davis346.open(f"replay:{ctx.fixtures / fixture}") as camera:
        recorder = Recorder(camera, path, RecordOptions(overwrite=True))
        r = recorder.run()
    if r.end_reason != "end of replay":
        raise InputError(f"recording {fixture} ended early ({r.end_reason}: {r.error})")
    return f"{r.events:,} events, {r.frames:,} frames, {r.imu:,} IMU samples into {path.name}"


def _calibrate(ctx: DemoContext) -> str:
    from evcap.calib.calibrate import calibrate, write_calibration

    with ctx.progress("calibrating") as update:
        cal = calibrate(ctx.calibration, progress=update)
    write_calibration([ctx.calibration, ctx.scene], cal)
    return cal.summary().replace("\n", "; ")


def _poses(ctx: DemoContext) -> str:
    from evcap.poses.estimate import estimate_poses, write_poses

    with ctx.progress("poses") as update:
        result = estimate_poses(ctx.scene, progress=update)
    write_poses(ctx.scene, result)
    return result.summary()


def _register(ctx: DemoContext) -> str:
    """Bring the simulator's truth into the session and the estimated poses onto it (a
    similarity), so that the reconstruction is measured against the true held-out views. Only
    the evaluation uses the truth: the poses were estimated from the events alone."""
    from evcap.records import GroundTruth, Poses
    from evcap.session import Session
    from evcap.sim.truth import copy_truth
    from evcap.trajectory_alignment import apply_similarity, pose_errors

    copy_truth(ctx.fixtures / SCENE / "truth.h5", ctx.scene, replace=True)
    with Session.open(ctx.scene) as s:
        poses = Poses.read(s)
        truth = GroundTruth.read(s).poses()
    t = poses.t
    inside = (t >= truth.start) & (t <= truth.end)
    errors = pose_errors(poses.T_world_cam[inside], truth.at(t[inside]), by="poses")
    scale, R, shift = errors["scale"], errors["R"], errors["t"]
    poses.replace(
        T_world_cam=apply_similarity(poses.T_world_cam, scale, R, shift),
        points_xyz=None if poses.points_xyz is None else scale * poses.points_xyz @ R.T + shift,
        scale="metric: registered to the simulator's truth by a similarity",
        notes={
            "rotation_median_deg": errors["rotation_median_deg"],
            "translation_median_pct": errors["translation_median_pct"],
        },
    ).write(ctx.scene)
    return (
        f"against the truth: rotation {errors['rotation_median_deg']:.2f} deg, translation "
        f"{errors['translation_median_pct']:.2f} % of the path (medians)"
    )


def _reconstruct(ctx: DemoContext, stage: str) -> str:
    from evcap.recon.reconstruct import POSES_FILE, reconstruct
    from evcap.records import Poses

    relight = None
    if stage == "material":
        relight = ctx.out / "relight.png"
        write_relight_environment(relight)
    with ctx.progress(f"stage {'I' if stage == 'radiance' else 'II'}") as update:
        m = reconstruct(
            ctx.scene,
            ctx.reconstruction,
            preset=ctx.preset,
            stage=stage,
            radiance_settings=STAGE_I[ctx.preset] if stage == "radiance" else None,
            relight=relight,
            overwrite=True,
            say=ctx.say,
            progress=update,
        )
    if m.interrupted:
        raise KeyboardInterrupt
    f = m.figures

    def show(value: float | None, scale: float = 1.0) -> float:
        return float("nan") if value is None else scale * value

    if stage == "radiance":
        refined = ""
        if (ctx.reconstruction / POSES_FILE).exists():
            notes = Poses.read_file(ctx.reconstruction / POSES_FILE).notes
            refined = f", poses refined (by {notes['refinement_median_deg']:.2f} deg, median)"
        return (
            f"{m.gaussians:,} Gaussians, {m.iterations} steps{refined}; held-out views: object "
            f"{show(f.object_psnr_cc):.1f} dB (a constant color "
            f"{show(f.object_psnr_constant):.1f} dB), normals "
            f"{show(f.normal_mae_deg):.1f} deg, depth {show(f.depth_rel_err, 100):.0f} % off"
        )
    return (
        f"{m.material_iterations} steps; base color {show(f.base_color_psnr_cc):.1f} dB, "
        f"roughness error {show(f.roughness_mae):.2f}, normals {show(f.normal_mae_deg):.1f} deg"
    )


def _report(ctx: DemoContext) -> str:
    from evcap.report.html import write_report

    page = write_report(ctx.reconstruction, ctx.scene)
    shutil.copyfile(page, ctx.out / "report.html")
    return f"{ctx.out / 'report.html'} ({page.stat().st_size / 1e6:.1f} MB, self-contained)"


def write_relight_environment(path: Path, height: int = 64) -> None:
    """A latitude-longitude sky for the relit views: a low warm sun over a dim blue sky
    (z up), unlike the scene's own light."""
    from evcap.recon.export import write_image

    elevation = (0.5 - (np.arange(height) + 0.5) / height)[:, None] * np.pi
    azimuth = ((np.arange(2 * height) + 0.5) / height)[None, :] * np.pi
    to_sun = np.cos(elevation) * np.cos(azimuth) * np.cos(0.3) + np.sin(elevation) * np.sin(0.3)
    glow = np.clip(to_sun, 0, 1) ** 64
    sky = np.where(elevation[..., None] > 0, [0.25, 0.35, 0.6], [0.15, 0.12, 0.1])
    write_image(np.clip(sky + glow[..., None] * [1.0, 0.7, 0.4], 0, 1), path)
