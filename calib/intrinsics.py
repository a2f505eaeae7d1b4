"""Intrinsics and lens distortion from APS frames of a ChArUco board.

The frames are raw Bayer mosaics. Each channel's pixels are divided by that channel's white
level, which makes the mosaic of a gray board flat gray at full resolution (demosaicing would
blur the corners the detector measures), then gamma-encoded to 8 bits. The board's corners are
detected in every frame; views with too few corners are set aside, a varied subset is chosen
(farthest-point sampling of the board's outline in the image), OpenCV's calibrateCamera solves
for K and the distortion, and views whose reprojection error is far above the median are
dropped before a second, final solve.

Pixel centres are at integer coordinates (OpenCV's convention); times are microseconds.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from evcap.calib.board import Board
from evcap.errors import CalibrationError, InputError
from evcap.events import COLOR_FILTERS, Channel, pixel_channels
from evcap.streams import APS_MAX

DISTORTION_MODELS = ("radtan", "none")
"""radtan: k1 k2 p1 p2 k3 in OpenCV's order, k3 held at 0 (Kalibr's radtan); none: a pinhole."""

MIN_CORNERS = 8  # per view; fewer constrain a homography (8 unknowns) too weakly
MIN_VIEWS = 6  # below this the focal length and the distortion trade off freely
# The fit's spread falls with every distinct view (simulated sweep, 75 frames: std of cy 0.59 px
# with 40 views, 0.39 px with all 75) and calibrateCamera on 100 views takes about a second.
MAX_VIEWS = 100
WHITE_PERCENTILE = 99.0  # a channel's white level; the maximum would follow hot pixels
GAMMA = 2.2  # measured on the simulated board: corners 10 % closer to the truth than linear
SIMILAR_PX = 1.0  # RMS motion of the board's outline below which a view adds nothing new
OUTLIER_FACTOR = 3.0  # a view whose RMS is this many times the median is dropped...
OUTLIER_FLOOR_PX = 0.5  # ...if it is also above this (a sharp image's median can be tiny)


@dataclass
class IntrinsicsResult:
    """A camera calibration and what it rests on."""

    K: np.ndarray  # [3, 3] camera matrix, pixels
    dist: np.ndarray  # radtan: [5] k1 k2 p1 p2 k3 (OpenCV's order); none: [0]
    distortion_model: str  # one of DISTORTION_MODELS
    rms_px: float  # RMS reprojection error over every corner of the views used
    width: int  # image size, pixels
    height: int
    per_view: list[tuple[int, float, int]] = field(default_factory=list)  # (t_us, rms_px, corners)
    rejected: list[tuple[int, str]] = field(default_factory=list)  # (t_us, why), in time order
    std: np.ndarray = field(default_factory=lambda: np.zeros(4))  # fx fy cx cy std, px (OpenCV)
    frames_seen: int = 0  # frames looked at
    frames_with_board: int = 0  # frames in which the board was detected at all


def frame_to_gray(frame: np.ndarray, color_filter: str) -> np.ndarray:
    """An 8-bit gray image [H, W] of a raw 10-bit APS frame [H, W], each color channel
    scaled by its own white level so that the mosaic of a gray surface comes out flat."""
    if color_filter not in COLOR_FILTERS:
        raise InputError(f"unknown color filter {color_filter!r}; expected one of {COLOR_FILTERS}")
    frame = np.asarray(frame)
    if frame.ndim != 2:
        raise InputError(f"a frame must be height x width, got shape {frame.shape}")
    flat = frame.astype(np.float32).ravel()
    out = np.empty_like(flat)
    for pixels in _channel_pixels(frame.shape, color_filter):
        values = flat[pixels]
        # at least one count: a black frame stays black instead of dividing by zero
        white = max(float(np.percentile(values, WHITE_PERCENTILE)), 1.0)
        out[pixels] = values / white
    out = np.clip(out, 0.0, 1.0) ** (1.0 / GAMMA)
    return np.round(out * 255).astype(np.uint8).reshape(frame.shape)


@functools.lru_cache(maxsize=8)
def _channel_pixels(shape: tuple[int, int], color_filter: str) -> tuple[np.ndarray, ...]:
    """The flat indices of each channel's pixels."""
    y, x = np.mgrid[0 : shape[0], 0 : shape[1]]
    channels = pixel_channels(x, y, color_filter).ravel()
    return tuple(np.flatnonzero(channels == c) for c in Channel if (channels == c).any())


