"""`evcap reconstruct`: a session in, a reconstruction folder out.

Stage I (radiance) fits the Gaussians' geometry and radiance; stage II (material) decomposes it
into base color, roughness, normals and the light. `--stage material` resumes from OUT's stage-I
checkpoint.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import assert_never

import numpy as np
import torch

from evcap.errors import InputError
from evcap.recon import config as cfg
from evcap.recon import resume as resume_
from evcap.recon.config import (
    ABLATIONS,
    DEVICES,
    REFINE_POSES,
    STAGES,
    Ablation,
    Backend,
    Device,
    EffectMode,
    Preset,
    RefinePoses,
    Stage,
    ZeroEvents,
)
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
    save_checkpoint,
    save_material_checkpoint,
    write_image,
    write_ply,
    write_views,
)
from evcap.recon.material.stage import (
    MaterialFit,
    environment_image,
    light_from_image,
    resume_misfit,
    train_material,
)
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

TRACK_VIEWS = 8  # views rendered along the path when the session has no held-out views
HISTORY_VIEWS = 2  # held-out views rendered for the accuracy-versus-time curve
ESTIMATED = ("evcap poses", "evcap reconstruct")  # sources of poses --refine-poses auto refines


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


def reconstruct(
    session_path: str | Path,
    out: str | Path,
    *,
    preset: Preset = "fast",
    stage: Stage = "all",
    device: Device = "cpu",
    backend: Backend | None = None,
    resolution: float | None = None,
    iterations: int | None = None,
    material_iterations: int | None = None,
    seed: int = 0,
    zero_events: ZeroEvents | None = None,
    radiance_settings: dict | None = None,
    material_settings: dict | None = None,
    visibility: EffectMode | None = None,
    indirect: EffectMode | None = None,
    ablate: tuple[Ablation, ...] = (),
    relight: str | Path | None = None,
    refine_poses: RefinePoses = "auto",
    write_poses: bool = False,
    overwrite: bool = False,
    resume: bool = True,
    say: Callable[[str], None] = lambda line: None,
    progress: Callable[[int, int, str], None] | None = None,
) -> ReconstructionResult:
    """Run the reconstruction; returns what it wrote to OUT/metrics.json. ``radiance_settings``,
    ``material_settings``: stage I's and stage II's (RadianceConfig's, MaterialConfig's fields)
    over the preset's. With ``resume``, a
    stage interrupted in OUT with the same session and settings goes on from where it
    stopped; ``overwrite`` lets a finished (or differently started) one be replaced.
    ``refine_poses``: stage I refines the trajectory (auto: when evcap estimated it) and writes
    it to OUT/poses.h5; ``write_poses`` also makes it the session's /poses."""
    if stage not in STAGES:
        raise InputError(f"unknown stage {stage!r}; expected one of {', '.join(STAGES)}")
    if refine_poses not in REFINE_POSES:
        raise InputError(f"--refine-poses must be one of {', '.join(REFINE_POSES)}")
    if set(ablate) - set(ABLATIONS):
        raise InputError(f"unknown ablation(s) {sorted(set(ablate) - set(ABLATIONS))}")
    runs = _trainings(stage)
    fits_radiance, fits_material = "radiance" in runs, "material" in runs
    out = ReconstructionFolder(out)
    named = {"iterations": material_iterations, "visibility": visibility, "indirect": indirect}
    named = {k: v for k, v in named.items() if v is not None}
    mconfig = cfg.material_preset(preset, **{**(material_settings or {}), **named})
    environment = read_environment(relight) if relight is not None else None
    device = pick_device(device)
    backend = pick_backend(backend, device)
    if not fits_radiance:
        field, settings = load_checkpoint(out.checkpoint("radiance"), device, backend)
        config = cfg.RadianceConfig(**settings)
    else:
        named = {"resolution": resolution, "iterations": iterations, "zero_events": zero_events}
        named = {k: v for k, v in named.items() if v is not None}
        overrides = {**(radiance_settings or {}), **named}
        config = cfg.preset(preset, **overrides)
    started = time.perf_counter()
    with Session.open(session_path) as session:
        if fits_radiance and Poses.present(session):  # else a clear error comes below
            refines = _refines(refine_poses, Poses.read(session))
            config = dataclasses.replace(config, refine_poses=refines)
        session_id = resume_.session_fingerprint(session)
        settings = {
            "radiance": {"config": cfg.to_dict(config), "seed": seed, "session": session_id},
        }
        settings["material"] = {
            **settings["radiance"],
            "material": cfg.to_dict(mconfig),
            "ablate": sorted(ablate),
        }
        states = _saved_states(out, runs, settings, resume, overwrite, say)
        if fits_radiance and states["radiance"] is None and states["material"] is not None:
            field, _ = load_checkpoint(out.checkpoint("radiance"), device, backend)
        stage_one = field if states["material"] is not None else None
        data = _data_to_go_on_with(session, config, device, out, states, stage_one, overwrite, say)
        # stage I is not run again for stage II alone, nor to go on with an interrupted stage II
        skip = not fits_radiance or states["material"] is not None
        if skip and out.poses.exists():  # stage II goes on the path stage I refined
            data.track = Poses.read_file(out.poses)
        gt = GroundTruth.read(session) if GroundTruth.present(session) else None
        truth = gt.held_out_views() if gt is not None else TruthViews(np.zeros((0, 4, 4)))
        if environment is not None:  # another light than the truth's: shown, not scored
            truth = truth.without("relit_radiance")
        elif gt is not None and truth.relit_radiance is not None:
            environment = gt.relight_environment.astype(np.float64)

        def poses_of(track: Poses) -> np.ndarray:
            return _view_poses(track, data.windows.frame_times, truth, gt)

        poses = poses_of(data.track)
        out.root.mkdir(parents=True, exist_ok=True)
        resumed = skip or states["radiance"] is not None
        before = out.previous_result() if resumed else ReconstructionResult()
        result = before if skip else ReconstructionResult()
        stopped = False
        if not skip:
            if states["radiance"] is not None:
                say(_going_on("stage I", states["radiance"], config.iterations))
            fit, figures, data.track = _stage_radiance(
                data,
                config,
                poses_of,
                truth,
                out,
                seed,
                device,
                backend,
                progress,
                states["radiance"],
                settings["radiance"],
            )
            field = fit.field
            poses = poses_of(data.track)
            result.figures = Figures.of(figures)
            result.seconds = time.perf_counter() - started
            if states["radiance"] is not None:  # and the time it took before
                result.seconds += before.seconds or 0.0
            result.preset, result.seed, result.zero_events = preset, seed, config.zero_events
            result.iterations, result.gaussians = fit.steps, len(field.gaussians)
            result.device, result.backend = device, backend
            result.interrupted, result.history = fit.interrupted, fit.history
            result.training_log["radiance"] = [dataclasses.asdict(x) for x in fit.log]
            stopped = fit.interrupted
        if fits_material and not stopped:
            if states["material"] is not None:
                say(_going_on("stage II", states["material"], mconfig.iterations))
            earlier = (before.material_seconds or 0.0) if states["material"] is not None else 0.0
            started = time.perf_counter()
            path = out.training_state("material")
            mfit = train_material(
                field,
                data,
                session,
                config,
                mconfig,
                seed=seed,
                device=device,
                progress=progress,
                ablate=frozenset(ablate),
                resume=states["material"],
                save_state=lambda state: resume_.save_state(path, state, settings["material"]),
            )
    if fits_material and not stopped:
        figures = result.figures
        if figures.normal_mae_deg is not None and figures.radiance_normal_mae_deg is None:
            figures.radiance_normal_mae_deg = figures.normal_mae_deg
        found = _material_outputs(mfit, field, poses, truth, data.optics, environment, out, device)
        result.figures = dataclasses.replace(figures, **Figures.of(found).measured())
        result.material_iterations = mfit.steps
        result.effects = {**mfit.field.effects, **{k: k not in ablate for k in ABLATIONS}}
        result.effect_variation = mfit.field.start_variation or None
        result.relit = environment is not None
        result.material_seconds = time.perf_counter() - started + earlier
        result.interrupted = mfit.interrupted
        result.training_log["material"] = [dataclasses.asdict(x) for x in mfit.log]
        if not mfit.interrupted:
            out.training_state("material").unlink(missing_ok=True)
    result.views = "held-out test views" if truth.maps() else "views along the camera path"
    sections = {
        "reconstruct": {
            "session": str(session_path),
            "stage": stage,
            "preset": preset,
            "device": device,
            "backend": backend,
            "seed": seed,
            "ablate": ",".join(ablate),
            "relight": str(relight) if relight else None,
        },
        "radiance": cfg.to_dict(config),
    }
    if fits_material:
        sections["material"] = cfg.to_dict(mconfig)
    out.write_config(sections)
    out.write_result(result)
    # an interrupted run's poses are not the session's yet: it goes on from the session's
    if write_poses and out.poses.exists() and not result.interrupted:
        Poses.read_file(out.poses).write(session_path)
    return result


