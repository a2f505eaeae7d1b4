"""`evcap simulate`: a scene -> a session with events (and frames, IMU) and its ground truth.

Sampling: renders come at key times whose spacing keeps the image motion under
``scene.max_step_px`` pixels; between two key renders, a pixel whose log signal changed by more
than ``scene.max_step_log`` thresholds is rendered again at the midpoint, recursively, down to
MIN_STEP_US (only those pixels, each from the camera at its own time). Each pixel's samples are
then joined linearly and the pixel model (evcap.sim.events) turns them into events. A still
camera renders identical frames and produces no events (unless noise effects are on).

The environment's specular light, most of a render's cost, is integrated exactly at every
ANCHOR_EVERY-th key render and shared between them where a pixel sees the same surface
(evcap.sim.specular_reuse); the refinements and the APS frames' renders (one a millisecond of
exposure) share it from the key renders around them; the ground truth's views are rendered
exactly.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from evcap.atomic_write import atomic_path
from evcap.errors import InputError
from evcap.events import Events
from evcap.records import Calibration, GroundTruth, Poses, TruthViews
from evcap.session import SensorInfo, SessionWriter
from evcap.sim.events import PixelArray
from evcap.sim.render import RENDERER_VERSION, Renderer, RenderResult, SpecularInputs
from evcap.sim.scene import Scene
from evcap.sim.sensor import (
    ChannelMap,
    aps_frame,
    imu_samples,
    measured_sensor,
    true_calibration,
)
from evcap.sim.specular_reuse import SpecularFrame, specular_between
from evcap.sim.trajectory import Trajectory, look_at
from evcap.streams import Frames, ImuSamples, TriggerKind, Triggers

MIN_STEP_US = 2.0  # refinement stops at this interval: event times are good to about this
MAX_STEP_US = 10_000.0  # longest key step (a still camera, or a slow one)
EPOCH_US = 1_767_225_600_000_000  # t = 0 of simulated sessions: 2026-01-01T00:00:00Z
POSE_RATE_HZ = 500.0  # rate of the /poses table (interpolate between)
# key renders per exact specular frame: at most max_step_px (0.5) x 8 = 4 pixels of image motion
# between the frames that the specular light is shared from (evcap.sim.specular_reuse)
ANCHOR_EVERY = 8


@dataclass
class _Key:
    """A key render: each pixel's log signal at time t (us), and the environment's specular
    light it holds."""

    t: float
    log: np.ndarray  # [P]
    frame: SpecularFrame
    depth: np.ndarray  # [P] z in the camera frame; 0 where no surface


@dataclass
class SimulationStats:
    """What a run did, and where its time went (seconds)."""

    events: int = 0
    frames: int = 0
    imu: int = 0
    key_renders: int = 0
    refined_pixels: int = 0  # pixel renders added by refinement
    exact_specular: int = 0  # surface pixels whose environment specular light was integrated
    shared_specular: int = 0  # ...and those whose light was interpolated (specular_reuse)
    seconds: dict = field(
        default_factory=lambda: {
            "setup": 0.0,  # the scene, the mesh and the diffuse light's bake (visibility)
            "render": 0.0,  # ray casting and shading, but the environment's specular light
            "specular": 0.0,  # the environment's specular light (integrated or shared)
            "events": 0.0,
            "noise": 0.0,
            "aps": 0.0,
            "gt": 0.0,
            "write": 0.0,
        }
    )


@contextmanager
def _timed(stats: SimulationStats, name: str) -> Iterator[None]:
    start = time.perf_counter()
    try:
        yield
    finally:
        stats.seconds[name] += time.perf_counter() - start


class Simulator:
    """Runs one scene."""

    def __init__(
        self,
        scene: Scene,
        *,
        seed: int | None = None,
        progress: Callable[[float, float], None] | None = None,
    ) -> None:
        self.scene = scene
        self.seed = scene.seed if seed is None else seed
        self.rng = np.random.default_rng(self.seed)
        self.progress = progress
        self.stats = SimulationStats()
        with _timed(self.stats, "setup"):
            self.renderer = Renderer(scene)
            self.camera = self.renderer.camera
            self.trajectory = Trajectory(scene.trajectory, self.seed)
            s = scene.sensor
            self.channels = ChannelMap(self.camera.width, self.camera.height, s.color_filter)
            n = self.camera.width * self.camera.height
            # The sensor's fixed imperfections come from [sensor] seed when the scene gives one
            # (the same physical sensor in every scene that gives it), else from the scene's
            # random numbers; its noise over time always comes from the scene's.
            made = self.rng if s.seed is None else np.random.default_rng(s.seed)
            if s.calibration is None:
                self.pixels = PixelArray(n, s.threshold_on, s.threshold_off, s.effects, made)
            else:
                on, off, hot, effects = measured_sensor(s.calibration, s.effects, n)
                self.pixels = PixelArray(n, on, off, effects, made, hot_pixels=hot)
            self.pixels.rng = self.rng
            self.effects = self.pixels.effects
            # points of the scene, to bound the image motion
            v = self.renderer.mesh.vertices
            self._motion_points = v[self.rng.choice(len(v), min(len(v), 4000), replace=False)]
        low = (
            min(s.threshold_on, s.threshold_off)
            if s.calibration is None
            else min(np.median(self.pixels.con), np.median(self.pixels.coff))
        )
        self.threshold = scene.max_step_log * low

    # -- sampling --------------------------------------------------------------------------------

    def _log(self, radiance: np.ndarray, pixels: np.ndarray | None = None) -> np.ndarray:
        return self.channels.log(radiance, self.scene.sensor.dark_level, pixels)

    def _keys(self, first: _Key, times: list[float]) -> list[_Key]:
        """Key renders at ``times`` after ``first``: the environment's specular light exact at
        the last (an anchor), shared from ``first`` and the last where a pixel sees the same
        surface (evcap.sim.specular_reuse), exact elsewhere."""
        renders = [self._render(t) for t in times]
        anchor = self._exact(renders[-1].specular_inputs)
        n = self.camera.width * self.camera.height
        frames = []
        for t, r in zip(times[:-1], renders[:-1], strict=True):
            inputs = r.specular_inputs
            s = (t - first.t) / (times[-1] - first.t)
            spec = self._shared(first.frame, anchor, s, inputs, inputs.rows)
            frames.append(SpecularFrame.of(n, inputs, spec))
        frames.append(anchor)
        return [self._key_of(t, r, f) for t, r, f in zip(times, renders, frames, strict=True)]

    def _first_key(self, t_us: float) -> _Key:
        r = self._render(t_us)
        return self._key_of(t_us, r, self._exact(r.specular_inputs))

    def _render(self, t_us: float) -> RenderResult:
        """A key render, the environment's specular light left out."""
        with _timed(self.stats, "render"):
            self.stats.key_renders += 1
            return self.renderer.render(self.trajectory.pose(t_us * 1e-6), specular=False)

    def _exact(self, inputs: SpecularInputs) -> SpecularFrame:
        with _timed(self.stats, "specular"):
            self.stats.exact_specular += len(inputs.rows)
            spec = self.renderer.environment_specular(inputs)
            return SpecularFrame.of(self.camera.width * self.camera.height, inputs, spec)

    def _key_of(self, t_us: float, r, frame: SpecularFrame) -> _Key:
        r.radiance[r.specular_inputs.rows] += frame.specular[r.specular_inputs.rows]
        measured = self.channels.of(r.radiance)
        log = np.log(np.maximum(measured, 0.0) + self.scene.sensor.dark_level)
        return _Key(t_us, log, frame, r.depth)

    def _shared(self, a, b, s, inputs, pixels) -> np.ndarray:
        with _timed(self.stats, "specular"):
            spec, exact = specular_between(self.renderer, a, b, s, inputs, pixels)
            self.stats.exact_specular += exact
            self.stats.shared_specular += len(pixels) - exact
            return spec

    def _key_times(self, t_us: float, duration_us: float) -> list[float]:
        """The next key times after ``t_us``, up to and including the next anchor."""
        times = []
        while len(times) < ANCHOR_EVERY and t_us < duration_us:
            t_us = min(t_us + self._step_us(t_us), duration_us)
            times.append(t_us)
        return times

    def _step_us(self, t_us: float) -> float:
        """The next key step: the image motion stays under max_step_px."""
        t = t_us * 1e-6
        dt = 1e-4
        b = min(t + dt, self.trajectory.duration_s)
        if b <= t:
            return MAX_STEP_US
        moved = 0.0
        uv = []
        for T in (self.trajectory.pose(t), self.trajectory.pose(b)):
            pc = (self._motion_points - T[:3, 3]) @ T[:3, :3]
            uv.append(pc)
        front = (uv[0][:, 2] > 1e-3) & (uv[1][:, 2] > 1e-3)
        if front.any():
            a_px, b_px = self.camera.project(uv[0][front]), self.camera.project(uv[1][front])
            inside = (
                (a_px[:, 0] > -10)
                & (a_px[:, 0] < self.camera.width + 10)
                & (a_px[:, 1] > -10)
                & (a_px[:, 1] < self.camera.height + 10)
            )
            if inside.any():
                moved = float(np.linalg.norm(b_px[inside] - a_px[inside], axis=1).max())
        # rotation alone moves the background (the environment) too
        ra, rb = self.trajectory.pose(t)[:3, :3], self.trajectory.pose(b)[:3, :3]
        angle = np.arccos(np.clip((np.trace(ra.T @ rb) - 1) / 2, -1, 1))
        moved = max(moved, angle * max(self.camera.K[0, 0], self.camera.K[1, 1]) * 1.5)
        speed = moved / ((b - t) * 1e6)  # px per us
        if speed <= 0:
            return MAX_STEP_US
        return float(np.clip(self.scene.max_step_px / speed, MIN_STEP_US, MAX_STEP_US))

    def _render_at(self, pixels: np.ndarray, times_us: np.ndarray, a: _Key, b: _Key) -> np.ndarray:
        """The log signal of ``pixels``, each from the camera at its own time (between the key
        renders ``a`` and ``b``)."""
        with _timed(self.stats, "render"):
            unique, inverse = np.unique(times_us, return_inverse=True)
            poses = self.trajectory.poses(unique * 1e-6)
            rays = self.camera.rays()[pixels]
            rot = poses[inverse, :3, :3]
            dirs = np.einsum("nij,nj->ni", rot, rays)
            origins = poses[inverse, :3, 3]
            self.stats.refined_pixels += len(pixels)
            r = self.renderer.render_rays(origins, dirs, specular=False)
        inputs = r.specular_inputs
        s = (times_us[inputs.rows] - a.t) / (b.t - a.t)
        r.radiance[inputs.rows] += self._shared(a.frame, b.frame, s, inputs, pixels[inputs.rows])
        return self._log(r.radiance, pixels)

    def _refine(self, a: _Key, b: _Key):
        """Extra samples (pixel, t, value) where a pixel's signal changed too much."""
        t0, t1, v0, v1 = a.t, b.t, a.log, b.log
        px = np.flatnonzero(np.abs(v1 - v0) > self.threshold)
        lo, hi = np.full(len(px), t0), np.full(len(px), t1)
        vlo, vhi = v0[px], v1[px]
        out_px, out_t, out_v = [], [], []
        while len(px):
            keep = hi - lo > MIN_STEP_US
            px, lo, hi, vlo, vhi = px[keep], lo[keep], hi[keep], vlo[keep], vhi[keep]
            if not len(px):
                break
            mid = np.round((lo + hi) / 2)  # whole microseconds
            vmid = self._render_at(px, mid, a, b)
            out_px.append(px)
            out_t.append(mid)
            out_v.append(vmid)
            left = np.abs(vmid - vlo) > self.threshold
            right = np.abs(vhi - vmid) > self.threshold
            px = np.concatenate([px[left], px[right]])
            lo = np.concatenate([lo[left], mid[right]])
            hi = np.concatenate([mid[left], hi[right]])
            vlo, vhi = (
                np.concatenate([vlo[left], vmid[right]]),
                np.concatenate([vmid[left], vhi[right]]),
            )
        if not out_px:
            return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
        return np.concatenate(out_px), np.concatenate(out_t), np.concatenate(out_v)

    def _interval_events(self, a: _Key, b: _Key):
        extra_px, extra_t, extra_v = self._refine(a, b)
        t0, t1, v0, v1 = a.t, b.t, a.log, b.log
        with _timed(self.stats, "events"):
            n = len(v0)
            px = np.concatenate([np.arange(n), np.arange(n), extra_px])
            t = np.concatenate([np.full(n, t0), np.full(n, t1), extra_t])
            v = np.concatenate([v0, v1, extra_v])
            order = np.lexsort((t, px))
            px, t, v = px[order], t[order], v[order]
            offsets = np.searchsorted(px, np.arange(n + 1))
            if self.pixels.footprint_px > 0:
                self.pixels.set_image_speed(self._image_speed(a, b))
            return self.pixels.events(t, v, offsets, np.arange(n))

    def _image_speed(self, a: _Key, b: _Key) -> np.ndarray:
        """[P] how fast (pixels a microsecond) what each pixel sees at ``a`` moves in the image
        by ``b`` (the environment, seen at no distance, by the rotation alone)."""
        Ta, Tb = self.trajectory.pose(a.t * 1e-6), self.trajectory.pose(b.t * 1e-6)
        rays = self.camera.rays()
        hit = a.depth > 0
        cam_a = rays * np.where(hit, a.depth / rays[:, 2], 1.0)[:, None]
        world = cam_a @ Ta[:3, :3].T + np.where(hit[:, None], Ta[:3, 3], 0.0)
        cam_b = (world - np.where(hit[:, None], Tb[:3, 3], 0.0)) @ Tb[:3, :3]
        ahead = cam_b[:, 2] > 1e-6
        speed = np.zeros(len(rays))
        moved = self.camera.project(cam_b[ahead]) - self.camera.project(cam_a[ahead])
        speed[ahead] = np.linalg.norm(moved, axis=1) / max(b.t - a.t, 1e-9)
        return speed

    # -- the run ---------------------------------------------------------------------------------

    def run(self, writer: SessionWriter) -> SimulationStats:
        """Simulate the whole path into ``writer`` (events, frames, IMU, triggers)."""
        scene, stats = self.scene, self.stats
        duration_us = scene.trajectory.duration_s * 1e6
        width = self.camera.width
        exposures = {start: 0.0 for start in self._aps_times()}  # start -> sum of renders so far
        pending: list[tuple] = []  # events not yet safe to write (jitter may reorder them)
        jitter = self.effects.get("timestamp_jitter", {}).get("sigma_us", 0.0)
        key = self._first_key(0.0)
        self.pixels.start(key.log, key.t)
        while key.t < duration_us:
            for nxt in self._keys(key, self._key_times(key.t, duration_us)):
                et, epx, ep = self._interval_events(key, nxt)
                with _timed(self.stats, "noise"):
                    nt, npx, np_ = self.pixels.noise(key.t, nxt.t)
                    et, epx, ep = (
                        np.concatenate([et, nt]),
                        np.concatenate([epx, npx]),
                        np.concatenate([ep, np_]),
                    )
                    et, epx, ep = self.pixels.degrade(et, epx, ep)
                pending.append((et, epx, ep))
                late = 6 * jitter + self.pixels.max_delay_us  # how far back an event may go
                safe = nxt.t - late if nxt.t < duration_us else np.inf
                pending = self._write_events(writer, pending, safe, width)
                self._expose(writer, exposures, key, nxt)
                key = nxt
                if self.progress:
                    self.progress(key.t / 1e6, duration_us / 1e6)
        if scene.imu is not None:
            ti, accel, gyro, temp = imu_samples(
                self.trajectory, scene.imu, scene.units_per_meter, self.rng
            )
            writer.append_imu(ImuSamples(ti, accel, gyro, temp))
            stats.imu = len(ti)
        return stats

    def _measured(self, t_us: float, a: _Key, b: _Key) -> np.ndarray:
        """[P] what each pixel measures at ``t_us`` (between the key renders ``a`` and ``b``)."""
        r = self.renderer.render(self.trajectory.pose(t_us * 1e-6), specular=False)
        inputs = r.specular_inputs
        s = (t_us - a.t) / (b.t - a.t)
        light, _ = specular_between(self.renderer, a.frame, b.frame, s, inputs, inputs.rows)
        r.radiance[inputs.rows] += light
        return self.channels.of(r.radiance)

    def _write_events(self, writer, pending, safe_us, width):
        with _timed(self.stats, "write"):
            t = np.concatenate([p[0] for p in pending])
            px = np.concatenate([p[1] for p in pending])
            p = np.concatenate([p[2] for p in pending])
            now = t < safe_us
            order = np.argsort(t[now], kind="stable")
            tn, pxn = t[now][order], px[now][order]
            if len(tn):
                writer.append_events(
                    Events(
                        pxn % width,
                        pxn // width,
                        np.floor(np.maximum(tn, 0)).astype(np.int64),
                        p[now][order],
                        width,
                        self.camera.height,
                        self.scene.sensor.color_filter,
                    )
                )
                self.stats.events += len(tn)
            rest = ~now
            return [(t[rest], px[rest], p[rest])] if rest.any() else []

    def _aps_times(self) -> list[float]:
        a = self.scene.aps
        if a is None:
            return []
        duration_us = self.scene.trajectory.duration_s * 1e6
        starts = np.arange(0.0, duration_us - a.exposure_us, 1e6 / a.fps)
        return list(starts)

    def _expose(self, writer, exposures: dict, a: _Key, b: _Key) -> None:
        """Add the renders that fall between the key renders ``a`` and ``b`` (one a
        millisecond of exposure: motion blur; the specular light shared from ``a`` and ``b``)
        to the APS exposures open then; write the frames whose exposure ends by ``b``."""
        spec = self.scene.aps
        if not exposures:
            return
        n = max(1, int(np.ceil(spec.exposure_us / 1000)))
        with _timed(self.stats, "aps"):
            for start in [s for s in exposures if s < b.t]:
                for k in range(n):
                    t = start + (k + 0.5) * spec.exposure_us / n
                    if a.t <= t < b.t:
                        exposures[start] = exposures[start] + self._measured(t, a, b)
                end = start + spec.exposure_us
                if end > b.t:
                    continue
                mean = exposures.pop(start) / n
                raw = aps_frame(mean, spec, self.rng).reshape(self.camera.height, self.camera.width)
                t0, t1 = int(round(start)), int(round(end))
                writer.append_frames(Frames(raw[None], [t0], [spec.exposure_us]))
                writer.append_triggers(
                    Triggers(
                        [t0, t0, t1, t1],
                        [
                            TriggerKind.APS_FRAME_START,
                            TriggerKind.APS_EXPOSURE_START,
                            TriggerKind.APS_EXPOSURE_END,
                            TriggerKind.APS_FRAME_END,
                        ],
                    )
                )
                self.stats.frames += 1

    # -- ground truth ----------------------------------------------------------------------------

    def ground_truth(self) -> GroundTruth:
        """Renders at gt.fps along the path and at held-out views (under the scene's light and
        the second one), with what the events were made with."""
        with _timed(self.stats, "gt"):
            g = self.scene.gt
            times = np.arange(0.0, self.scene.trajectory.duration_s + 1e-9, 1.0 / g.fps)
            path = _rendered(self.renderer, self.trajectory.poses(times))
            held_out, relight = None, None
            test = self._test_poses(g.test_views)
            if len(test):
                held_out = _rendered(self.renderer, test)
                relit = Renderer(dataclasses.replace(self.scene, lighting=g.relight))
                held_out.relit_radiance = _rendered(relit, test).radiance
                relight = relit.env.table(256).astype(np.float32)
        spec, shape = self.scene.camera, (self.camera.height, self.camera.width)
        return GroundTruth(
            source="evcap simulate",
            t=np.round(times * 1e6).astype(np.int64),
            path=path,
            held_out=held_out,
            K=self.camera.K,
            distortion_model=spec.distortion_model,
            distortion=np.asarray(spec.distortion, np.float64),
            threshold_on=self.pixels.con.reshape(shape).astype(np.float32),
            threshold_off=self.pixels.coff.reshape(shape).astype(np.float32),
            relight_environment=relight,
            renderer_version=RENDERER_VERSION,
            hot_pixels=self.pixels.hot.astype(np.int64),
            notes={
                "scene": self.scene.name,
                "seed": self.seed,
                "charuco": json.dumps([_board_json(b) for b in self.renderer.boards if b]),
            },
        )

    def calibration(self) -> Calibration:
        """The sensor's true calibration."""
        spec = self.scene.camera
        return true_calibration(
            self.pixels,
            self.camera.width,
            self.camera.height,
            self.camera.K,
            spec.distortion_model,
            spec.distortion,
        )

    def _test_poses(self, count: int) -> np.ndarray:
        """Held-out views: off the path (moved by a tenth of the distance to the target,
        looking at it), at times spread over the path."""
        if count <= 0:
            return np.zeros((0, 4, 4))
        rng = np.random.default_rng(self.seed + 1_000_003)
        target = self.trajectory.target
        out = []
        for t in (np.arange(count) + 0.5) / count * self.trajectory.duration_s:
            T = self.trajectory.pose(t).copy()
            eye = T[:3, 3]
            offset = rng.normal(size=3)
            offset *= 0.1 * np.linalg.norm(eye - target) / np.linalg.norm(offset)
            T[:3, 3] = eye + offset
            T[:3, :3] = look_at(T[:3, 3], target)
            out.append(T)
        return np.array(out)


