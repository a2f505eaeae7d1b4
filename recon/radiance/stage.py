"""Stage I: a Gaussian radiance field fitted to the events alone (method.md).

Each step draws a window between two frame times, renders the two views (poses interpolated),
reads them at the sensor's pixels, and compares the change of log radiance of each pixel's
channel with its events: L = L_event + 0.1 L_GW + 0.05 L_normal, and (ours, in `fast`)
10 L_spread, the spread of the depths along each ray, and 0.3 L_smooth, neighbouring normals
alike on one surface, after a tenth of the run that fits the background alone (terms.py).
The densification is a strategy (densify.py) whose state the trainer holds.
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
from evcap.recon.config import Backend
from evcap.recon.events.windows import EventWindows
from evcap.recon.radiance.config import RadianceConfig
from evcap.recon.radiance.densify import DefaultStrategy, Strategy
from evcap.recon.radiance.losses import checked_loss
from evcap.recon.radiance.pose_refinement import PoseCorrections, PoseRefinementConfig
from evcap.recon.radiance.terms import StepInputs, after, stage_one_terms, total_loss
from evcap.recon.raster.rasterize import Camera, Render, rasterize
from evcap.recon.resume import Steps, random_states, restore_random_states
from evcap.recon.scene.event_stereo import event_stereo
from evcap.recon.scene.gaussians import Background, Gaussians, make_optimizer, means_lr
from evcap.recon.scene.optics import CHANNEL_WEIGHTS, RenderGrid, SensorOptics, render_grid
from evcap.recon.scene.support_plane import Plane, on_plane, support_plane
from evcap.recon.scene.volume import (
    Ball,
    SceneVolume,
    foreground_ball,
    sample_points,
    scene_volume,
)
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
    structure: np.ndarray | None = None  # [N, 3] the events' stereo points (init.on_events)
    bound: Ball | None = None  # the foreground's (densify.confine)
    support: Plane | None = None  # what the structure stands on (init.on_support)
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
            "bound": self.bound.state() if self.bound is not None else None,
            "support": self.support.state() if self.support is not None else None,
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
        bound = derived.get("bound")  # a state saved before the bound was: the volume's
        data.bound = Ball.from_state(bound) if bound else foreground_ball(data.volume, None)
        support = derived.get("support")
        data.support = Plane.from_state(support) if support else None
    return data


def _training_data(
    session: Session, config: RadianceConfig, device: str, geometry: bool
) -> TrainingData:
    """The events' windows and the sensor's optics; with ``geometry``, the render grids and
    the scene's volume too (else left None, for the caller to give)."""
    optics = SensorOptics.from_session(session)
    if config.windows.refractory_bound and optics.refractory_us <= 0:
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
    windows = EventWindows.from_session(session, optics, start, end, config.windows, device)
    weights = CHANNEL_WEIGHTS[torch.from_numpy(optics.channels().astype(np.int64))]
    mask = torch.from_numpy(~optics.hot_pixels.ravel())
    volume, grid, coarse, structure, bound, support = None, None, None, None, None, None
    if geometry:
        poses = track.at(windows.frame_times)
        volume = scene_volume(poses, optics.K, optics.width, optics.height)
        grid = render_grid(optics, config.resolution, device)
        if config.coarse.until:
            coarse = render_grid(optics, config.coarse.resolution, device)
        if config.init.on_events > 0:
            stretch = windows.frame_times[0], windows.frame_times[-1]
            found = event_stereo(session.events, stretch, track, optics, volume, config.init.stereo)
            structure = found.points
        bound = foreground_ball(volume, structure)
        # a known backdrop (a release composited over white) is seen wherever the object is
        # not: a support that makes no events of its own is that backdrop, not a floor
        # (mic: the cable and the stand's feet lie on a plane the release has no floor on)
        seek = config.init.on_support > 0 and config.background.known is None
        if seek and structure is not None and bound is not None:
            cameras = poses[:, :3, 3]
            support = support_plane(structure, cameras, bound.radius, config.init.support)
    return TrainingData(
        optics,
        track,
        windows,
        grid,
        coarse,
        weights.to(device),
        mask.to(device),
        volume,
        structure,
        bound,
        support,
    )


class RadianceField(torch.nn.Module):
    """Gaussians with view-dependent radiance, in front of a distant background."""

    def __init__(
        self,
        gaussians: Gaussians,
        background: Background,
        backend: Backend = "cpu",
        backdrop: tuple[float, float, float] | None = None,
        surfels: bool = False,
    ) -> None:
        super().__init__()
        self.gaussians = gaussians
        self.background = background
        self.backend = backend
        self.surfels = surfels  # config.surfels: the Gaussians rendered as flat discs
        # a known background (config.background.known): seen in place of the learnt one
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
        if spread:  # the centres' depths (a surfel's own at each pixel: rasterize's)
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
            surfels=self.surfels,
            depth_squared=spread,
        )


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


