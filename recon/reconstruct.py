"""`evcap reconstruct`: a session in, a reconstruction folder out.

Stage I (radiance) fits the Gaussians' geometry and radiance; stage II (material) decomposes it
into base color, roughness, normals and the light. `--stage material` resumes from OUT's stage-I
checkpoint.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import assert_never

import numpy as np
import torch

from evcap.errors import InputError
from evcap.recon import resume as resume_
from evcap.recon.config import ABLATIONS, DEVICES, Backend, Device, Stage
from evcap.recon.evaluate.metrics import image_metrics, normal_mae_deg, object_metrics
from evcap.recon.evaluate.views import (
    material_metrics,
    metrics,
    relit_metrics,
    render_views,
    shown_gain,
)
from evcap.recon.export import (
    load_checkpoint,
    read_stage_one_settings,
    save_checkpoint,
    save_material_checkpoint,
    write_image,
    write_ply,
    write_views,
)
from evcap.recon.material.config import MaterialConfig
from evcap.recon.material.stage import (
    MaterialFit,
    environment_image,
    light_from_image,
    resume_misfit,
    train_material,
)
from evcap.recon.options import Feedback, ReconstructOptions, Resume
from evcap.recon.radiance.config import RadianceConfig
from evcap.recon.radiance.stage import (
    Fit,
    RadianceField,
    TrainingData,
    load_training_data,
    train_radiance,
)
from evcap.recon.raster.rasterize import pick_backend
from evcap.recon.scene.cube_map import mip_chain
from evcap.recon.scene.optics import SensorOptics
from evcap.recon.settings import NONE, to_dict
from evcap.records import (
    Figures,
    GroundTruth,
    Poses,
    ReconstructionFolder,
    ReconstructionResult,
    TruthViews,
)
from evcap.records.reconstruction_folder import Training
from evcap.session import Session
from evcap.trajectory_alignment import apply_similarity, pose_errors

DEFAULTS, SILENT = ReconstructOptions(), Feedback()
TRACK_VIEWS = 8  # views rendered along the path when the session has no held-out views
HISTORY_VIEWS = 2  # held-out views rendered for the accuracy-versus-time curve


def pick_device(name: Device) -> Device:
    """The device asked for, if PyTorch can use it here."""
    if name not in DEVICES:
        raise InputError(f"unknown device {name!r}; expected cpu or cuda")
    match name:
        case "cpu":
            pass
        case "cuda":
            if not torch.cuda.is_available():
                raise InputError(
                    "--device cuda: no CUDA GPU is visible to PyTorch here; use --device cpu"
                )
        case _:
            assert_never(name)
    return name


def _trainings(stage: Stage) -> tuple[Training, ...]:
    """What a stage runs: stage I, stage II (from OUT's stage-I checkpoint), or both."""
    match stage:
        case "radiance" | "material":
            return (stage,)
        case "all":
            return ("radiance", "material")
        case _:
            assert_never(stage)


def read_environment(path: str | Path) -> np.ndarray:
    """A latitude-longitude environment image (HDR as it is, 8/16-bit from sRGB), linear."""
    from evcap.images import read_image_linear

    path = Path(path)
    if not path.exists():
        raise InputError(f"--relight {path}: no such file")
    image = read_image_linear(path)
    if not np.isfinite(image).all() or image.shape[1] < 2 * image.shape[0] - 2:
        raise InputError(
            f"--relight {path}: expected a latitude-longitude image (twice as wide as tall) "
            "of finite values"
        )
    return image


@dataclass(frozen=True)
class Plan:
    """What a reconstruction will do, settled before it reads the events: the stages it runs,
    their settings (stage I's from OUT's checkpoint when it runs stage II alone), the device
    and rasterizer, the new light."""

    options: ReconstructOptions
    out: ReconstructionFolder
    runs: tuple[Training, ...]
    stage1: RadianceConfig
    stage2: MaterialConfig
    device: Device
    backend: Backend
    environment: np.ndarray | None  # --relight's, linear

    @property
    def fits_radiance(self) -> bool:
        return "radiance" in self.runs

    @property
    def fits_material(self) -> bool:
        return "material" in self.runs

    def saved_settings(self, session: Session) -> dict[Training, dict]:
        """What each stage's saved state is checked against before it is gone on from."""
        o = self.options
        stage1 = {"config": to_dict(self.stage1), "seed": o.seed}
        stage1["session"] = resume_.session_fingerprint(session)
        stage2 = {**stage1, "material": to_dict(self.stage2), "ablate": sorted(o.ablate)}
        return {"radiance": stage1, "material": stage2}


@dataclass
class Run:
    """A reconstruction under way: the training data, the saved states it goes on from, the
    truth it is scored on, the field stage II starts from, the result so far."""

    data: TrainingData
    settings: dict[Training, dict]  # Plan.saved_settings
    states: dict[Training, dict | None]
    truth: TruthViews
    gt: GroundTruth | None
    environment: np.ndarray | None  # the new light: --relight's, or the truth's second light
    result: ReconstructionResult
    before: ReconstructionResult  # what OUT's metrics.json held, when a stage goes on
    field: RadianceField | None = None
    stopped: bool = False

    def poses_of(self, track: Poses) -> np.ndarray:
        return _view_poses(track, self.data.windows.frame_times, self.truth, self.gt)


def reconstruct(
    session_path: str | Path,
    out: str | Path,
    options: ReconstructOptions = DEFAULTS,
    feedback: Feedback = SILENT,
) -> ReconstructionResult:
    """Run the reconstruction as ``options`` say; returns what it wrote to OUT/metrics.json.
    A stage interrupted in OUT goes on from where it stopped, or starts over, as
    ``options.resume`` says; stage I refines the trajectory when its settings say so
    (stage1.poses.refine) and writes it to OUT/poses.h5."""
    plan = plan_reconstruction(out, options)
    started = time.perf_counter()
    with Session.open(session_path) as session:
        run = _start(plan, session, feedback.say)
        if plan.fits_radiance and run.states["material"] is None:
            _stage_one(plan, run, feedback, started)
        if plan.fits_material and not run.stopped:
            _stage_two(plan, run, session, feedback)
    _write(plan, run, session_path)
    return run.result


def plan_reconstruction(out: str | Path, options: ReconstructOptions) -> Plan:
    """The stages, their settings, the device and rasterizer, the new light; every option
    checked before the session is read."""
    runs = _trainings(options.stage)
    folder = ReconstructionFolder(out)
    settings = options.resolved()
    environment = read_environment(options.relight) if options.relight is not None else None
    device = pick_device(options.device)
    backend = pick_backend(options.backend, device)
    stage1 = settings.stage1
    if "radiance" not in runs:
        stage1 = read_stage_one_settings(folder.checkpoint("radiance"))
    return Plan(options, folder, runs, stage1, settings.stage2, device, backend, environment)


def _start(plan: Plan, session: Session, say: Callable[[str], None]) -> Run:
    """The saved states to go on from, the training data, the truth."""
    out = plan.out
    settings = plan.saved_settings(session)
    states = _saved_states(out, plan.runs, settings, plan.options.resume, say)
    field = None
    if not plan.fits_radiance or states["material"] is not None:
        field, _ = load_checkpoint(out.checkpoint("radiance"), plan.device, plan.backend)
    stage_one = field if states["material"] is not None else None
    start_over = plan.options.resume != "go on"
    data = _data_to_go_on_with(
        session, plan.stage1, plan.device, out, states, stage_one, start_over, say
    )
    # stage I is not run again for stage II alone, nor to go on with an interrupted stage II
    if field is not None and out.poses.exists():  # stage II goes on the path stage I refined
        data.track = Poses.read_file(out.poses)
    gt = GroundTruth.read(session) if GroundTruth.present(session) else None
    truth = gt.held_out_views() if gt is not None else TruthViews(np.zeros((0, 4, 4)))
    environment = plan.environment
    if environment is not None:  # another light than the truth's: shown, not scored
        truth = truth.without("relit_radiance")
    elif gt is not None and truth.relit_radiance is not None:
        environment = gt.relight_environment.astype(np.float64)
    out.root.mkdir(parents=True, exist_ok=True)
    going_on = field is not None or states["radiance"] is not None
    before = out.previous_result() if going_on else ReconstructionResult()
    result = before if field is not None else ReconstructionResult()
    return Run(data, settings, states, truth, gt, environment, result, before, field)


def _stage_one(plan: Plan, run: Run, feedback: Feedback, started: float) -> None:
    """Stage I, its outputs, and its part of the result."""
    config, state = plan.stage1, run.states["radiance"]
    if state is not None:
        feedback.say(_going_on("stage I", state, config.iterations))
    fit, figures, run.data.track = _stage_radiance(plan, run, feedback.progress)
    run.field = fit.field
    result = run.result
    result.figures = Figures.of(figures)
    result.seconds = time.perf_counter() - started
    if state is not None:  # and the time it took before
        result.seconds += run.before.seconds or 0.0
    o = plan.options
    result.preset, result.seed = o.preset, o.seed
    result.zero_events = config.event_loss.zero_events
    result.iterations, result.gaussians = fit.steps, len(fit.field.gaussians)
    result.device, result.backend = plan.device, plan.backend
    result.interrupted, result.history = fit.interrupted, fit.history
    result.training_log["radiance"] = [dataclasses.asdict(x) for x in fit.log]
    run.stopped = fit.interrupted


def _stage_two(plan: Plan, run: Run, session: Session, feedback: Feedback) -> None:
    """Stage II, its outputs, and its part of the result."""
    state, out = run.states["material"], plan.out
    if state is not None:
        feedback.say(_going_on("stage II", state, plan.stage2.iterations))
    earlier = (run.before.material_seconds or 0.0) if state is not None else 0.0
    started = time.perf_counter()
    path = out.training_state("material")
    fit = train_material(
        run.field,
        run.data,
        session,
        plan.stage1,
        plan.stage2,
        seed=plan.options.seed,
        device=plan.device,
        progress=feedback.progress,
        ablate=frozenset(plan.options.ablate),
        resume=state,
        save_state=lambda s: resume_.save_state(path, s, run.settings["material"]),
    )
    result = run.result
    figures = result.figures
    if figures.normal_mae_deg is not None and figures.radiance_normal_mae_deg is None:
        figures.radiance_normal_mae_deg = figures.normal_mae_deg
    poses = run.poses_of(run.data.track)
    found = _material_outputs(
        fit, run.field, poses, run.truth, run.data.optics, run.environment, out, plan.device
    )
    result.figures = dataclasses.replace(figures, **Figures.of(found).measured())
    result.material_iterations = fit.steps
    ablate = plan.options.ablate
    result.effects = {**fit.field.effects, **{k: k not in ablate for k in ABLATIONS}}
    result.effect_variation = fit.field.start_variation or None
    result.relit = run.environment is not None
    result.material_seconds = time.perf_counter() - started + earlier
    result.interrupted = fit.interrupted
    result.training_log["material"] = [dataclasses.asdict(x) for x in fit.log]
    if not fit.interrupted:
        path.unlink(missing_ok=True)


def _write(plan: Plan, run: Run, session_path: str | Path) -> None:
    """OUT/config.toml and OUT/metrics.json; the refined poses into the session when asked."""
    o, out, result = plan.options, plan.out, run.result
    result.views = "held-out test views" if run.truth.maps() else "views along the camera path"
    sections = {
        "reconstruct": {
            "session": str(session_path),
            "stage": o.stage,
            "preset": o.preset,
            "device": plan.device,
            "backend": plan.backend,
            "seed": o.seed,
            "ablate": ",".join(o.ablate),
            "relight": str(o.relight) if o.relight else None,
        },
        "stage1": to_dict(plan.stage1, NONE),
    }
    if plan.fits_material:
        sections["stage2"] = to_dict(plan.stage2, NONE)
    out.write_config(sections)
    out.write_result(result)
    # an interrupted run's poses are not the session's yet: it goes on from the session's
    if o.write_poses and out.poses.exists() and not result.interrupted:
        Poses.read_file(out.poses).write(session_path)


def _view_poses(
    track: Poses, frame_times: np.ndarray, truth: TruthViews, gt: GroundTruth | None
) -> np.ndarray:
    """The poses of the views scored (the truth's held-out views) or shown (along the path),
    in the world of ``track``. A refined track's world is the estimate's, moved a little
    (its gauge is its first keyframe): the held-out views are brought into it by the
    similarity that best maps it onto the true path (by orientations and centres)."""
    if not len(truth):
        times = np.linspace(frame_times[0], frame_times[-1], TRACK_VIEWS).astype(np.int64)
        return track.at(times)
    if gt is None or "refinement_keyframes" not in track.notes:
        return truth.T_world_cam
    true = gt.poses()
    inside = (track.t >= true.start) & (track.t <= true.end)
    fit = pose_errors(track.T_world_cam[inside], true.at(track.t[inside]), by="poses")
    scale, R = fit["scale"], fit["R"]
    return apply_similarity(truth.T_world_cam, 1 / scale, R.T, -R.T @ fit["t"] / scale)


def _saved_states(
    out: ReconstructionFolder,
    runs: tuple[Training, ...],
    settings: dict,
    resume: Resume,
    say: Callable[[str], None],
) -> dict[Training, dict | None]:
    """The training states to go on from ({"radiance": ..., "material": ...}, None where a
    stage starts afresh), as ``resume`` says: what OUT holds is replaced only when it may
    start over; why a saved state is not gone on from is said."""
    states: dict[Training, dict | None] = {"radiance": None, "material": None}
    start_over = resume != "go on"
    for name in runs if resume != "start over" else ():
        path = out.training_state(name)
        try:
            state = resume_.load_state(path)
        except InputError as e:
            state, why, remedy = None, str(e), "pass --force to start over"
        else:
            why = resume_.misfit(state, settings[name]) if state is not None else ""
            remedy = resume_.remedy(state) if why else ""
        if why:
            _refuse_or_say(out, name, why, remedy, start_over, say)
        states[name] = None if why else state
    if states["radiance"] is not None:
        states["material"] = None  # stage II starts afresh after it
    nothing_saved = all(v is None for v in states.values())
    if nothing_saved and out.stage_done(runs[0]) and not start_over:
        raise InputError(
            f"{out} already holds a reconstruction; choose another folder or pass --force"
        )
    # a stage that runs afresh makes what was saved of it (and, for stage I, of stage II) old
    for name in states if "radiance" in runs else runs:
        if states[name] is None:
            out.training_state(name).unlink(missing_ok=True)
    return states


def _data_to_go_on_with(
    session: Session,
    config: RadianceConfig,
    device: Device,
    out: ReconstructionFolder,
    states: dict[Training, dict | None],
    stage_one: RadianceField | None,
    start_over: bool,
    say: Callable[[str], None],
) -> TrainingData:
    """The training data; for a stage that goes on, with what it derived at its start, once
    the checks that need the session's events (and for stage II, the stage I beside it, the
    ``stage_one`` field, and the path it refined) find its state fits. One that does not is
    refused, or where it may ``start_over`` said and dropped (from ``states`` and OUT)."""
    name: Training = "radiance" if states["radiance"] is not None else "material"
    state = states[name]
    if state is None:
        return load_training_data(session, config, device)
    data = load_training_data(session, config, device, state["data"])
    why = ""
    if state["data"]["windows"] != data.windows.digest():
        why = "the session's events, as this evcap counts them, are not those it was fitted to"
    elif name == "material":
        track = Poses.read_file(out.poses) if out.poses.exists() else data.track
        why = resume_misfit(state, stage_one, track)
    if not why:
        return data
    _refuse_or_say(out, name, why, "pass --force to start over", start_over, say)
    states[name] = None
    out.training_state(name).unlink(missing_ok=True)
    return load_training_data(session, config, device)


def _refuse_or_say(
    out: ReconstructionFolder,
    name: Training,
    why: str,
    remedy: str,
    start_over: bool,
    say: Callable[[str], None],
) -> None:
    """A saved state that cannot be gone on with: refused (InputError), or where the stage may
    ``start_over`` said, for it to start over."""
    stage = "stage I" if name == "radiance" else "stage II"
    if not start_over:
        raise InputError(
            f"{out} holds a reconstruction interrupted in {stage} that cannot be gone on with "
            f"({why}); {remedy}"
        )
    say(f"{stage}: starting over; the state it saved cannot be gone on with ({why})")


def _going_on(name: str, state: dict, iterations: int) -> str:
    return (
        f"{name}: going on from step {state['step']:,} of {iterations:,} (saved when it was "
        f"interrupted, {state['seconds']:.0f} s in)"
    )


def _stage_radiance(
    plan: Plan, run: Run, progress: Callable[[int, int, str], None] | None
) -> tuple[Fit, dict[str, float | None], Poses]:
    """Stage I and its outputs; (the fit, its figures on the views at ``run.poses_of`` the
    trajectory, the trajectory: refined when the settings say so, written to OUT/poses.h5)."""
    data, truth, out, device = run.data, run.truth, plan.out, plan.device
    config = plan.stage1
    poses_of = run.poses_of
    poses = poses_of(data.track)  # the evaluations along the way: the input's

    def evaluate(field: RadianceField) -> dict:
        views = render_views(field, poses[:HISTORY_VIEWS], data.optics, device)
        seen = truth[:HISTORY_VIEWS]
        out = {"views": len(seen), **image_metrics(views["radiance"], seen.radiance, "render")}
        mask = seen.object_mask()
        if mask is not None:
            out.update(object_metrics(views["radiance"], seen.radiance, mask))
        if seen.normal is not None:
            out["normal_mae_deg"] = normal_mae_deg(views["normal"], seen.normal)
        return out

    path = out.training_state("radiance")
    fit = train_radiance(
        data,
        config,
        seed=plan.options.seed,
        device=device,
        backend=plan.backend,
        progress=progress,
        evaluate=evaluate if truth.radiance is not None else None,
        resume=run.states["radiance"],
        save_state=lambda s: resume_.save_state(path, s, run.settings["radiance"]),
    )
    field = fit.field
    track = data.track
    if fit.corrections is not None:
        track = fit.corrections.refined(track)
        track.write_file(out.poses)
    else:
        out.poses.unlink(missing_ok=True)
    views = render_views(field, poses_of(track), data.optics, device)
    scored = bool(truth.maps())
    figures = metrics(views, truth) if scored else {}
    write_ply(field, out.ply)
    write_views(
        views, out, "radiance", "test" if scored else "path", shown_gain(views["radiance"], truth)
    )
    save_checkpoint(field, to_dict(config), out.checkpoint("radiance"))
    if not fit.interrupted:
        path.unlink(missing_ok=True)
    return fit, figures, track


def _material_outputs(
    fit: MaterialFit,
    radiance: RadianceField,
    poses: np.ndarray,
    truth: TruthViews,
    optics: SensorOptics,
    environment: np.ndarray | None,
    out: ReconstructionFolder,
    device: Device,
) -> dict[str, float | None]:
    """Stage II's renders, light, relit views, checkpoint; its figures, with what stage I's
    radiance (``radiance``, the field) reaches in their place."""
    field = fit.field
    views = render_views(field, poses, optics, device)
    scored = bool(truth.maps())
    figures: dict[str, float | None] = {}
    before = render_views(radiance, poses, optics, device)["radiance"] if scored else None
    if scored:
        figures.update(material_metrics(views, truth, before))
    split = "test" if scored else "path"
    write_views(views, out, "material", split, shown_gain(views["radiance"], truth))
    light = mip_chain(field.light.radiance_faces().detach())
    write_image(environment_image(light), out.environment)
    if environment is not None:
        new = light_from_image(environment, light[0].shape[-1], device)
        relit = render_views(field, poses, optics, device, new)
        gain = shown_gain(views["radiance"], truth)
        if truth.relit_radiance is not None and gain is not None:
            # the new light in the model's units (its radiance is the truth's over the gain),
            # the render taken back by the same gain: nothing fitted to the relit truth
            k = torch.as_tensor(gain, dtype=torch.float32, device=device)[None, :, None, None]
            scaled = render_views(field, poses, optics, device, [f / k for f in new])
            corrected = scaled["radiance"] * gain
            figures.update(relit_metrics(relit["radiance"], corrected, truth, before))
        out.renders("relit").mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out.views_values("relit", split), radiance=relit["radiance"])
        for i, image in enumerate(relit["radiance"]):
            write_image(image, out.view_image("relit", split, i, "radiance"))
        write_image(environment_image(new), out.relit_environment)
    save_material_checkpoint(field, out.checkpoint("material"))
    return figures
