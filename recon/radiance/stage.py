"""Stage I: a Gaussian radiance field fitted to the events alone (method.md).

Each step draws a window between two frame times, renders the two views (poses interpolated),
reads them at the sensor's pixels, and compares the change of log radiance of each pixel's
channel with its events: L = L_event + 0.1 L_GW + 0.05 L_normal, and (ours, in `fast`)
10 L_spread, the spread of the depths along each ray, and 0.3 L_smooth, neighbouring normals
alike on one surface, after a tenth of the run that fits the background alone.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from evcap.errors import InputError
from evcap.recon._threads import torch_on_one_thread
from evcap.recon.config import Backend, RadianceConfig
from evcap.recon.events.windows import EventWindows
from evcap.recon.radiance.densify import Densifier
from evcap.recon.radiance.losses import (
    anchor_loss,
    checked_loss,
    depth_curvature_loss,
    event_loss,
    log_radiance,
    quiet_variation_loss,
    surface_terms,
)
from evcap.recon.radiance.pose_refinement import PoseCorrections
from evcap.recon.raster.rasterize import Camera, Render, rasterize
from evcap.recon.resume import Steps, random_states, restore_random_states
from evcap.recon.scene.gaussians import Background, Gaussians, make_optimizer, means_lr
from evcap.recon.scene.optics import CHANNEL_WEIGHTS, RenderGrid, SensorOptics, render_grid
from evcap.recon.scene.volume import SceneVolume, sample_points, scene_volume
from evcap.recon.step_timer import UNTIMED, StepTimer
from evcap.records import Poses
from evcap.session import Session


@dataclass
class TrainingData:
    """What stage I takes from a session."""

    optics: SensorOptics
    track: Poses
    windows: EventWindows
    grid: RenderGrid  # the training renders
    coarse_grid: RenderGrid | None  # the renders of the run's first part (coarse to fine)
    channel_weights: torch.Tensor  # [H * W, 3]: what each sensor pixel sees of (R, G, B)
    mask: torch.Tensor  # [H * W] bool: pixels the loss uses (hot pixels left out)
    volume: SceneVolume
    _viewmats: tuple[Poses, torch.Tensor] | None = dataclasses.field(default=None, repr=False)

    def viewmats(self) -> torch.Tensor:
        """[F, 4, 4] world to camera at every frame time (float32, on the training device),
        from the track as it is now (stage I may have refined it): prepared once, so that a
        step reads its views' poses without the host."""
        if self._viewmats is None or self._viewmats[0] is not self.track:
            T = np.linalg.inv(self.track.at(self.windows.frame_times))
            device = self.grid.K.device
            self._viewmats = (self.track, torch.as_tensor(T, dtype=torch.float32, device=device))
        return self._viewmats[1]

    def derived(self) -> dict:
        """What was derived from the session beside its events' windows (the render grids, the
        scene's volume) as a training saves it, and the windows' digest."""
        coarse = self.coarse_grid.state() if self.coarse_grid is not None else None
        return {
            "grid": self.grid.state(),
            "coarse_grid": coarse,
            "volume": self.volume.state(),
            "windows": self.windows.digest(),
        }


def load_training_data(
    session: Session, config: RadianceConfig, device: str, derived: dict | None = None
) -> TrainingData:
    """What stage I takes from the session. ``derived``: what a saved training derived
    (TrainingData.derived()'s), taken instead of deriving it again (the events' windows are
    counted again: whoever goes on compares their digest with the saved one)."""
    with torch_on_one_thread():  # see recon/_threads.py
        data = _training_data(session, config, device, derived is None)
    if derived is not None:
        data.grid = RenderGrid.from_state(derived["grid"], device)
        coarse = derived["coarse_grid"]
        data.coarse_grid = RenderGrid.from_state(coarse, device) if coarse is not None else None
        data.volume = SceneVolume.from_state(derived["volume"])
    return data


