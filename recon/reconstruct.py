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
from evcap.recon.evaluate import material_metrics, metrics, render_views, test_views
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
from evcap.recon.metrics import fit_color_correction, image_metrics
from evcap.recon.radiance import load_training_data, train_radiance
from evcap.recon.rasterize import default_backend
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
    from evcap.sim.lighting import read_image_linear

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
    resolution: float | None = None,
    iterations: int | None = None,
    material_iterations: int | None = None,
    seed: int = 0,
    zero_events: str | None = None,
    visibility: str | None = None,
    indirect: str | None = None,
    ablate: tuple[str, ...] = (),
    relight: str | Path | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict:
    """Run the reconstruction; returns what went into OUT/metrics.json."""
    if stage not in STAGES:
        raise InputError(f"unknown stage {stage!r}; expected one of {', '.join(STAGES)}")
    if set(ablate) - set(ABLATIONS):
        raise InputError(f"unknown ablation(s) {sorted(set(ablate) - set(ABLATIONS))}")
    out = Path(out)
    done = out / "gaussians.ply" if stage != "material" else out / "checkpoint" / "material.pt"
    if done.exists() and not overwrite:
        raise InputError(
            f"{out} already holds a reconstruction; choose another folder or pass --force"
        )
    mconfig = cfg.material_preset(
        preset, iterations=material_iterations, visibility=visibility, indirect=indirect
    )
    environment = read_environment(relight) if relight is not None else None
    device = pick_device(device)
    backend = default_backend(device)
    if stage == "material":
        field, settings = load_checkpoint(out / "checkpoint" / "radiance.pt", device, backend)
        config = cfg.RadianceConfig(**settings)
        previous = out / "metrics.json"
        result = json.loads(previous.read_text()) if previous.exists() else {}
    else:
        config = cfg.preset(
            preset, resolution=resolution, iterations=iterations, zero_events=zero_events
        )
        result = {}
    started = time.perf_counter()
    with Session.open(session_path) as session:
        data = load_training_data(session, config, device)
        poses, truth = test_views(session)
        if not len(poses):
            times = np.linspace(
                data.windows.frame_times[0], data.windows.frame_times[-1], TRACK_VIEWS
            )
            poses = data.track.at(times.astype(np.int64))
        out.mkdir(parents=True, exist_ok=True)
        if stage != "material":
            field, figures = _stage_radiance(
                data, config, poses, truth, out, seed, device, backend, progress
            )
            result.update(figures)
            result["seconds"] = time.perf_counter() - started
            result.update(preset=preset, seed=seed, zero_events=config.zero_events)
        if stage != "radiance":
            started = time.perf_counter()
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
            )
    if stage != "radiance":
        if "normal_mae_deg" in result:
            result["radiance_normal_mae_deg"] = result["normal_mae_deg"]
        result.update(
            _material_outputs(fit, poses, truth, data.optics, environment, out, device, ablate)
        )
        result["material_seconds"] = time.perf_counter() - started
        result["interrupted"] = bool(result.get("interrupted")) or fit.interrupted
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


def _stage_radiance(data, config, poses, truth, out: Path, seed, device, backend, progress):
    """Stage I and its outputs; (the field, its figures)."""

    def evaluate(field) -> dict:
        views = render_views(field, poses[:HISTORY_VIEWS], data.optics, device)
        return image_metrics(views["radiance"], truth["radiance"][:HISTORY_VIEWS], "render")

    fit = train_radiance(
        data,
        config,
        seed=seed,
        device=device,
        backend=backend,
        progress=progress,
        evaluate=evaluate if "radiance" in truth else None,
    )
    field, log = fit.field, fit.log
    views = render_views(field, poses, data.optics, device)
    result: dict = metrics(views, truth) if truth else {}
    cc = fit_color_correction(views["radiance"], truth["radiance"]) if "radiance" in truth else None
    result.update(
        {
            "iterations": log[-1].step if log else 0,
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
    return field, result


def _material_outputs(fit, poses, truth, optics, environment, out: Path, device, ablate) -> dict:
    """Stage II's renders, light, relit views, checkpoint; its figures."""
    field = fit.field
    views = render_views(field, poses, optics, device)
    result: dict = {}
    if truth:
        result.update(material_metrics(views, truth))
    name = "test" if truth else "path"
    cc = fit_color_correction(views["radiance"], truth["radiance"]) if "radiance" in truth else None
    write_views(views, out / "renders" / "material", name, cc)
    light = mip_chain(field.light.radiance_faces().detach())
    write_image(environment_image(light), out / "environment.png")
    if environment is not None:
        new = light_from_image(environment, light[0].shape[-1], device)
        relit = render_views(field, poses, optics, device, new)
        for i, image in enumerate(relit["radiance"]):
            write_image(image, out / "renders" / "relit" / f"{name}_{i:03d}.png")
        write_image(environment_image(new), out / "renders" / "relit" / "environment.png")
    save_material_checkpoint(
        field, {"log": [dataclasses.asdict(x) for x in fit.log]}, out / "checkpoint" / "material.pt"
    )
    result.update(
        {
            "material_iterations": fit.log[-1].step if fit.log else 0,
            "effects": {**field.effects, **{k: k not in ablate for k in ABLATIONS}},
            "relit": environment is not None,
        }
    )
    return result
