"""`evcap calibrate`: what a recording allows to measure about its sensor (intrinsics and
distortion, per-pixel contrast thresholds, hot pixels, noise, refractory period), written to
the session's /calibration group with the biases it was measured under. The intrinsics may come
from another tool's calibration file instead (`--intrinsics`: Kalibr, ROS, VINS, DV), with the
camera-IMU transform and time shift where the file has them."""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from evcap.calib.board import DEFAULT_BOARD, Board
from evcap.calib.camera_imu import camera_imu
from evcap.calib.intrinsics import IntrinsicsResult, calibrate_intrinsics
from evcap.calib.noise import NoiseStats, measure_noise
from evcap.calib.thresholds import DATASHEET_THRESHOLDS, ThresholdFit, fit_thresholds
from evcap.errors import CalibrationError, InputError
from evcap.importers.calibration_files import CameraCalibration, check_size
from evcap.records import Calibration
from evcap.records.calibration import BoardViews, describe_camera_imu
from evcap.session import Session

SKIPPABLE = ("intrinsics", "thresholds")  # the noise is always measured: it finds the hot pixels
# Frames of the board made from the events when the recording has no APS frames: rate and
# high-pass corner measured on the simulated hand-held sweep (50 Hz, 3 Hz: 40 views, focal length
# within 0.5 %; 20 Hz: the board smeared, found in a third as many frames); slower motion wants
# a lower corner, faster a higher one, so each is tried
EVENT_FRAME_HZ = 50.0
EVENT_FRAME_CUTOFFS_HZ = (0.3, 1.0, 3.0, 10.0)
MIN_EVENTS = 1000
UNCERTAIN_F = 0.005  # a focal length standard deviation above this share gets a warning