def _training_data(
    session: Session, config: RadianceConfig, device: str, geometry: bool
) -> TrainingData:
    """The events' windows and the sensor's optics; with ``geometry``, the render grids and
    the scene's volume too (else left None, for the caller to give)."""
    optics = SensorOptics.from_session(session)
    if config.refractory_bound and optics.refractory_us <= 0:
        raise InputError(
            f"{session.path}: the refractory bound needs the sensor's refractory period, and "
            "the calibration has none: measure it with `evcap calibrate`, or leave "
            "--refractory-bound out"
        )
    track = Poses.read(session)
    span = session.time_range()
    if span is None:
        raise InputError(f"{session.path} has no events to reconstruct from")
    # the recording starts at 0, whenever its first event came
    start, end = max(track.start, 0), min(track.end, span[1])
    windows = EventWindows.from_session(
        session,
        optics,
        start,
        end,
        round(config.frame_interval_ms * 1000),
        config.max_frames,
        device,
        optics.refractory_us if config.refractory_bound else 0.0,
        config.noise_filter_ms * 1000,
    )
    weights = CHANNEL_WEIGHTS[torch.from_numpy(optics.channels().astype(np.int64))]
    mask = torch.from_numpy(~optics.hot_pixels.ravel())
    volume, grid, coarse = None, None, None
    if geometry:
        poses = track.at(windows.frame_times)
        volume = scene_volume(poses, optics.K, optics.width, optics.height)
        grid = render_grid(optics, config.resolution, device)
        if config.coarse_until:
            coarse = render_grid(optics, config.coarse_resolution, device)
    return TrainingData(
        optics, track, windows, grid, coarse, weights.to(device), mask.to(device), volume
    )


class RadianceField(torch.nn.Module):
    """Gaussians with view-dependent radiance, in front of a distant background."""

    def __init__(
        self,
        gaussians: Gaussians,
        background: Background,
        backend: Backend = "cpu",
        backdrop: tuple[float, float, float] | None = None,
    ) -> None:
        super().__init__()
        self.gaussians = gaussians
        self.background = background
        self.backend = backend
        # a known background (config.known_background): seen in place of the learnt one
        known = None if backdrop is None else torch.tensor(backdrop, dtype=torch.float32)
        self.register_buffer("backdrop", known)

    def render(
        self,
        T_world_cam: np.ndarray | torch.Tensor,
        grid: RenderGrid,
        sh_degree: int | None = None,
        spread: bool = False,
        hidden: bool = False,
    ) -> Render:
        """The view; with ``spread``, color has a fourth channel: sum w z^2, the composited
        second moment of the Gaussians' depths (its spread about the expected depth is
        what the depth-spread loss takes); ``hidden`` renders the background alone. A pose
        given as a tensor (pose refinement) gets the render's gradient: every backend
        differentiates the camera."""
        device = self.gaussians.means.device
        if isinstance(T_world_cam, torch.Tensor):
            viewmat = torch.linalg.inv(T_world_cam).to(device, torch.float32)
        else:
            viewmat = torch.as_tensor(
                np.linalg.inv(T_world_cam), dtype=torch.float32, device=device
            )
        return self.render_view(viewmat, grid, sh_degree, spread, hidden)

    def render_view(
        self,
        viewmat: torch.Tensor,
        grid: RenderGrid,
        sh_degree: int | None = None,
        spread: bool = False,
        hidden: bool = False,
    ) -> Render:
        """render() from ``viewmat`` [4, 4] (world to camera, on the field's device)."""
        cam = Camera(viewmat, grid.K, grid.width, grid.height)
        g = self.gaussians
        colors = g.radiance(cam.center, sh_degree)
        if self.backdrop is None:
            bg = self.background(grid.directions(viewmat))
        else:
            bg = self.backdrop.expand(grid.height, grid.width, 3)
        if spread:
            z = g.means @ viewmat[2, :3] + viewmat[2, 3]
            colors = torch.cat([colors, (z * z)[:, None]], 1)
            bg = torch.cat([bg, bg.new_zeros(*bg.shape[:-1], 1)], -1)
        return rasterize(
            g.means,
            g.quats,
            g.scales,
            g.opacities * 0 if hidden else g.opacities,
            colors,
            cam,
            background=bg,
            backend=self.backend,
        )


def background_alone(config: RadianceConfig, step: int) -> bool:
    """Whether this step fits the background alone (config.background_first); never where the
    background is known."""
    return config.known_background is None and step <= config.background_first * config.iterations


CHECK_EVERY = 10  # steps: the log's and the NaN check's (each check waits for the device)


@dataclass
class StepLog:
    step: int
    loss: float
    event: float
    anchor: float
    normal: float
    gaussians: int
    seconds: float