@dataclass(frozen=True)
class Schedule:
    """Stage I's fractions of the run as steps, made once where it starts: each part runs at
    the steps after its ``*_after`` or up to its ``*_until``."""

    iterations: int
    background_until: int  # the background fitted alone (config.background.first)
    coarse_until: int  # rendered on the coarse grid
    poses_after: float  # the trajectory refined; a step, as the rates' decay reads it
    degree_every: int  # the view dependence's degree grows by one every this many steps

    @classmethod
    def of(cls, config: RadianceConfig) -> Schedule:
        n = config.iterations
        alone = after(config.background.first, n) if config.background.known is None else 0
        return cls(
            n,
            alone,
            after(config.coarse.until, n),
            config.poses.start * n,
            max(n // 30, 1),
        )


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
    init = config.init
    points = np.zeros((0, 3))
    discs = np.zeros((0, 3))
    if init.on_support > 0 and data.support is not None and data.bound is not None:
        n = round(init.on_support * init.gaussians)
        discs = on_plane(data.support, data.bound, poses, o.K, o.width, o.height, n, rng)
    left = init.gaussians - len(discs)  # the other shares' Gaussians
    if init.on_points > 0 and data.track.points_xyz is not None:
        n = min(round(init.on_points * init.gaussians), left)
        points = on_points(data.track.points_xyz, data.volume, n, rng)
    missing = 0  # stereo points asked for and not found: none drawn at random in their place
    if init.on_events > 0 and data.structure is not None:
        n = min(round(init.on_events * init.gaussians), left - len(points))
        found = data.structure[rng.permutation(len(data.structure))[:n]]
        points, missing = np.concatenate([points, found]), n - len(found)
    rest = left - len(points) - missing
    if rest > 0:
        randoms = sample_points(data.volume, poses, o.K, o.width, o.height, rest, rng)
        points = np.concatenate([points, randoms])
    if len(points) + len(discs) == 0:
        raise InputError(
            "stage I has no Gaussians to start from: the events' stereo found no structure "
            "(too few events, or none that moved across the sensor); start some at random "
            "(--set stage1.init.on_events=0.5)"
        )
    g = torch.Generator().manual_seed(seed)
    # no larger than init.size_px render pixels at the volume's distance: random points fill
    # the whole view, and large ones would overlap by hundreds at every pixel
    distance = np.median(np.linalg.norm(poses[:, :3, 3] - data.volume.center, axis=1))
    if not data.volume.converging:
        distance = np.sqrt(data.volume.near * data.volume.far)
    footprint = distance / float(data.grid.K[0, 0])
    parts = []
    if len(points):
        parts.append(Gaussians.random(points, config.sh_degree, g, init.size_px * footprint))
    if len(discs):
        normals = np.tile(np.asarray(data.support.normal), (len(discs), 1))
        spacing = float(np.sqrt(np.pi * data.bound.radius**2 / len(discs)))
        parts.append(Gaussians.on_surface(discs, normals, spacing, config.sh_degree, DISC_OPACITY))
    gaussians = Gaussians.joined(parts)
    if config.surfels:
        gaussians.flatten_third_axis()
    background = Background(config.background.size)
    field = RadianceField(gaussians, background, backend, config.background.known, config.surfels)
    return field.to(device)


DISC_OPACITY = 0.5  # the support's discs: a surface the events do not contradict, not yet seen


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
    strategy: Strategy | None = None,
) -> Fit:
    """Fit stage I; Ctrl-C ends it at the end of the step with what was learnt so far.
    ``evaluate``, when given, is called at ``evaluations`` evenly spaced steps (its time not
    counted in the training's seconds) and what it returns goes into the fit's history with
    step and seconds: the accuracy-versus-time curve. ``save_state`` is given the training's
    state every ``save_every_s`` seconds and when it is interrupted; ``resume`` (such a state)
    goes on from its step as if it had never stopped (``data`` loaded with the state's
    ``data``: load_training_data's ``derived``). The loss and the parameters are checked
    for NaN every CHECK_EVERY steps (each check makes a GPU wait for the host); ``timer``
    measures the parts of each step (bench/steps.py). ``strategy``: the densification
    (default: 3DGS's, as config.densify sets it)."""
    torch.manual_seed(seed)
    if resume is None:
        field = new_field(data, config, seed, device, backend)
        derived = data.derived()  # saved with every state
    else:
        derived = resume["data"]
        gaussians = Gaussians.from_state(resume["gaussians"])
        background = Background.from_faces(resume["background"])
        field = RadianceField(
            gaussians, background, backend, config.background.known, config.surfels
        ).to(device)
    schedule = Schedule.of(config)
    extent = data.volume.radius
    optimizer = make_optimizer(field.gaussians, field.background, config.lr, extent)
    if strategy is None:
        strategy = DefaultStrategy.for_run(config.densify, config.iterations, extent, data.bound)
    strategy_state = strategy.initialize_state()
    refines = config.poses.refines(data.track)
    corrections, pose_optimizer = _pose_corrections(data, config.poses, extent, refines)
    terms = stage_one_terms(config, refines)
    rng = np.random.default_rng(seed + 1)
    log: list[StepLog] = []
    history: list[dict] = []
    steps = Steps(config.iterations, save_state, save_every_s, clock, resume)
    if resume is not None:
        optimizer.load_state_dict(resume["optimizer"])
        strategy_state = dict(resume["densify"])
        restore_random_states(rng, resume["random"])
        log = [StepLog(**x) for x in resume["log"]]
        history = list(resume["history"])
        if corrections is not None:
            corrections.load_state_dict(resume["corrections"])
            pose_optimizer.load_state_dict(resume["pose_optimizer"])
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
            "densify": strategy_state,
            "random": random_states(rng),
            "log": [dataclasses.asdict(x) for x in log],
            "history": history,
            "seconds": steps.seconds(),
        }

    with steps.running(state):
        while steps.next():
            step = steps.step
            sh_degree = min(config.sh_degree, (step - 1) // schedule.degree_every)
            frames = config.windows.draw(rng, len(data.windows))
            grid = data.grid
            if data.coarse_grid is not None and step <= schedule.coarse_until:
                grid = data.coarse_grid
            refining = corrections is not None and step > schedule.poses_after
            hidden = step <= schedule.background_until
            with timer("render"):
                spread = config.loss.spread.weight > 0
                moved = corrections if refining else None
                renders = _renders(field, data, grid, frames, sh_degree, spread, hidden, moved)
            with timer("loss"):
                seen = [grid.sample(r.color[..., :3]) for r in renders]  # [H * W, 3]
                inputs = StepInputs(field, data, grid, frames, renders, seen, moved, step, timer)
                total = total_loss(terms, inputs, step, hidden)
            with timer("backward"):
                total.backward()
            with timer("optimizer"):
                for group in optimizer.param_groups:
                    if group["name"] == "means":
                        group["lr"] = means_lr(config.lr, extent, step, config.iterations)
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
                if refining:
                    _pose_step(pose_optimizer, corrections, config.poses, schedule, step)
                with torch.no_grad():
                    q = field.gaussians.quats
                    q.data = F.normalize(q.data, dim=1)  # any length is a rotation; keep off zero
            with timer("densification"):
                # the background alone shows no Gaussian: no weight of theirs to count
                shown = [] if hidden else renders
                strategy.step_post_backward(
                    field.gaussians, optimizer, strategy_state, step, shown, grid
                )
            n = len(field.gaussians)
            if step % CHECK_EVERY == 0 or step == config.iterations:
                loss = checked_loss("stage I", step, total, field.parameters())
                shown = {k: float(inputs.logged.get(k, 0.0)) for k in ("event", "anchor", "normal")}
                log.append(StepLog(step, loss, **shown, gaussians=n, seconds=steps.seconds()))
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
    data: TrainingData, config: PoseRefinementConfig, extent: float, refines: bool
) -> tuple[PoseCorrections | None, torch.optim.Optimizer | None]:
    """The trajectory's corrections and their optimiser, when the poses are refined."""
    if not refines:
        return None, None
    times = data.windows.frame_times
    every = round(config.keyframe_ms * 1000)
    corrections = PoseCorrections(data.track, int(times[0]), int(times[-1]), every, extent)
    optimizer = torch.optim.Adam(
        [
            {"params": [corrections.rotation], "lr": config.lr_rotation, "name": "rotation"},
            {"params": [corrections.shift], "lr": config.lr_shift, "name": "shift"},
        ],
        eps=1e-15,
    )
    return corrections, optimizer


