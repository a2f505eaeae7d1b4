"""Intensity frames from a session's events, for structure from motion: the classical high-pass
filter (no weights, the default), a time surface (no weights; it does not change sign with the
direction of motion), or a recurrent network (E2VID, FireNet) from a checkpoint the user
gives. Frames are made on the raw mosaic (each pixel in its own color channel), then
demosaiced and tone-mapped to 8-bit gray for feature matching."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Literal, assert_never, get_args

import cv2
import numpy as np

from evcap.errors import InputError
from evcap.events import Events, pixel_channels
from evcap.streams import Frames

FrameKind = Literal["filter", "timesurface", "e2vid", "firenet"]  # no weights, or a network
KINDS: tuple[FrameKind, ...] = get_args(FrameKind)
EVENTS_PER_PIXEL = 0.35  # events per frame per pixel that set the rate (E2VID's window)
MIN_RATE_HZ, MAX_RATE_HZ = 5.0, 60.0
MIN_FRAMES = 60  # structure from motion wants views a few pixels of motion apart
FILTER_CUTOFF_HZ = 3.0  # the filter's corner: about 50 ms of memory
# the time surface's decay and its smoothing (a color filter's pixels see an edge only where
# their channel does: the blur joins its dotted ridge); measured on the demo's orbit (60 Hz
# frames): tau 17 or 33 ms, or a 1 px blur, give too few features to register half the frames
TIME_SURFACE_TAU_US = 50_000
TIME_SURFACE_BLUR_PX = 1.5


def frame_rate(events: Events) -> float:
    """Frames per second such that each frame spans about EVENTS_PER_PIXEL events per pixel,
    and a recording gives at least MIN_FRAMES frames, within MIN_RATE_HZ..MAX_RATE_HZ."""
    span_s = max((int(events.t[-1]) - int(events.t[0])) * 1e-6, 1e-6) if len(events) else 1.0
    rate = len(events) / span_s / (EVENTS_PER_PIXEL * events.width * events.height)
    return float(np.clip(max(rate, MIN_FRAMES / span_s), MIN_RATE_HZ, MAX_RATE_HZ))


def check_kind(kind: str) -> None:
    """Refuse a frame kind that is not one of KINDS, naming the known ones."""
    if kind not in KINDS:
        raise InputError(f"unknown frame kind {kind!r}; known: {', '.join(KINDS)}")


def memory_us(kind: FrameKind) -> int:
    """How long a frame of this kind looks back: the first frame is made this long after the
    first event, when it shows what a later one would (the filter's time constant, the time
    surface's decay; a network's frame only the events since the previous one)."""
    match kind:
        case "filter":
            return int(round(1e6 / (2 * np.pi * FILTER_CUTOFF_HZ)))
        case "timesurface":
            return TIME_SURFACE_TAU_US
        case "e2vid" | "firenet":
            return 0
        case _:
            assert_never(kind)


def demosaic(mosaic: np.ndarray, color_filter: str) -> np.ndarray:
    """[H, W, 3] RGB of a [H, W] mosaic: each channel interpolated from its own pixels (a
    normalised 3 x 3 convolution); MONO is copied to the three channels."""
    m = mosaic.astype(np.float32)
    if color_filter == "MONO":
        return np.repeat(m[..., None], 3, axis=2)
    h, w = m.shape
    yy, xx = np.mgrid[0:h, 0:w]
    channel = pixel_channels(xx.ravel(), yy.ravel(), color_filter).reshape(h, w)
    kernel = np.array([[0.25, 0.5, 0.25], [0.5, 1.0, 0.5], [0.25, 0.5, 0.25]], np.float32)
    out = np.empty((h, w, 3), np.float32)
    for c in range(3):
        mask = (channel == c).astype(np.float32)
        num = cv2.filter2D(m * mask, -1, kernel, borderType=cv2.BORDER_REFLECT)
        den = cv2.filter2D(mask, -1, kernel, borderType=cv2.BORDER_REFLECT)
        out[..., c] = num / np.maximum(den, 1e-6)
    return out


def to_gray8(rgb: np.ndarray, low: float = 1.0, high: float = 99.0) -> np.ndarray:
    """8-bit gray of a float RGB image, stretched between two percentiles."""
    gray = rgb @ np.array([0.299, 0.587, 0.114], np.float32)
    lo, hi = np.percentile(gray, [low, high])
    return np.clip((gray - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)


def event_frames(
    events: Events,
    times_us: np.ndarray,
    *,
    kind: FrameKind = "filter",
    weights: str | Path | None = None,
    threshold_on: np.ndarray | float = 0.2,
    threshold_off: np.ndarray | float = 0.2,
    hot_pixels: np.ndarray | None = None,
    aps: Frames | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """[K, H, W] uint8 gray frames at ``times_us`` from ``events`` (and for the filter, the
    recording's ``aps`` frames when it has them: the complementary filter)."""
    check_kind(kind)
    match kind:
        case "filter":
            if weights is not None:
                raise InputError("--weights is for --frames e2vid or firenet, not filter")
            from evcap.event_frames import high_pass_frames

            mosaics = high_pass_frames(
                events,
                times_us,
                cutoff_hz=FILTER_CUTOFF_HZ,
                threshold_on=threshold_on,
                threshold_off=threshold_off,
                exclude=hot_pixels,
                aps=aps,
            )
        case "timesurface":
            if weights is not None:
                raise InputError("--weights is for --frames e2vid or firenet, not timesurface")
            from evcap.event_frames import time_surface_frames

            surfaces = time_surface_frames(
                events, times_us, tau_us=TIME_SURFACE_TAU_US, exclude=hot_pixels
            )
            out = np.empty(surfaces.shape, np.uint8)
            for k, m in enumerate(surfaces):  # per pixel, whatever its color: no demosaicing
                smooth = cv2.GaussianBlur(m, (0, 0), TIME_SURFACE_BLUR_PX)
                out[k] = to_gray8(demosaic(smooth, "MONO"))
            return out
        case "e2vid" | "firenet":
            mosaics = _network_frames(events, times_us, kind, weights, hot_pixels, progress)
        case _:
            assert_never(kind)
    out = np.empty(mosaics.shape, np.uint8)
    for k, m in enumerate(mosaics):
        out[k] = to_gray8(demosaic(m, events.color_filter))
    return out


def _network_frames(events, times_us, kind, weights, hot_pixels, progress) -> np.ndarray:
    """The network's [0, 1] frames on the mosaic, each from the events since the previous."""
    from evcap.poses.e2vid import FrameReconstructor, load_checkpoint
    from evcap.poses.voxel import voxel_grid

    if weights is None:
        raise InputError(
            f"--frames {kind} needs the network's weights: --weights FILE (the released "
            f"{'E2VID_lightweight.pth.tar' if kind == 'e2vid' else 'firenet_1000.pth.tar'}); "
            "evcap never downloads them. Without weights use --frames filter"
        )
    net = load_checkpoint(weights)
    found = type(net).__name__.lower()
    if kind not in found:
        raise InputError(f"{weights} holds a {type(net).__name__} network, not {kind}")
    if hot_pixels is not None:
        events = events.select(~hot_pixels[events.y, events.x])
    reconstruct = FrameReconstructor(net)
    bounds = np.searchsorted(events.t, np.asarray(times_us, np.int64), side="right")
    out = np.zeros((len(times_us), events.height, events.width), np.float32)
    start = 0
    for k, stop in enumerate(bounds):
        if stop > start:
            e = slice(start, stop)
            v = voxel_grid(
                events.x[e],
                events.y[e],
                events.t[e],
                events.p[e],
                events.width,
                events.height,
                bins=net.num_bins,
            )
            out[k] = reconstruct(v)  # it normalises the voxels itself
        elif k:
            out[k] = out[k - 1]
        start = stop
        if progress:
            progress(k + 1, len(times_us))
    return out