@dataclass
class CalibrationRun:
    """What `evcap calibrate` measured and what it rests on; `record()` is what it writes."""

    width: int
    height: int
    K: np.ndarray | None  # 3 x 3, pixels; None: not known (not measured, none kept)
    dist: np.ndarray  # coefficients of distortion_model (OpenCV order)
    distortion_model: str  # "none", "radtan"
    intrinsics_source: str  # "APS frames", "event frames", or what was kept
    threshold_on: np.ndarray  # [H, W] float32, log units
    threshold_off: np.ndarray
    threshold_source: str
    threshold_confidence: np.ndarray | None  # [H, W] 0..1; None: not fitted
    noise: NoiseStats
    intrinsics: IntrinsicsResult | None = None
    thresholds: ThresholdFit | None = None
    board: Board | None = None
    biases: dict | None = None  # bias codes in force while recording; None: not recorded
    warnings: list[str] = field(default_factory=list)
    # the IMU's frame into the camera's (4 x 4, m) and t_imu = t_cam + shift, when known
    T_cam_imu: np.ndarray | None = None
    timeshift_cam_imu_us: float = 0.0
    camera_imu_source: str = ""  # the file they came from, or "kept (...)"

    @property
    def rms_reprojection_px(self) -> float:
        return float(self.intrinsics.rms_px) if self.intrinsics else float("nan")

    def record(self) -> Calibration:
        """The session's /calibration: the measurement, with how each part was measured in its
        notes."""
        n = self.noise
        notes: dict = {
            "intrinsics_source": self.intrinsics_source,
            "threshold_source": self.threshold_source,
            "intrinsics_std_px": self.intrinsics.std if self.intrinsics else np.full(4, np.nan),
            "biases": json.dumps(self.biases) if self.biases is not None else "not recorded",
        }
        if self.board is not None:
            notes["board"] = json.dumps(self.board.to_attrs())
        views = None
        if self.intrinsics is not None:
            notes["rejected_views"] = json.dumps(
                [{"t_us": int(t), "reason": r} for t, r in self.intrinsics.rejected]
            )
            per_view = self.intrinsics.per_view
            views = BoardViews(
                t_us=np.array([v[0] for v in per_view], np.int64),
                rms_px=np.array([v[1] for v in per_view], np.float64),
                corners=np.array([v[2] for v in per_view], np.int64),
            )
        if self.thresholds is not None:
            t = self.thresholds
            notes["threshold_channel_means"] = json.dumps(
                {k: [float(v[0]), float(v[1])] for k, v in t.channel_means.items()}
            )
            notes["threshold_confident_share"] = float((t.confidence >= 0.5).mean())
        if self.warnings:
            notes["warnings"] = json.dumps(self.warnings)
        if self.T_cam_imu is not None:
            notes["camera_imu_source"] = self.camera_imu_source
        confidence = self.threshold_confidence
        if confidence is None:  # not fitted: no pixel is known well
            confidence = np.zeros((self.height, self.width), np.float32)
        return Calibration(
            width=self.width,
            height=self.height,
            source="evcap calibrate",
            K=self.K,
            distortion_model=self.distortion_model,
            dist=self.dist,
            threshold_on=self.threshold_on,
            threshold_off=self.threshold_off,
            threshold_confidence=confidence,
            hot_pixels=n.hot_pixels,
            event_rate_hz=n.rate_hz,
            views=views,
            rms_reprojection_px=self.rms_reprojection_px,
            refractory_period_us=float(n.refractory_period_us),
            background_activity_hz=float(n.background_activity_hz),
            shot_noise_hz=float(n.shot_noise_hz),
            T_cam_imu=self.T_cam_imu,
            timeshift_cam_imu_us=self.timeshift_cam_imu_us,
            notes=notes,
        )

    def summary(self) -> str:
        """What was measured, for a person, a few lines."""
        lines = []
        K, i = self.K, self.intrinsics
        if K is None:
            lines.append(f"intrinsics: {self.intrinsics_source}")
        else:
            how = f" ({self.intrinsics_source}, {len(i.per_view)} views)" if i else ""
            line = (
                f"intrinsics{how or ', ' + self.intrinsics_source}: fx {K[0, 0]:.2f} fy "
                f"{K[1, 1]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f} px, {self.distortion_model} "
                f"{' '.join(f'{d:+.4f}' for d in self.dist)}"
            )
            lines.append(line + (f"; RMS reprojection {i.rms_px:.3f} px" if i else ""))
        if i is not None:
            reasons: dict[str, int] = {}
            for _, r in i.rejected:
                reasons[r.split(" (")[0]] = reasons.get(r.split(" (")[0], 0) + 1
            if reasons:
                lines.append(
                    "  views not used: " + ", ".join(f"{n} {r}" for r, n in reasons.items())
                )
        if self.T_cam_imu is not None:
            relation = describe_camera_imu(self.T_cam_imu, self.timeshift_cam_imu_us)
            lines.append(f"camera-IMU, {self.camera_imu_source}: {relation}")
        if self.thresholds is not None:
            t = self.thresholds
            means = ", ".join(f"{k} {v[0]:.3f}/{v[1]:.3f}" for k, v in t.channel_means.items())
            lines.append(
                f"thresholds ON/OFF ({self.threshold_source}): {means} log units; "
                f"{(t.confidence >= 0.5).mean():.0%} of pixels fitted with confidence, "
                "the others take their channel's mean"
            )
        else:
            lines.append(
                f"thresholds ({self.threshold_source}): ON {self.threshold_on.mean():.3f}, "
                f"OFF {self.threshold_off.mean():.3f} log units"
            )
        n = self.noise
        if n.duration_us == 0:
            lines.append("hot pixels and noise: not measured")
        else:
            lines.append(
                f"hot pixels: {int(n.hot_pixels.sum())}; background activity "
                f"{n.background_activity_hz:.3g} Hz and shot noise {n.shot_noise_hz:.3g} Hz "
                f"per pixel; refractory period {n.refractory_period_us:.0f} us"
            )
        lines.append("biases: " + ("as recorded in the session" if self.biases else "not recorded"))
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def calibrate(
    path: str | Path,
    *,
    board: Board = DEFAULT_BOARD,
    skip: frozenset[str] = frozenset(),
    intrinsics: CameraCalibration | None = None,
    say: Callable[[str], None] = lambda line: None,
    progress: Callable[[int, int, str], None] | None = None,
) -> CalibrationRun:
    """Measure what the session at ``path`` allows. ``skip``: parts of SKIPPABLE not to measure
    (what the session's /calibration already holds is kept for them). ``intrinsics``: taken
    from another tool's file (checked against the sensor) instead of measured on a board, with
    its camera-IMU transform. ``progress(done, total, stage)`` follows the thresholds' fit and
    the board's detection."""
    report = progress or (lambda done, total, stage: None)
    unknown = set(skip) - set(SKIPPABLE)
    if unknown:
        raise InputError(
            f"cannot skip {sorted(unknown)}; what can be skipped: {', '.join(SKIPPABLE)}"
        )
    if intrinsics is not None and "intrinsics" in skip:
        raise InputError(
            "--intrinsics gives the intrinsics and --skip intrinsics keeps the session's: "
            "give one of them"
        )
    with Session.open(path) as s:
        sensor = s.sensor
        events = s.events()
        frames = s.frames()
        old = _stored(s, damaged_ok=not skip)
        biases, changed = _biases(s)
    w, h = sensor.width, sensor.height
    if intrinsics is not None:
        check_size(intrinsics, w, h, str(path))
        say(f"intrinsics: {intrinsics.describe()}")
    warnings = [] if intrinsics is None else list(intrinsics.warnings)
    if len(events) < MIN_EVENTS:
        if intrinsics is None:
            raise CalibrationError(
                f"{path}: {len(events)} events; calibrating the sensor needs at least "
                f"{MIN_EVENTS:,} (record longer, with the camera moving)"
            )
        return _nominal(intrinsics, w, h, len(events), biases, warnings, old)
    if changed:
        warnings.append(
            f"biases changed while recording ({', '.join(changed)}): "
            "the thresholds hold for a mix of settings"
        )

    say("noise: hot pixels, background activity, refractory period")
    noise = measure_noise(events, frames if len(frames) else None)

    cal_thresholds = None
    kept = old is not None and old.threshold_on is not None and old.threshold_off is not None
    if "thresholds" in skip and kept:
        on, off = old.thresholds()
        t_source, confidence = f"kept ({old.source})", old.threshold_confidence
    elif "thresholds" not in skip and len(frames) >= 3:
        say(f"thresholds: {len(frames)} APS frames against {len(events):,} events")
        cal_thresholds = fit_thresholds(
            events,
            frames,
            sensor.color_filter,
            exclude=noise.hot_pixels,
            refractory_us=noise.refractory_period_us,
            progress=lambda done, total: report(done, total, "thresholds"),
        )
        on, off, t_source = cal_thresholds.on, cal_thresholds.off, "APS frames vs events"
        confidence = cal_thresholds.confidence
    else:
        on, off = _balanced_thresholds(events, noise.hot_pixels)
        t_source = "no APS frames: the datasheet's mean level, ON/OFF ratio from the event counts"
        confidence = None
        if "thresholds" not in skip:
            warnings.append("no APS frames: the thresholds are not measured per pixel")

    fitted = None
    if intrinsics is not None:
        K, model, dist = intrinsics.K, intrinsics.distortion_model, intrinsics.dist
        i_source = intrinsics.describe()
    elif "intrinsics" in skip:
        if old is not None and old.K is not None:
            K, model, dist = old.intrinsics()
            i_source = f"kept ({old.source})"
        else:
            warnings.append(
                "no intrinsics (none measured, none stored before): calibrate a recording of "
                "the board and pass this session to its --apply-to"
            )
            K, model, dist, i_source = None, "none", np.zeros(0), "not measured"
    else:
        if len(frames):
            say(f"intrinsics: the board in {len(frames)} APS frames")
            images, times, i_source = frames.data, frames.t + frames.exposure_us // 2, "APS frames"
        else:
            say(f"intrinsics: the board in event frames at {EVENT_FRAME_HZ:g} Hz")
            images, times = _event_images(events, on, off, noise.hot_pixels, board)
            i_source = "event frames"
        try:
            fitted = calibrate_intrinsics(
                images,
                times,
                sensor.color_filter,
                board,
                progress=lambda done, total: report(done, total, "finding the board"),
            )
        except CalibrationError as e:
            raise CalibrationError(
                f"{e} (to measure only the thresholds, hot pixels and noise: --skip intrinsics)"
            ) from None
        K, dist, model = fitted.K, fitted.dist, fitted.distortion_model
        spread = float(np.max(fitted.std[:2] / np.diag(K)[:2]))
        if spread > UNCERTAIN_F:
            warnings.append(
                f"the views leave the focal length uncertain by {spread:.1%}: move the board "
                "over the whole image, nearer and farther, tilted up to 45 degrees"
            )
    return CalibrationRun(
        width=w,
        height=h,
        K=K,
        dist=np.asarray(dist, np.float64),
        distortion_model=model,
        intrinsics_source=i_source,
        threshold_on=np.asarray(on, np.float32),
        threshold_off=np.asarray(off, np.float32),
        threshold_source=t_source,
        threshold_confidence=confidence,
        noise=noise,
        intrinsics=fitted,
        thresholds=cal_thresholds,
        board=board if fitted is not None else None,
        biases=biases,
        warnings=warnings,
        **camera_imu(intrinsics, old),
    )


