"""`evcap demo`: the whole of evcap on a bundled capture, with no camera.

Two hardware-replay fixtures (app/demo_data/demo-scene and demo-calibration, made by the
simulator) are recorded through the real driver, then the pipeline runs on the scene's: the
calibration recording calibrates it, the poses come from its events, they are registered to the
simulator's truth (so that the held-out views are scored), the reconstruction runs both stages
and the report shows it all. Each step is saved as it ends, so a second run goes on from the
first step not yet done.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from pathlib import Path

from evcap.app.compile_ahead import KernelsAhead
from evcap.errors import InputError, OutputExistsError
from evcap.pipeline import Pipeline, Progress, Settings, StepDefinition, Workspace
from evcap.recon.config import Preset
from evcap.recon.options import ReconstructOptions

FIXTURES = Path(__file__).resolve().parent / "demo_data"  # package data: in the wheel too
SCENE, CALIBRATION = "demo-scene", "demo-calibration"  # the captures
SCENE_FILE, CALIBRATION_FILE = "scene.h5", "calibration.h5"  # their recordings, in DIR
PRESETS: tuple[Preset, ...] = ("small", "fast")  # recon's presets that a CPU runs in minutes
SMALL = ReconstructOptions(preset="small")  # the demo's reconstruction
EARLIER_STATE = "demo.json"  # the state file of the demo before it ran on the pipeline


def demo_workspace(out: str | Path) -> Workspace:
    """DIR/scene.h5 (the scene's recording, the pipeline's session), DIR/calibration.h5."""
    return Workspace(Path(out), SCENE_FILE, calibration=Path(out) / CALIBRATION_FILE)


def demo_pipeline(
    out: str | Path,
    options: ReconstructOptions = SMALL,
    *,
    fixtures: str | Path | None = None,
    say: Callable[[str], None] = print,
    progress: Progress | None = None,
    ahead: KernelsAhead | None = None,
) -> Pipeline:
    """The pipeline with the demo's steps: starting the compilation of the reconstruction's
    kernels in a second process (``ahead``) and recording the two captures, first; registering
    the estimated poses to the truth, after the poses; the compiled kernels waited for, before
    the reconstruction."""
    ws = demo_workspace(out)
    fixtures = Path(fixtures) if fixtures is not None else FIXTURES
    settings = Settings(reconstruct=options)
    pipeline = Pipeline(
        ws, settings, say=say, progress=progress, hint="pass --force to start the demo over"
    )
    ahead = ahead or KernelsAhead()
    pipeline.add(
        StepDefinition(
            "compile the reconstruction's kernels (a second process, beside the next steps)",
            lambda: ahead.start(fixtures, options.preset),
            lambda: True,
        ),
        before="calibrate",
    )
    for fixture, path in ((CALIBRATION, ws.root / CALIBRATION_FILE), (SCENE, ws.session)):
        pipeline.add(
            StepDefinition(
                f"record {path.name} (replayed through the driver)",
                lambda f=fixture, p=path: record_fixture(fixtures / f, p),
                path.exists,
            ),
            before="calibrate",
        )
    pipeline.add(
        StepDefinition("the compiled kernels", ahead.finish, lambda: True), before="reconstruct"
    )
    pipeline.add(
        StepDefinition(
            "register the poses to the simulator's truth",
            lambda: _register(fixtures / SCENE / "truth.h5", ws.session),
            ws.session.exists,
        ),
        before="reconstruct",
    )
    return pipeline


def run_demo(
    out: str | Path,
    options: ReconstructOptions = SMALL,
    *,
    fixtures: str | Path | None = None,
    force: bool = False,
    say: Callable[[str], None] = print,
    progress: Progress | None = None,
) -> Path:
    """Run (or go on with) the demo into ``out``, the reconstruction as ``options`` say;
    returns the report's path."""
    from evcap._progress import progress_bar

    if options.preset not in PRESETS:
        raise InputError(f"unknown preset {options.preset!r}; expected one of {', '.join(PRESETS)}")
    fixtures = Path(fixtures) if fixtures is not None else FIXTURES
    for name in (SCENE, CALIBRATION):
        if not (fixtures / name / "bulk.bin").exists():
            raise InputError(
                f"the demo's capture {fixtures / name} is missing: it ships with evcap "
                "(app/demo_data/); reinstall evcap, or name the folder with --fixtures"
            )
    ws = demo_workspace(out)
    _prepare(ws, force)
    ahead = KernelsAhead()  # ended below if the demo ends first (an error, Ctrl-C)
    pipeline = demo_pipeline(
        out,
        options,
        fixtures=fixtures,
        say=say,
        progress=progress or progress_bar,
        ahead=ahead,
    )
    started = time.perf_counter()
    try:
        pipeline.run()
    finally:
        ahead.stop()
    say(f"the demo took {time.perf_counter() - started:.0f} s here; open {ws.report}")
    return ws.report