@functools.lru_cache(maxsize=8)
def _detector(board: Board) -> cv2.aruco.CharucoDetector:
    return cv2.aruco.CharucoDetector(board.cv())


def detect_board(image_u8: np.ndarray, board: Board) -> tuple[np.ndarray, np.ndarray]:
    """The board's inner corners in an 8-bit gray image: (corners [M, 2] float64 pixels,
    ids [M] int64), both empty when the board is not found."""
    image = np.asarray(image_u8)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise InputError(f"detect_board needs a 2-D uint8 image, got {image.dtype} {image.shape}")
    corners, ids, _, _ = _detector(board).detectBoard(image)
    if ids is None or len(ids) == 0:
        return np.zeros((0, 2)), np.zeros(0, np.int64)
    return corners.reshape(-1, 2).astype(np.float64), ids.reshape(-1).astype(np.int64)


@dataclass
class _View:
    t_us: int
    corners: np.ndarray  # [M, 2] image points
    ids: np.ndarray  # [M]
    obj: np.ndarray  # [M, 3] board points, metres
    outline: np.ndarray  # [8] the board's 4 outer corners in the image (by homography)


def calibrate_intrinsics(
    frames: np.ndarray,
    times: np.ndarray,
    color_filter: str,
    board: Board,
    *,
    distortion_model: str = "radtan",
    max_views: int = MAX_VIEWS,
    progress: Callable[[int, int], None] | None = None,
) -> IntrinsicsResult:
    """Calibrate from raw APS frames [N, H, W] (10-bit) taken at ``times`` [N] (us) of
    ``board``; ``progress(done, total)`` follows the detection. Raises CalibrationError when
    too few frames show the board well enough."""
    frames = np.asarray(frames)
    times = np.asarray(times).astype(np.int64, copy=False)
    if frames.ndim != 3 or times.shape != (frames.shape[0],):
        raise InputError(
            f"frames must be N x height x width with N times, got {frames.shape} and {times.shape}"
        )
    if distortion_model not in DISTORTION_MODELS:
        raise InputError(
            f"unknown distortion model {distortion_model!r}; expected one of "
            f"{', '.join(DISTORTION_MODELS)}"
        )
    if max_views < MIN_VIEWS:
        raise InputError(f"max_views must be at least {MIN_VIEWS}, not {max_views}")
    n, height, width = frames.shape
    if frames.size and (int(frames.max()) > APS_MAX or int(frames.min()) < 0):
        raise InputError(f"frames must hold raw APS values in 0..{APS_MAX}")

    views, rejected = [], []
    cv_board = board.cv()
    found = 0
    for i in range(n):
        corners, ids = detect_board(frame_to_gray(frames[i], color_filter), board)
        t = int(times[i])
        if len(ids):
            found += 1
        if len(ids) < MIN_CORNERS:
            why = f"only {len(ids)} corners (need {MIN_CORNERS})" if len(ids) else "board not found"
            rejected.append((t, why))
        elif cv_board.checkCharucoCornersCollinear(ids.reshape(-1, 1).astype(np.int32)):
            rejected.append((t, f"its {len(ids)} corners lie on one line"))
        else:
            views.append(_view(t, corners, ids, cv_board, board))
        if progress is not None:
            progress(i + 1, n)

    def too_few(usable: int) -> CalibrationError:
        return CalibrationError(
            f"the board was found in {found} of {n} frames and {usable} views are usable "
            f"(need {MIN_VIEWS} with {MIN_CORNERS}+ corners each): is --board right "
            f"({board.spec()})? move the board closer so that it fills more of the view, "
            "and tilt it"
        )

    if len(views) < MIN_VIEWS:
        raise too_few(len(views))
    chosen, left_out = _choose(views, max_views)
    rejected += left_out
    if len(chosen) < MIN_VIEWS:
        raise too_few(len(chosen))

    solved = _solve(chosen, width, height, distortion_model)
    rms_views = solved[3]
    cut = max(OUTLIER_FACTOR * float(np.median(rms_views)), OUTLIER_FLOOR_PX)
    keep = rms_views <= cut
    if not keep.all() and keep.sum() >= MIN_VIEWS:
        rejected += [
            (v.t_us, f"reprojection {e:.1f} px > {OUTLIER_FACTOR:g}x the median")
            for v, e, k in zip(chosen, rms_views, keep, strict=True)
            if not k
        ]
        chosen = [v for v, k in zip(chosen, keep, strict=True) if k]
        solved = _solve(chosen, width, height, distortion_model)
    rms, K, dist, rms_views, std = solved
    return IntrinsicsResult(
        K=K,
        dist=dist,
        distortion_model=distortion_model,
        rms_px=rms,
        width=width,
        height=height,
        per_view=[(v.t_us, float(e), len(v.ids)) for v, e in zip(chosen, rms_views, strict=True)],
        rejected=sorted(rejected),
        std=std,
        frames_seen=n,
        frames_with_board=found,
    )