def _nominal(
    intrinsics: CameraCalibration,
    width: int,
    height: int,
    n_events: int,
    biases: dict | None,
    warnings: list[str],
    stored: Calibration | None,
) -> CalibrationRun:
    """The file's intrinsics with the datasheet's nominal thresholds, the noise not measured:
    a recording with too few events to measure the sensor from."""
    why = f"{n_events} events are too few to measure the sensor (at least {MIN_EVENTS:,})"
    shape = (height, width)
    on, off = DATASHEET_THRESHOLDS
    return CalibrationRun(
        width=width,
        height=height,
        K=intrinsics.K,
        dist=intrinsics.dist,
        distortion_model=intrinsics.distortion_model,
        intrinsics_source=intrinsics.describe(),
        threshold_on=np.full(shape, on, np.float32),
        threshold_off=np.full(shape, off, np.float32),
        threshold_source=f"the datasheet's nominal values (14.3 % ON, 22.5 % OFF): {why}",
        threshold_confidence=None,
        noise=NoiseStats(
            hot_pixels=np.zeros(shape, bool),
            rate_hz=np.zeros(shape, np.float32),
            background_activity_hz=0.0,
            shot_noise_hz=0.0,
            refractory_period_us=0.0,
            notes=(f"not measured: {why}",),
        ),
        biases=biases,
        warnings=[*warnings, f"{why}: thresholds nominal, hot pixels and noise not measured"],
        **camera_imu(intrinsics, stored),
    )