def _refines(choice: RefinePoses, track: Poses) -> bool:
    match choice:
        case "on":
            return True
        case "off":
            return False
        case "auto":
            return track.source.startswith(ESTIMATED)
        case _:
            assert_never(choice)


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
    resume: bool,
    overwrite: bool,
    say: Callable[[str], None],
) -> dict[Training, dict | None]:
    """The training states to go on from ({"radiance": ..., "material": ...}, None where a
    stage starts afresh); refuses to replace what OUT holds unless ``overwrite``, and says
    why a saved state is not gone on from."""
    states: dict[Training, dict | None] = {"radiance": None, "material": None}
    for name in runs if resume else ():
        path = out.training_state(name)
        try:
            state = resume_.load_state(path)
        except InputError as e:
            state, why, remedy = None, str(e), "pass --force to start over"
        else:
            why = resume_.misfit(state, settings[name]) if state is not None else ""
            remedy = resume_.remedy(state) if why else ""
        if why:
            _refuse_or_say(out, name, why, remedy, overwrite, say)
        states[name] = None if why else state
    if states["radiance"] is not None:
        states["material"] = None  # stage II starts afresh after it
    nothing_saved = all(v is None for v in states.values())
    if nothing_saved and out.stage_done(runs[0]) and not overwrite:
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
    config: cfg.RadianceConfig,
    device: Device,
    out: ReconstructionFolder,
    states: dict[Training, dict | None],
    stage_one: RadianceField | None,
    overwrite: bool,
    say: Callable[[str], None],
) -> TrainingData:
    """The training data; for a stage that goes on, with what it derived at its start, once
    the checks that need the session's events (and for stage II, the stage I beside it, the
    ``stage_one`` field, and the path it refined) find its state fits. One that does not is
    refused, or with ``overwrite`` said and dropped (from ``states`` and OUT)."""
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
    _refuse_or_say(out, name, why, "pass --force to start over", overwrite, say)
    states[name] = None
    out.training_state(name).unlink(missing_ok=True)
    return load_training_data(session, config, device)