def _view(
    t_us: int, corners: np.ndarray, ids: np.ndarray, cv_board: cv2.aruco.CharucoBoard, b: Board
) -> _View:
    obj, img = cv_board.matchImagePoints(
        corners.astype(np.float32).reshape(-1, 1, 2), ids.astype(np.int32).reshape(-1, 1)
    )
    obj, img = obj.reshape(-1, 3).astype(np.float64), img.reshape(-1, 2).astype(np.float64)
    H, _ = cv2.findHomography(obj[:, :2], img)
    w, h = b.cols * b.square_m, b.rows * b.square_m
    rim = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)
    if H is None:  # cannot happen for 8+ non-collinear corners; keep the view anyway
        outline = np.zeros(8)
    else:
        outline = cv2.perspectiveTransform(rim[:, None], H).reshape(-1)
    return _View(t_us, img, ids, obj, outline)


def _choose(views: list[_View], max_views: int) -> tuple[list[_View], list[tuple[int, str]]]:
    """At most max_views views, each as unlike the ones before as possible (farthest-point
    sampling of where the board's outline lies in the image); the rest with why."""
    outlines = np.stack([v.outline for v in views])
    first = int(np.argmax([len(v.ids) for v in views]))  # ties: the earliest
    chosen = [first]
    # RMS distance over the 4 outline corners to the nearest chosen view
    nearest = np.sqrt(((outlines - outlines[first]) ** 2).reshape(len(views), 4, 2).sum(2).mean(1))
    while len(chosen) < min(max_views, len(views)):
        nearest[chosen] = -1.0
        best = int(np.argmax(nearest))
        if nearest[best] < SIMILAR_PX:
            break
        chosen.append(best)
        d = np.sqrt(((outlines - outlines[best]) ** 2).reshape(len(views), 4, 2).sum(2).mean(1))
        nearest = np.minimum(nearest, d)
    nearest[chosen] = -1.0
    left_out = [
        (
            views[i].t_us,
            "too similar to a view already used"
            if nearest[i] < SIMILAR_PX
            else f"not needed ({max_views} views are enough)",
        )
        for i in range(len(views))
        if i not in set(chosen)
    ]
    return [views[i] for i in sorted(chosen)], left_out


def _solve(
    views: list[_View], width: int, height: int, model: str
) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(rms, K, dist, per-view rms, std of fx fy cx cy) of calibrateCamera on ``views``."""
    flags = cv2.CALIB_FIX_K3
    if model == "none":
        flags |= cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_ZERO_TANGENT_DIST
    obj = [v.obj.astype(np.float32) for v in views]
    img = [v.corners.astype(np.float32) for v in views]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    # OpenCV's threads sum the normal equations in any order: on one, the same views give the
    # same intrinsics bit for bit (and poses and reconstructions after them)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        rms, K, dist, _, _, std, _, per_view = cv2.calibrateCameraExtended(
            obj, img, (width, height), None, None, flags=flags, criteria=criteria
        )
    except cv2.error as e:
        raise CalibrationError(
            f"the calibration failed on {len(views)} views ({str(e).strip().splitlines()[-1]}): "
            "the views are too alike; move and tilt the board more"
        ) from None
    finally:
        cv2.setNumThreads(threads)
    dist = dist.reshape(-1)[:5].astype(np.float64)
    if not (np.isfinite(K).all() and np.isfinite(dist).all() and math.isfinite(rms)):
        raise CalibrationError(
            f"the calibration on {len(views)} views did not converge (not finite): the views "
            "are too alike; move and tilt the board more"
        )
    if model == "none":
        dist = np.zeros(0)
    return float(rms), K, dist, per_view.reshape(-1), std.reshape(-1)[:4].copy()