@dataclass
class Fit:
    field: RadianceField
    log: list[StepLog]  # every 10 steps
    interrupted: bool
    history: list[dict] = dataclasses.field(default_factory=list)  # the evaluations along the way
    steps: int = 0  # the steps done
    corrections: PoseCorrections | None = None  # the trajectory's, when it was refined


def new_field(
    data: TrainingData, config: RadianceConfig, seed: int, device: str, backend: Backend
) -> RadianceField:
    """Stage I's first Gaussians (torch on one thread: recon/_threads.py)."""
    with torch_on_one_thread():
        return _new_field(data, config, seed, device, backend)


def _new_field(
    data: TrainingData, config: RadianceConfig, seed: int, device: str, backend: Backend
) -> RadianceField:
    rng = np.random.default_rng(seed)
    poses = data.track.at(data.windows.frame_times)
    o = data.optics
    points = np.zeros((0, 3))
    if config.init_on_points > 0 and data.track.points_xyz is not None:
        n = min(round(config.init_on_points * config.init_gaussians), config.init_gaussians)
        points = on_points(data.track.points_xyz, data.volume, n, rng)
    rest = config.init_gaussians - len(points)
    if rest > 0:
        randoms = sample_points(data.volume, poses, o.K, o.width, o.height, rest, rng)
        points = np.concatenate([points, randoms])
    g = torch.Generator().manual_seed(seed)
    # no larger than init_size_px render pixels at the volume's distance: random points fill
    # the whole view, and large ones would overlap by hundreds at every pixel
    distance = np.median(np.linalg.norm(poses[:, :3, 3] - data.volume.center, axis=1))
    if not data.volume.converging:
        distance = np.sqrt(data.volume.near * data.volume.far)
    footprint = distance / float(data.grid.K[0, 0])
    gaussians = Gaussians.random(points, config.sh_degree, g, config.init_size_px * footprint)
    background = Background(config.background_size)
    return RadianceField(gaussians, background, backend, config.known_background).to(device)


def on_points(
    points: np.ndarray, volume: SceneVolume, n: int, rng: np.random.Generator
) -> np.ndarray:
    """Up to n of structure from motion's ``points`` [P, 3], drawn among those inside twice
    the volume's ball (the scene's surfaces reach beyond where the cameras' axes meet)."""
    if volume.converging:
        points = points[np.linalg.norm(points - volume.center, axis=1) <= 2 * volume.radius]
    return points[rng.permutation(len(points))[:n]]