def check_targets(paths: list[str | Path]) -> None:
    """Each session a calibration will be written to opens and may be written: checked before
    anything is computed or written."""
    for path in paths:
        with Session.open(path):
            pass
        if not os.access(path, os.W_OK):
            raise InputError(f"{path}: no permission to write to it")


def write_calibration(paths: list[str | Path], cal: CalibrationRun) -> None:
    """Replace the sessions' /calibration with ``cal``, after checking every one of them
    against it (its sensor size), so that a bad target leaves all of them as they were."""
    check_targets(paths)
    record = cal.record()
    records = [_for_target(path, cal, record) for path in paths]
    for path, r in zip(paths, records, strict=True):
        r.write(path, replace=True)


def _for_target(path: str | Path, cal: CalibrationRun, record: Calibration) -> Calibration:
    """``record`` as written to the session ``path`` (checked against its sensor), warning
    when that session was recorded under other biases."""
    with Session.open(path) as s:
        size = (s.sensor.width, s.sensor.height)
        biases, _ = _biases(s)
    if size != (cal.width, cal.height):
        raise InputError(
            f"{path}: its sensor is {size[0]} x {size[1]}, the calibration is for "
            f"{cal.width} x {cal.height}"
        )
    if cal.biases is None or biases is None or biases == cal.biases:
        return record
    differ = sorted(k for k in set(biases) | set(cal.biases) if biases.get(k) != cal.biases.get(k))
    warnings = [*cal.warnings, f"{path} was recorded under other biases ({', '.join(differ)})"]
    return dataclasses.replace(record, notes={**record.notes, "warnings": json.dumps(warnings)})