def _prepare(ws: Workspace, force: bool) -> None:
    """The demo's folder: made, or one that holds a demo (started over with ``force``); never
    a folder of something else."""
    earlier = (ws.root / EARLIER_STATE).exists()
    holds_demo = ws.state.exists() or earlier
    if earlier and not force:
        raise InputError(
            f"{ws.root} holds a demo made by an earlier evcap; pass --force to start it over"
        )
    if force and ws.root.exists():
        if not holds_demo and any(ws.root.iterdir()):
            raise OutputExistsError(
                f"{ws.root} is not empty and holds no demo: --force only starts a demo folder over"
            )
        shutil.rmtree(ws.root)
        holds_demo = False
    if not holds_demo and ws.root.exists() and any(ws.root.iterdir()):
        raise OutputExistsError(f"{ws.root} is not empty and holds no demo; choose another -o")
    ws.root.mkdir(parents=True, exist_ok=True)


def record_fixture(fixture: Path, path: Path) -> str:
    """Record a capture (a hardware-replay fixture) through the driver into ``path``."""
    from evcap.acquire.device import Davis346
    from evcap.acquire.recorder import Recorder, RecordOptions

    with Davis346.open(f"replay:{fixture}") as camera:
        recorder = Recorder(camera, path, RecordOptions(overwrite=True))
        r = recorder.run()
    if r.end_reason != "end of replay":
        raise InputError(f"recording {fixture.name} ended early ({r.end_reason}: {r.error})")
    return f"{r.events:,} events, {r.frames:,} frames, {r.imu:,} IMU samples into {path.name}"


def _register(truth_file: Path, session: Path) -> str:
    """Bring the simulator's truth into the session and the estimated poses onto it (a
    similarity), so that the reconstruction is measured against the true held-out views. Only
    the evaluation uses the truth: the poses were estimated from the events alone."""
    from evcap.records import GroundTruth, Poses
    from evcap.session import Session
    from evcap.sim.truth import copy_truth
    from evcap.trajectory_alignment import apply_similarity, errors_against_truth, pose_errors

    copy_truth(truth_file, session, replace=True)
    with Session.open(session) as s:
        poses = Poses.read(s)
        truth = GroundTruth.read(s).poses()
    # fitted over the estimate's poses (the truth interpolated between its views there)
    t = poses.t
    inside = (t >= truth.start) & (t <= truth.end)
    fit = pose_errors(poses.T_world_cam[inside], truth.at(t[inside]), by="poses")
    scale, R, shift = fit["scale"], fit["R"], fit["t"]
    registered = poses.replace(
        T_world_cam=apply_similarity(poses.T_world_cam, scale, R, shift),
        points_xyz=None if poses.points_xyz is None else scale * poses.points_xyz @ R.T + shift,
        scale="metric: registered to the simulator's truth by a similarity",
    )
    # the errors as the report shows them: at the truth's own poses, where it is exact
    errors = errors_against_truth(registered, truth)
    notes = {k: errors[k] for k in ("rotation_median_deg", "translation_median_pct")}
    registered.replace(notes=notes).write(session)
    return (
        f"against the truth: rotation {errors['rotation_median_deg']:.2f} deg, translation "
        f"{errors['translation_median_pct']:.2f} % of the path (medians over its "
        f"{errors['compared']} poses)"
    )