def _rendered(renderer: Renderer, poses: np.ndarray) -> TruthViews:
    """Every map the renderer makes, at each pose."""
    renders = [renderer.render_full(T) for T in poses]
    return TruthViews(poses, **{k: np.stack([r[k] for r in renders]) for k in renders[0]})


def _board_json(board: dict) -> dict:
    return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in board.items()}


def simulate(
    scene: Scene,
    output: str | Path,
    *,
    seed: int | None = None,
    overwrite: bool = False,
    fixture: str | Path | None = None,
    progress: Callable[[float, float], None] | None = None,
) -> SimulationStats:
    """Simulate ``scene`` into the session ``output`` (with /gt, /poses, /calibration); with
    ``fixture``, also write a hardware-replay fixture of it."""
    output = Path(output)
    if output.exists() and not overwrite:
        raise InputError(f"{output} exists; choose another name or pass --force")
    sim = Simulator(scene, seed=seed, progress=progress)
    cam = sim.camera
    sensor = SensorInfo(
        "simulated",
        cam.width,
        cam.height,
        scene.sensor.color_filter,
        f"SIM-{scene.name}"[:32],
        EPOCH_US,
    )
    attrs = {
        "scene": scene.name,
        "scene_file": str(scene.path),
        "seed": sim.seed,
        "effects": json.dumps(sim.effects),
        "sensor_profile": scene.sensor.profile,
    }
    # written under another name and renamed when whole: an interrupted simulation leaves
    # nothing half-made (nor harms what ``output`` held), and is repeated exactly by running
    # it again
    with atomic_path(output) as partial:
        with SessionWriter(partial, sensor, attrs=attrs, overwrite=True) as writer:
            stats = sim.run(writer)
        sim.ground_truth().write(partial)
        times = np.arange(0.0, scene.trajectory.duration_s + 1e-9, 1.0 / POSE_RATE_HZ)
        t = np.round(times * 1e6).astype(np.int64)
        Poses(t, sim.trajectory.poses(times), source="ground truth").write(partial)
        sim.calibration().write(partial)
    if fixture is not None:
        from evcap.sim.fixture import write_session_fixture

        write_session_fixture(output, fixture)
    return stats
