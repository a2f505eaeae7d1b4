"""Stage I: a Gaussian radiance field fitted to the events alone (method.md).

Each step draws a window between two frame times, renders the two views (poses interpolated),
reads them at the sensor's pixels, and compares the change of log radiance of each pixel's
channel with its events: L = L_event + 0.1 L_GW + 0.05 L_normal.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from evcap.errors import InputError
from evcap.poses.track import PoseTrack
from evcap.recon.config import RadianceConfig
from evcap.recon.densify import Densifier
from evcap.recon.event_windows import EventWindows
from evcap.recon.gaussians import Background, Gaussians, make_optimizer, means_lr
from evcap.recon.losses import anchor_loss, event_loss, log_radiance, normal_loss
from evcap.recon.optics import CHANNEL_WEIGHTS, RenderGrid, SensorOptics, render_grid
from evcap.recon.rasterize import Camera, Render, rasterize
from evcap.recon.volume import SceneVolume, sample_points, scene_volume
from evcap.session import Session


@dataclass
class TrainingData:
    """What stage I takes from a session."""

    optics: SensorOptics
    track: PoseTrack
    windows: EventWindows
    grid: RenderGrid  # the training renders
    channel_weights: torch.Tensor  # [H * W, 3]: what each sensor pixel sees of (R, G, B)
    mask: torch.Tensor  # [H * W] bool: pixels the loss uses (hot pixels left out)
    volume: SceneVolume


def load_training_data(session: Session, config: RadianceConfig, device: str) -> TrainingData:
    optics = SensorOptics.from_session(session)
    track = PoseTrack.from_session(session)
    span = session.time_range()
    if span is None:
        raise InputError(f"{session.path} has no events to reconstruct from")
    # the recording starts at 0, whenever its first event came
    start, end = max(track.start, 0), min(track.end, span[1])
    windows = EventWindows.from_session(
        session, optics, start, end, round(config.frame_interval_ms * 1000), config.max_frames
    )
    poses = track.at(windows.frame_times)
    volume = scene_volume(poses, optics.K, optics.width, optics.height)
    weights = CHANNEL_WEIGHTS[torch.from_numpy(optics.channels().astype(np.int64))]
    mask = torch.from_numpy(~optics.hot_pixels.ravel())
    grid = render_grid(optics, config.resolution, device)
    return TrainingData(optics, track, windows, grid, weights.to(device), mask.to(device), volume)


class RadianceField(torch.nn.Module):
    """Gaussians with view-dependent radiance, in front of a distant background."""

    def __init__(
        self, gaussians: Gaussians, background: Background, backend: str = "torch"
    ) -> None:
        super().__init__()
        self.gaussians = gaussians
        self.background = background
        self.backend = backend

    def render(
        self, T_world_cam: np.ndarray, grid: RenderGrid, sh_degree: int | None = None
    ) -> Render:
        device = self.gaussians.means.device
        viewmat = torch.as_tensor(np.linalg.inv(T_world_cam), dtype=torch.float32, device=device)
        cam = Camera(viewmat, grid.K, grid.width, grid.height)
        g = self.gaussians
        colors = g.radiance(cam.center, sh_degree)
        bg = self.background(pixel_directions(cam))
        return rasterize(
            g.means,
            g.quats,
            g.scales,
            g.opacities,
            colors,
            cam,
            background=bg,
            backend=self.backend,
        )


def pixel_directions(cam: Camera) -> torch.Tensor:
    """[H, W, 3] unit world directions of the rays through each pixel centre."""
    dev = cam.K.device
    ys, xs = torch.meshgrid(
        torch.arange(cam.height, dtype=torch.float32, device=dev),
        torch.arange(cam.width, dtype=torch.float32, device=dev),
        indexing="ij",
    )
    d = torch.stack(
        [(xs - cam.K[0, 2]) / cam.K[0, 0], (ys - cam.K[1, 2]) / cam.K[1, 1], torch.ones_like(xs)],
        -1,
    )
    return F.normalize(d @ cam.viewmat[:3, :3], dim=-1)


@dataclass
class StepLog:
    step: int
    loss: float
    event: float
    anchor: float
    normal: float
    gaussians: int
    seconds: float


def new_field(
    data: TrainingData, config: RadianceConfig, seed: int, device: str, backend: str
) -> RadianceField:
    rng = np.random.default_rng(seed)
    poses = data.track.at(data.windows.frame_times)
    o = data.optics
    points = sample_points(data.volume, poses, o.K, o.width, o.height, config.init_gaussians, rng)
    g = torch.Generator().manual_seed(seed)
    gaussians = Gaussians.random(points, config.sh_degree, g)
    return RadianceField(gaussians, Background(config.background_sh_degree), backend).to(device)


def train_radiance(
    data: TrainingData,
    config: RadianceConfig,
    *,
    seed: int = 0,
    device: str = "cpu",
    backend: str = "torch",
    progress: Callable[[int, int, str], None] | None = None,
    clock: Callable[[], float] = time.perf_counter,
) -> tuple[RadianceField, list[StepLog]]:
    """Fit stage I; returns the field and a log of the loss (every 10 steps)."""
    torch.manual_seed(seed)
    field = new_field(data, config, seed, device, backend)
    extent = data.volume.radius
    optimizer = make_optimizer(field.gaussians, field.background, config, extent)
    densifier = Densifier(config, extent)
    rng = np.random.default_rng(seed + 1)
    frames = len(data.windows)
    times = data.windows.frame_times
    grid = data.grid
    log: list[StepLog] = []
    started = clock()
    degree_every = max(config.iterations // 30, 1)
    for step in range(1, config.iterations + 1):
        sh_degree = min(config.sh_degree, (step - 1) // degree_every)
        renders = []
        terms = {"event": 0.0, "anchor": 0.0, "normal": 0.0}
        total = torch.zeros((), device=device)
        for _ in range(config.windows_per_step):
            a = int(rng.integers(0, frames - 1))
            b = min(a + int(rng.integers(1, config.max_window_frames + 1)), frames - 1)
            poses = data.track.at(times[[a, b]])
            pair = [field.render(T, grid, sh_degree) for T in poses]
            renders += pair
            seen = [grid.sample(r.color) for r in pair]  # [H * W, 3] at the sensor's pixels
            logs = [log_radiance((s * data.channel_weights).sum(1), config.log_eps) for s in seen]
            target, counts = data.windows.log_change(a, b)
            ev = event_loss(
                logs[1] - logs[0],
                target.to(device),
                counts.to(device),
                data.windows.threshold_on.to(device),
                data.windows.threshold_off.to(device),
                data.mask,
                config.zero_events,
                config.silent_weight,
            )
            an = anchor_loss(torch.cat(seen), config.anchor_level)
            loss = ev + config.anchor_weight * an
            terms["event"] += ev.item()
            terms["anchor"] += an.item()
            if config.normal_weight > 0 and step > config.normal_from * config.iterations:
                nl = sum(normal_loss(r.normal, r.depth, r.alpha, grid.K) for r in pair) / 2
                loss = loss + config.normal_weight * nl
                terms["normal"] += nl.item()
            total = total + loss / config.windows_per_step
        if not torch.isfinite(total):
            raise FloatingPointError(f"stage I: the loss became {float(total)} at step {step}")
        total.backward()
        for r in renders:
            densifier.observe(r, grid.width, grid.height)
        for group in optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = means_lr(config, extent, step)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        with torch.no_grad():
            g = field.gaussians
            # quaternions of any length are rotations; keep them well away from zero
            g.quats.data = F.normalize(g.quats.data, dim=1)
        densify, reset = densifier.due(step)
        if densify:
            densifier.densify(field.gaussians, optimizer)
        if reset:
            densifier.reset_opacities(field.gaussians, optimizer)
        if step % 10 == 0 or step == config.iterations:
            n = config.windows_per_step
            log.append(
                StepLog(
                    step,
                    float(total),
                    terms["event"] / n,
                    terms["anchor"] / n,
                    terms["normal"] / n,
                    len(field.gaussians),
                    clock() - started,
                )
            )
        if progress:
            progress(
                step,
                config.iterations,
                f"loss {float(total):.4f}  {len(field.gaussians)} Gaussians",
            )
    return field, log


def isfinite_field(field: RadianceField) -> bool:
    return all(bool(torch.isfinite(p).all()) for p in field.parameters())