def _pose_step(
    optimizer: torch.optim.Optimizer,
    corrections: PoseCorrections,
    config: PoseRefinementConfig,
    schedule: Schedule,
    step: int,
) -> None:
    """One step of the corrections, their rates decayed tenfold over the refinement."""
    start = schedule.poses_after
    progress = (step - start) / max(schedule.iterations - start, 1)
    for group in optimizer.param_groups:
        base = config.lr_rotation if group["name"] == "rotation" else config.lr_shift
        group["lr"] = base * 0.1**progress
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    corrections.fix_gauge()


def _renders(
    field: RadianceField,
    data: TrainingData,
    grid: RenderGrid,
    frames: np.ndarray,
    sh_degree: int,
    spread: bool,
    hidden: bool,
    corrections: PoseCorrections | None,
) -> list[Render]:
    """The views on ``grid`` at the frames (from the corrected poses when ``corrections`` are
    given); with ``spread``, the depths' second moment too (render()); ``hidden``: the
    background alone."""
    if corrections is None:
        views = [data.viewmats()[int(f)] for f in frames]
        return [field.render_view(v, grid, sh_degree, spread, hidden) for v in views]
    times = data.windows.frame_times[frames]
    poses = corrections.apply(data.track.at(times), times)
    return [field.render(T, grid, sh_degree, spread, hidden) for T in poses]