def train_radiance(
    data: TrainingData,
    config: RadianceConfig,
    *,
    seed: int = 0,
    device: str = "cpu",
    backend: Backend = "cpu",
    progress: Callable[[int, int, str], None] | None = None,
    clock: Callable[[], float] = time.perf_counter,
    evaluate: Callable[[RadianceField], dict] | None = None,
    evaluations: int = 6,
    resume: dict | None = None,
    save_state: Callable[[dict], None] | None = None,
    save_every_s: float = 120.0,
    timer: StepTimer = UNTIMED,
) -> Fit:
    """Fit stage I; Ctrl-C ends it at the end of the step with what was learnt so far.
    ``evaluate``, when given, is called at ``evaluations`` evenly spaced steps (its time not
    counted in the training's seconds) and what it returns goes into the fit's history with
    step and seconds: the accuracy-versus-time curve. ``save_state`` is given the training's
    state every ``save_every_s`` seconds and when it is interrupted; ``resume`` (such a state)
    goes on from its step as if it had never stopped (``data`` loaded with the state's
    ``data``: load_training_data's ``derived``). The loss and the parameters are checked
    for NaN every CHECK_EVERY steps (each check makes a GPU wait for the host); ``timer``
    measures the parts of each step (bench/steps.py)."""
    torch.manual_seed(seed)
    if resume is None:
        field = new_field(data, config, seed, device, backend)
        derived = data.derived()  # saved with every state
    else:
        derived = resume["data"]
        gaussians = Gaussians.from_state(resume["gaussians"])
        background = Background.from_faces(resume["background"])
        field = RadianceField(gaussians, background, backend, config.known_background)
        field = field.to(device)
    extent = data.volume.radius
    optimizer = make_optimizer(field.gaussians, field.background, config, extent)
    densifier = Densifier(config, extent, data.volume)
    corrections, pose_optimizer = _pose_corrections(data, config, extent)
    rng = np.random.default_rng(seed + 1)
    log: list[StepLog] = []
    history: list[dict] = []
    steps = Steps(config.iterations, save_state, save_every_s, clock, resume)
    if resume is not None:
        optimizer.load_state_dict(resume["optimizer"])
        densifier.grad_sum, densifier.count = resume["grad_sum"], resume["count"]
        restore_random_states(rng, resume["random"])
        log = [StepLog(**x) for x in resume["log"]]
        history = list(resume["history"])
        if corrections is not None:
            corrections.load_state_dict(resume["corrections"])
            pose_optimizer.load_state_dict(resume["pose_optimizer"])
    degree_every = max(config.iterations // 30, 1)
    evaluate_at = set(np.linspace(0, config.iterations, evaluations + 1)[1:].round().astype(int))
    loss = math.nan  # as last checked

    def state() -> dict:
        checked_loss("stage I", steps.step, None, field.parameters())  # none saved broken
        poses = {}
        if corrections is not None:
            poses["corrections"] = corrections.state_dict()
            poses["pose_optimizer"] = pose_optimizer.state_dict()
        return {
            **poses,
            "step": steps.step,
            "data": derived,
            "gaussians": field.gaussians.state_dict(),
            "background": field.background.faces.detach(),
            "optimizer": optimizer.state_dict(),
            "grad_sum": densifier.grad_sum,
            "count": densifier.count,
            "random": random_states(rng),
            "log": [dataclasses.asdict(x) for x in log],
            "history": history,
            "seconds": steps.seconds(),
        }

    with steps.running(state):
        while steps.next():
            step = steps.step
            sh_degree = min(config.sh_degree, (step - 1) // degree_every)
            frames = draw_frames(rng, len(data.windows), config)
            grid = data.grid
            if data.coarse_grid is not None and step <= config.coarse_until * config.iterations:
                grid = data.coarse_grid
            refining = corrections is not None and step > config.pose_from * config.iterations
            renders, total, terms = _losses(
                field,
                data,
                grid,
                config,
                frames,
                sh_degree,
                step,
                corrections if refining else None,
                timer,
            )
            with timer("backward"):
                total.backward()
            with timer("densification"):
                for r in renders:
                    densifier.observe(r, grid.width, grid.height)
            with timer("optimizer"):
                for group in optimizer.param_groups:
                    if group["name"] == "means":
                        group["lr"] = means_lr(config, extent, step)
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
                if refining:
                    _pose_step(pose_optimizer, corrections, config, step)
                with torch.no_grad():
                    q = field.gaussians.quats
                    q.data = F.normalize(q.data, dim=1)  # any length is a rotation; keep off zero
            with timer("densification"):
                densify, reset = densifier.due(step)
                if densify:
                    densifier.densify(field.gaussians, optimizer)
                if reset:
                    densifier.reset_opacities(field.gaussians, optimizer)
            n = len(field.gaussians)
            if step % CHECK_EVERY == 0 or step == config.iterations:
                loss = checked_loss("stage I", step, total, field.parameters())
                terms = {k: float(v) for k, v in terms.items()}
                log.append(StepLog(step, loss, **terms, gaussians=n, seconds=steps.seconds()))
            if evaluate is not None and step in evaluate_at:
                seconds = steps.seconds()
                with steps.paused_clock():
                    history.append({"step": step, "seconds": seconds, **evaluate(field)})
            steps.end()
            if progress:
                shown = f"loss {loss:.4f}  " if math.isfinite(loss) else ""
                progress(step, config.iterations, f"{shown}{n:,} Gaussians")
    return Fit(field, log, steps.interrupted, history, steps.step, corrections)


def _pose_corrections(
    data: TrainingData, config: RadianceConfig, extent: float
) -> tuple[PoseCorrections | None, torch.optim.Optimizer | None]:
    """The trajectory's corrections and their optimiser, when the config refines poses."""
    if not config.refine_poses:
        return None, None
    times = data.windows.frame_times
    every = round(config.pose_keyframe_ms * 1000)
    corrections = PoseCorrections(data.track, int(times[0]), int(times[-1]), every, extent)
    optimizer = torch.optim.Adam(
        [
            {"params": [corrections.rotation], "lr": config.lr_pose_rotation, "name": "rotation"},
            {"params": [corrections.shift], "lr": config.lr_pose_shift, "name": "shift"},
        ],
        eps=1e-15,
    )
    return corrections, optimizer


def _pose_step(
    optimizer: torch.optim.Optimizer,
    corrections: PoseCorrections,
    config: RadianceConfig,
    step: int,
) -> None:
    """One step of the corrections, their rates decayed tenfold over the refinement."""
    start = config.pose_from * config.iterations
    progress = (step - start) / max(config.iterations - start, 1)
    for group in optimizer.param_groups:
        base = config.lr_pose_rotation if group["name"] == "rotation" else config.lr_pose_shift
        group["lr"] = base * 0.1**progress
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    corrections.fix_gauge()


def draw_frames(rng: np.random.Generator, frames: int, config: RadianceConfig) -> np.ndarray:
    """views_per_step frame indices, increasing, each 1..max_window_frames after the last."""
    gaps = rng.integers(1, config.max_window_frames + 1, config.views_per_step - 1)
    span = int(gaps.sum())
    if span >= frames:
        gaps = np.maximum(gaps * (frames - 1) // span, 1)
        span = int(gaps.sum())
    start = int(rng.integers(0, max(frames - span, 1)))
    return np.minimum(start + np.concatenate([[0], np.cumsum(gaps)]), frames - 1)


def windows_event_loss(
    data: TrainingData,
    config: RadianceConfig,
    frames: np.ndarray,
    seen: list[torch.Tensor],
    timer: StepTimer = UNTIMED,
) -> torch.Tensor:
    """The event loss of every window between two of the views ``seen`` [H * W, 3] (the
    renders at the sensor's pixels) at ``frames``, averaged (on the CPU in one compiled pass,
    recon/events/_loss_cpu.py)."""
    w = data.windows
    with timer("events"):
        before = w.before_frames(frames)
        crowded = w.crowded.before_frames(frames) if w.crowded is not None else None
    pairs = [
        (i, j)
        for i in range(len(frames))
        for j in range(i + 1, len(frames))
        if frames[j] != frames[i]
    ]
    if not pairs:
        return seen[0].sum() * 0
    noise = expected_noise(data, config, frames, pairs)
    if seen[0].device.type == "cpu":
        from evcap.recon.events._loss_cpu import event_loss_cpu

        return event_loss_cpu(
            seen,
            data.channel_weights,
            config.log_eps,
            before,
            pairs,
            noise,
            w.threshold_on,
            w.threshold_off,
            data.mask,
            config.zero_events,
            config.silent_weight,
            crowded,
        )
    return event_loss_torch(data, config, before, pairs, noise, seen, crowded)


def expected_noise(
    data: TrainingData, config: RadianceConfig, frames: np.ndarray, pairs: list[tuple[int, int]]
) -> np.ndarray:
    """[windows, 2] the noise events (ON, OFF) a pixel fires in each window at the
    calibration's rates (config.noise_rates; else 0)."""
    out = np.zeros((len(pairs), 2))
    if config.noise_rates:
        t = data.windows.frame_times[np.asarray(frames)]
        seconds = np.array([(t[j] - t[i]) * 1e-6 for i, j in pairs])
        out[:, 0] = data.optics.noise_on_hz * seconds
        out[:, 1] = data.optics.noise_off_hz * seconds
    return out


def event_loss_torch(
    data: TrainingData,
    config: RadianceConfig,
    before: torch.Tensor,
    pairs: list[tuple[int, int]],
    noise: np.ndarray,
    seen: list[torch.Tensor],
    crowded: torch.Tensor | None = None,
) -> torch.Tensor:
    """windows_event_loss in PyTorch operations: losses.event_loss window by window."""
    w = data.windows
    logs = [log_radiance((s * data.channel_weights).sum(1), config.log_eps) for s in seen]
    event = []
    for (i, j), (mu_on, mu_off) in zip(pairs, noise, strict=True):
        target, counts = w.change(*w.between(before[i], before[j]))
        target = target - (w.threshold_on * float(mu_on) - w.threshold_off * float(mu_off))
        near = None
        if crowded is not None:
            near = sum(w.crowded.between(crowded[i], crowded[j]))
        event.append(
            event_loss(
                logs[j] - logs[i],
                target,
                counts,
                w.threshold_on,
                w.threshold_off,
                data.mask,
                config.zero_events,
                config.silent_weight,
                near,
            )
        )
    return torch.stack(event).mean()


def _losses(
    field: RadianceField,
    data: TrainingData,
    grid: RenderGrid,
    config: RadianceConfig,
    frames: np.ndarray,
    sh_degree: int,
    step: int,
    corrections: PoseCorrections | None = None,
    timer: StepTimer = UNTIMED,
) -> tuple[list[Render], torch.Tensor, dict[str, torch.Tensor]]:
    """The renders on ``grid`` at the frames (from the corrected poses when ``corrections``
    are given), and the loss of every window between two of them; (renders, total, its terms
    as tensors, to be read when logged)."""
    spread = config.spread_weight > 0
    hidden = background_alone(config, step)
    with timer("render"):
        if corrections is None:
            views = [data.viewmats()[int(f)] for f in frames]
            renders = [field.render_view(v, grid, sh_degree, spread, hidden) for v in views]
        else:
            times = data.windows.frame_times[frames]
            poses = corrections.apply(data.track.at(times), times)
            renders = [field.render(T, grid, sh_degree, spread, hidden) for T in poses]
    with timer("loss"):
        return _terms(field, data, grid, config, frames, step, renders, corrections, timer)


def _terms(
    field: RadianceField,
    data: TrainingData,
    grid: RenderGrid,
    config: RadianceConfig,
    frames: np.ndarray,
    step: int,
    renders: list[Render],
    corrections: PoseCorrections | None,
    timer: StepTimer,
) -> tuple[list[Render], torch.Tensor, dict[str, torch.Tensor]]:
    seen = [grid.sample(r.color[..., :3]) for r in renders]  # [H * W, 3], sensor pixels
    ev = windows_event_loss(data, config, frames, seen, timer)
    an = anchor_loss(torch.cat(seen), config.anchor_level)
    total = ev if config.known_background is not None else ev + config.anchor_weight * an
    if corrections is not None:
        total = total + config.pose_smooth_weight * corrections.smoothness()
    terms = {"event": ev.detach(), "anchor": an.detach(), "normal": torch.zeros(())}
    hidden = background_alone(config, step)
    if config.quiet_tv_weight > 0:
        H, W = data.optics.height, data.optics.width
        _, counts = data.windows.log_change(int(frames[0]), int(frames[-1]))
        loud = ((counts > 0) | ~data.mask).reshape(H, W)
        tv = sum(
            quiet_variation_loss(log_radiance(s, config.log_eps).reshape(H, W, 3), loud)
            for s in seen
        )
        total = total + config.quiet_tv_weight * tv / len(seen)
    if config.background_tv_weight > 0:
        total = total + config.background_tv_weight * field.background.log_variation()
    if hidden:  # the background alone: the terms of the Gaussians wait for them
        return renders, total, terms
    which = (
        config.normal_weight > 0 and step > config.normal_from * config.iterations,
        config.spread_weight > 0,
        config.smooth_weight > 0,
    )
    if any(which):
        surface = sum(
            surface_terms(
                r.normal,
                r.depth,
                r.alpha,
                r.color[..., 3] if which[1] else None,
                grid.K,
                config.smooth_step,
                which,
            )
            for r in renders
        ) / len(renders)
        weights = (config.normal_weight, config.spread_weight, config.smooth_weight)
        total = total + sum(w * surface[k] for k, w in enumerate(weights) if which[k])
        terms["normal"] = surface[0].detach()
    if config.curvature_weight > 0:
        cu = sum(depth_curvature_loss(r.depth, r.alpha) for r in renders)
        total = total + config.curvature_weight * cu / len(renders)
    if config.alpha_weight > 0:
        alpha = torch.stack([r.alpha.mean() for r in renders]).mean()
        total = total + config.alpha_weight * alpha
    g = field.gaussians
    if config.opacity_reg > 0:
        total = total + config.opacity_reg * g.opacities.mean()
    if config.binary_weight > 0 and step > config.binary_from * config.iterations:
        o = g.opacities
        total = total + config.binary_weight * (o * (1 - o)).mean()
    if config.flatten_weight > 0:
        s = g.log_scales
        total = total + config.flatten_weight * (s.min(1).values - s.max(1).values).exp().mean()
    return renders, total, terms