def _refuse_or_say(
    out: ReconstructionFolder,
    name: Training,
    why: str,
    remedy: str,
    overwrite: bool,
    say: Callable[[str], None],
) -> None:
    """A saved state that cannot be gone on with: refused (InputError), or with ``overwrite``
    said, for the stage to start over."""
    stage = "stage I" if name == "radiance" else "stage II"
    if not overwrite:
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
    data: TrainingData,
    config: cfg.RadianceConfig,
    poses_of: Callable[[Poses], np.ndarray],
    truth: TruthViews,
    out: ReconstructionFolder,
    seed: int,
    device: Device,
    backend: Backend,
    progress: Callable[[int, int, str], None] | None,
    state: dict | None,
    settings: dict,
) -> tuple[Fit, dict[str, float | None], Poses]:
    """Stage I and its outputs; (the fit, its figures on the views at ``poses_of`` the
    trajectory, the trajectory: refined when the config says so, written to OUT/poses.h5)."""
    poses = poses_of(data.track)  # the evaluations along the way: the input's

    def evaluate(field: RadianceField) -> dict:
        views = render_views(field, poses[:HISTORY_VIEWS], data.optics, device)
        seen = truth[:HISTORY_VIEWS]
        out = image_metrics(views["radiance"], seen.radiance, "render")
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
        seed=seed,
        device=device,
        backend=backend,
        progress=progress,
        evaluate=evaluate if truth.radiance is not None else None,
        resume=state,
        save_state=lambda s: resume_.save_state(path, s, settings),
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
    save_checkpoint(field, cfg.to_dict(config), out.checkpoint("radiance"))
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