def _stored(s: Session, damaged_ok: bool = False) -> Calibration | None:
    """The session's /calibration now (kept for the parts not measured), or None; with
    ``damaged_ok`` None too when it cannot be read (a new calibration replaces it whole)."""
    if not Calibration.present(s):
        return None
    try:
        return Calibration.read(s)
    except InputError:
        if damaged_ok:
            return None
        raise


def _biases(s: Session) -> tuple[dict | None, list[str]]:
    """(the bias codes at the start of the recording or None, the biases changed during it)."""
    raw = s.attrs.get("biases")
    biases = json.loads(raw) if raw else None
    changed = sorted(
        {name.removeprefix("bias.") for _, name, _ in s.settings_log() if name.startswith("bias.")}
    )
    return biases, changed


def _balanced_thresholds(events, hot) -> tuple[np.ndarray, np.ndarray]:
    """Uniform thresholds at the datasheet's mean level whose ON/OFF ratio balances the event
    counts: a scene that comes back to the same brightness gives C_on N_on = C_off N_off.
    (The ratio matters: frames integrated from the events drift with a wrong one.)"""
    keep = ~hot[events.y, events.x]
    n_on = max(int(events.p[keep].sum()), 1)
    n_off = max(int(keep.sum()) - n_on, 1)
    level = float(np.mean(DATASHEET_THRESHOLDS))
    shape = (events.height, events.width)
    on = np.full(shape, 2 * level * n_off / (n_on + n_off), np.float32)
    off = np.full(shape, 2 * level * n_on / (n_on + n_off), np.float32)
    return on, off


def _event_images(events, on, off, hot, board: Board) -> tuple[np.ndarray, np.ndarray]:
    """Pseudo-APS frames (10-bit, linear) from the events, for finding the board: made with
    each of EVENT_FRAME_CUTOFFS_HZ, keeping those in which the board shows most often (the
    corner that suits depends on how fast the camera moves)."""
    from evcap.calib.intrinsics import MIN_CORNERS, detect_board, frame_to_gray
    from evcap.event_frames import high_pass_frames

    step = int(1e6 / EVENT_FRAME_HZ)
    times = np.arange(int(events.t[0]) + step, int(events.t[-1]), step, dtype=np.int64)
    if len(times) == 0:
        raise CalibrationError(
            f"the events span {(events.t[-1] - events.t[0]) / 1e6:.2f} s: too short to make "
            "frames of the board from them"
        )
    best, best_views = None, -1
    for cutoff in EVENT_FRAME_CUTOFFS_HZ:
        log_change = high_pass_frames(
            events, times, cutoff_hz=cutoff, threshold_on=on, threshold_off=off, exclude=hot
        )
        images = np.clip(512 * np.exp(log_change), 0, 1023).astype(np.uint16)
        views = sum(
            len(detect_board(frame_to_gray(im, events.color_filter), board)[1]) >= MIN_CORNERS
            for im in images
        )
        if views > best_views:
            best, best_views = images, views
    return best, times
