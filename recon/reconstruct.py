"""`evcap reconstruct`: a session in, a reconstruction folder out."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from evcap.errors import InputError
from evcap.recon import config as cfg
from evcap.recon.evaluate import metrics, render_views, test_views
from evcap.recon.export import save_checkpoint, write_json, write_ply, write_toml, write_views
from evcap.recon.metrics import fit_color_correction
from evcap.recon.radiance import load_training_data, train_radiance
from evcap.recon.rasterize import default_backend
from evcap.session import Session

STAGES = ("radiance",)
TRACK_VIEWS = 8  # views rendered along the path when the session has no held-out views


def pick_device(name: str) -> str:
    if name not in ("cpu", "cuda"):
        raise InputError(f"unknown device {name!r}; expected cpu or cuda")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA GPU is visible to PyTorch here; use --device cpu")
    return name


def reconstruct(
    session_path: str | Path,
    out: str | Path,
    *,
    preset: str = "fast",
    stage: str = "radiance",
    device: str = "cpu",
    resolution: float | None = None,
    iterations: int | None = None,
    seed: int = 0,
    zero_events: str | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict:
    """Run the reconstruction; returns what went into OUT/metrics.json."""
    if stage not in STAGES:
        raise InputError(f"unknown stage {stage!r}; expected one of {', '.join(STAGES)}")
    out = Path(out)
    if (out / "gaussians.ply").exists() and not overwrite:
        raise InputError(
            f"{out} already holds a reconstruction; choose another folder or pass --force"
        )
    config = cfg.preset(
        preset, resolution=resolution, iterations=iterations, zero_events=zero_events
    )
    device = pick_device(device)
    backend = default_backend(device)
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
    fit = train_radiance(data, config, seed=seed, device=device, backend=backend, progress=progress)
    field, log = fit.field, fit.log
    seconds = time.perf_counter() - started
    views = render_views(field, poses, data.optics, device)
    result: dict = {}
    if truth:
        result.update(metrics(views, truth))
    cc = fit_color_correction(views["radiance"], truth["radiance"]) if "radiance" in truth else None
    result.update(
        {
            "seconds": seconds,
            "iterations": log[-1].step if log else 0,
            "gaussians": len(field.gaussians),
            "device": device,
            "backend": backend,
            "preset": preset,
            "seed": seed,
            "zero_events": config.zero_events,
            "interrupted": fit.interrupted,
            "views": "held-out test views" if truth else "views along the camera path",
        }
    )
    write_ply(field, out / "gaussians.ply")
    write_views(views, out / "renders", "test" if truth else "path", cc)
    settings = cfg.to_dict(config)
    save_checkpoint(
        field,
        settings,
        {"stage": "radiance", "log": [vars(x) for x in log]},
        out / "checkpoint" / "radiance.pt",
    )
    write_toml(
        {
            "reconstruct": {
                "session": str(session_path),
                "stage": stage,
                "preset": preset,
                "device": device,
                "backend": backend,
                "seed": seed,
            },
            "radiance": settings,
        },
        out / "config.toml",
    )
    write_json(result, out / "metrics.json")
    return result
