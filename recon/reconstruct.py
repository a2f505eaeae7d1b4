"""`evcap reconstruct`: a session in, a reconstruction folder out.

Stage I (radiance) fits the Gaussians' geometry and radiance; stage II (material) decomposes it
into base color, roughness, normals and the light. `--stage material` resumes from OUT's stage-I
checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from evcap.errors import InputError
from evcap.recon import config as cfg
from evcap.recon import resume as resume_
from evcap.recon.evaluate import (
    material_metrics,
    metrics,
    object_mask,
    relit_metrics,
    render_views,
    test_views,
)
from evcap.recon.export import (
    load_checkpoint,
    save_checkpoint,
    save_material_checkpoint,
    write_image,
    write_json,
    write_ply,
    write_toml,
    write_views,
)
from evcap.recon.material import environment_image, light_from_image, train_material
from evcap.recon.metrics import (
    fit_color_correction,
    image_metrics,
    normal_mae_deg,
    object_metrics,
)
from evcap.recon.radiance import load_training_data, train_radiance
from evcap.recon.rasterize import pick_backend
from evcap.recon.shading import mip_chain
from evcap.session import Session

STAGES = ("radiance", "material", "all")
ABLATIONS = ("anchor", "tv", "distill")
TRACK_VIEWS = 8  # views rendered along the path when the session has no held-out views
HISTORY_VIEWS = 2  # held-out views rendered for the accuracy-versus-time curve


def pick_device(name: str) -> str:
    if name not in ("cpu", "cuda"):
        raise InputError(f"unknown device {name!r}; expected cpu or cuda")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA GPU is visible to PyTorch here; use --device cpu")
    return name


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
    preset: str = "fast",
    stage: str = "all",
    device: str = "cpu",
    backend: str | None = None,
    resolution: float | None = None,
    iterations: int | None = None,
    material_iterations: int | None = None,
    seed: int = 0,
    zero_events: str | None = None,
    radiance_settings: dict | None = None,
    visibility: str | None = None,
    indirect: str | None = None,
    ablate: tuple[str, ...] = (),
    relight: str | Path | None = None,
    overwrite: bool = False,
    resume: bool = True,
    say: Callable[[str], None] = lambda line: None,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict:
    """Run the reconstruction; returns what went into OUT/metrics.json. ``radiance_settings``:
    stage I's (RadianceConfig's fields) over the preset's. With ``resume``, a
    stage interrupted in OUT with the same session and settings goes on from where it
    stopped; ``overwrite`` lets a finished (or differently started) one be replaced."""
    if stage not in STAGES:
        raise InputError(f"unknown stage {stage!r}; expected one of {', '.join(STAGES)}")
    if set(ablate) - set(ABLATIONS):
        raise InputError(f"unknown ablation(s) {sorted(set(ablate) - set(ABLATIONS))}")
    out = Path(out)
    mconfig = cfg.material_preset(
        preset, iterations=material_iterations, visibility=visibility, indirect=indirect
    )
    environment = read_environment(relight) if relight is not None else None
    device = pick_device(device)
    backend = pick_backend(backend, device)
    if stage == "material":
        field, settings = load_checkpoint(out / "checkpoint" / "radiance.pt", device, backend)
        config = cfg.RadianceConfig(**settings)
    else:
        named = {"resolution": resolution, "iterations": iterations, "zero_events": zero_events}
        named = {k: v for k, v in named.items() if v is not None}
        overrides = {**(radiance_settings or {}), **named}
        config = cfg.preset(preset, **overrides)
    started = time.perf_counter()
    with Session.open(session_path) as session:
        session_id = resume_.session_fingerprint(session)
        settings = {
            "radiance": {"config": cfg.to_dict(config), "seed": seed, "session": session_id},
        }
        settings["material"] = {
            **settings["radiance"],
            "material": cfg.to_dict(mconfig),
            "ablate": sorted(ablate),
        }
        states = _saved_states(out, stage, settings, resume, overwrite)
        if stage == "all" and states["radiance"] is None and states["material"] is not None:
            field, _ = load_checkpoint(out / "checkpoint" / "radiance.pt", device, backend)
        data = load_training_data(session, config, device)
        poses, truth = test_views(session)
        if environment is None and "relit_radiance" in truth:
            environment = session.group("gt")["relight_environment"][:].astype(np.float64)
        elif environment is not None:  # another light than the truth's: shown, not scored
            truth.pop("relit_radiance", None)
        if not len(poses):
            times = np.linspace(
                data.windows.frame_times[0], data.windows.frame_times[-1], TRACK_VIEWS
            )
            poses = data.track.at(times.astype(np.int64))
        out.mkdir(parents=True, exist_ok=True)
        # stage I is not run again for stage II alone, nor to go on with an interrupted stage II
        skip = stage == "material" or states["material"] is not None
        previous = out / "metrics.json"
        before = json.loads(previous.read_text()) if previous.exists() else {}
        result = dict(before) if skip else {}
        stopped = False
        if not skip:
            if states["radiance"] is not None:
                say(_going_on("stage I", states["radiance"], config.iterations))
            field, figures = _stage_radiance(
                data,
                config,
                poses,
                truth,
                out,
                seed,
                device,
                backend,
                progress,
                states["radiance"],
                settings["radiance"],
            )
            result.update(figures)
            result["seconds"] = time.perf_counter() - started
            if states["radiance"] is not None:  # and the time it took before
                result["seconds"] += before.get("seconds", 0.0)
            result.update(preset=preset, seed=seed, zero_events=config.zero_events)
            stopped = figures["interrupted"]
        if stage != "radiance" and not stopped:
            if states["material"] is not None:
                say(_going_on("stage II", states["material"], mconfig.iterations))
            started = time.perf_counter()
            path = resume_.state_path(out, "material")
            fit = train_material(
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
    if stage != "radiance" and not stopped:
        if "normal_mae_deg" in result and "radiance_normal_mae_deg" not in result:
            result["radiance_normal_mae_deg"] = result["normal_mae_deg"]
        result.update(
            _material_outputs(
                fit, field, poses, truth, data.optics, environment, out, device, ablate
            )
        )
        result["material_seconds"] = time.perf_counter() - started
        if states["material"] is not None:
            result["material_seconds"] += before.get("material_seconds", 0.0)
        result["interrupted"] = fit.interrupted
        if not fit.interrupted:
            resume_.state_path(out, "material").unlink(missing_ok=True)
    result["views"] = "held-out test views" if truth else "views along the camera path"
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
    if stage != "radiance":
        sections["material"] = cfg.to_dict(mconfig)
    write_toml(sections, out / "config.toml")
    write_json(result, out / "metrics.json")
    return result


def _saved_states(
    out: Path, stage: str, settings: dict, resume: bool, overwrite: bool
) -> dict[str, dict | None]:
    """The training states to go on from ({"radiance": ..., "material": ...}, None where a
    stage starts afresh); refuses to replace what OUT holds unless ``overwrite``."""
    states: dict[str, dict | None] = {"radiance": None, "material": None}
    names = {"radiance": ("radiance",), "material": ("material",)}.get(stage, tuple(states))
    saved = [n for n in names if resume_.state_path(out, n).exists()]
    for name in saved if resume else ():
        states[name] = resume_.load_state(resume_.state_path(out, name), settings[name])
        if states[name] is None and not overwrite:
            raise InputError(
                f"{out} holds a reconstruction interrupted in stage "
                f"{'I' if name == 'radiance' else 'II'} with another session or other settings: "
                "run the command it was started with to go on, or pass --force to start over"
            )
    if states["radiance"] is not None:
        states["material"] = None  # stage II starts afresh after it
    if not any(v is not None for v in states.values()):
        done = out / "gaussians.ply" if stage != "material" else out / "checkpoint" / "material.pt"
        if done.exists() and not overwrite:
            raise InputError(
                f"{out} already holds a reconstruction; choose another folder or pass --force"
            )
    # a stage that runs afresh makes what was saved of it (and, for stage I, of stage II) old
    for name in ("material",) if stage == "material" else tuple(states):
        if states[name] is None:
            resume_.state_path(out, name).unlink(missing_ok=True)
    return states


def _going_on(name: str, state: dict, iterations: int) -> str:
    return (
        f"{name}: going on from step {state['step']:,} of {iterations:,} (saved when it was "
        f"interrupted, {state['seconds']:.0f} s in)"
    )


def _stage_radiance(
    data, config, poses, truth, out: Path, seed, device, backend, progress, state, settings
):
    """Stage I and its outputs; (the field, its figures)."""

    def evaluate(field) -> dict:
        views = render_views(field, poses[:HISTORY_VIEWS], data.optics, device)
        seen = {k: v[:HISTORY_VIEWS] for k, v in truth.items()}
        out = image_metrics(views["radiance"], seen["radiance"], "render")
        mask = object_mask(seen)
        if mask is not None:
            out.update(object_metrics(views["radiance"], seen["radiance"], mask))
        if "normal" in seen:
            out["normal_mae_deg"] = normal_mae_deg(views["normal"], seen["normal"])
        return out

    path = resume_.state_path(out, "radiance")
    fit = train_radiance(
        data,
        config,
        seed=seed,
        device=device,
        backend=backend,
        progress=progress,
        evaluate=evaluate if "radiance" in truth else None,
        resume=state,
        save_state=lambda s: resume_.save_state(path, s, settings),
    )
    field, log = fit.field, fit.log
    views = render_views(field, poses, data.optics, device)
    result: dict = metrics(views, truth) if truth else {}
    cc = fit_color_correction(views["radiance"], truth["radiance"]) if "radiance" in truth else None
    result.update(
        {
            "iterations": fit.steps,
            "gaussians": len(field.gaussians),
            "device": device,
            "backend": backend,
            "interrupted": fit.interrupted,
            "history": fit.history,
        }
    )
    write_ply(field, out / "gaussians.ply")
    write_views(views, out / "renders", "test" if truth else "path", cc)
    save_checkpoint(
        field,
        cfg.to_dict(config),
        {"stage": "radiance", "log": [vars(x) for x in log]},
        out / "checkpoint" / "radiance.pt",
    )
    if not fit.interrupted:
        path.unlink(missing_ok=True)
    return field, result


def _material_outputs(
    fit, radiance, poses, truth, optics, environment, out: Path, device, ablate
) -> dict:
    """Stage II's renders, light, relit views, checkpoint; its figures, with what stage I's
    radiance (``radiance``, the field) reaches in their place."""
    field = fit.field
    views = render_views(field, poses, optics, device)
    result: dict = {}
    before = render_views(radiance, poses, optics, device)["radiance"] if truth else None
    if truth:
        result.update(material_metrics(views, truth, before))
    name = "test" if truth else "path"
    cc = fit_color_correction(views["radiance"], truth["radiance"]) if "radiance" in truth else None
    write_views(views, out / "renders" / "material", name, cc)
    light = mip_chain(field.light.radiance_faces().detach())
    write_image(environment_image(light), out / "environment.png")
    if environment is not None:
        new = light_from_image(environment, light[0].shape[-1], device)
        relit = render_views(field, poses, optics, device, new)
        if "relit_radiance" in truth:
            result.update(relit_metrics(relit["radiance"], truth, before))
        for i, image in enumerate(relit["radiance"]):
            write_image(image, out / "renders" / "relit" / f"{name}_{i:03d}.png")
        write_image(environment_image(new), out / "renders" / "relit" / "environment.png")
    save_material_checkpoint(
        field, {"log": [dataclasses.asdict(x) for x in fit.log]}, out / "checkpoint" / "material.pt"
    )
    result.update(
        {
            "material_iterations": fit.steps,
            "effects": {**field.effects, **{k: k not in ablate for k in ABLATIONS}},
            "relit": environment is not None,
        }
    )
    return result
