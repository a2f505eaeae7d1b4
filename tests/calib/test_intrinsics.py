"""Intrinsics from APS frames: synthetic Bayer views of a board seen by a camera with known K and
distortion, and the frames a calibration cannot use."""

import cv2
import numpy as np
import pytest

import evcap.calib.intrinsics as intrinsics
from evcap.calib.board import DEFAULT_BOARD
from evcap.calib.intrinsics import (
    MIN_CORNERS,
    calibrate_intrinsics,
    detect_board,
    frame_to_gray,
)
from evcap.errors import CalibrationError, InputError
from evcap.events import pixel_channels

pytestmark = pytest.mark.filterwarnings("error")

W, H = 346, 260
K_TRUE = np.array([[262.0, 0.0, 176.5], [0.0, 261.0, 127.0], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.32, 0.11, 4e-4, -3e-4, 0.0])
# board centre in the camera (metres) and its tilt about x, y, z (degrees): near, far, tilted
# both ways, in every part of the image
POSES = [
    ((0.0, 0.0, 0.34), (0, 0, 0)),
    ((-0.07, -0.05, 0.32), (25, -30, 5)),
    ((0.07, 0.05, 0.32), (-25, 30, -5)),
    ((0.07, -0.05, 0.30), (30, 25, 10)),
    ((-0.07, 0.05, 0.30), (-30, -25, -10)),
    ((0.0, 0.0, 0.26), (0, 40, 0)),
    ((0.0, 0.0, 0.28), (40, 0, 0)),
    ((-0.03, 0.03, 0.28), (-20, 35, 15)),
    ((0.10, 0.0, 0.36), (10, -25, 0)),
    ((-0.10, 0.0, 0.36), (-10, 25, 0)),
    ((0.0, 0.07, 0.36), (25, 10, -15)),
    ((0.0, -0.07, 0.36), (-25, -10, 15)),
    ((0.09, 0.07, 0.34), (20, -20, 20)),
    ((-0.09, -0.07, 0.34), (-20, 20, -20)),
    ((0.09, -0.07, 0.34), (-20, -20, -25)),
    ((-0.09, 0.07, 0.34), (20, 20, 25)),
    ((0.05, 0.0, 0.27), (0, -45, 0)),
    ((-0.05, 0.0, 0.27), (0, 45, 0)),
    ((0.0, 0.04, 0.27), (-45, 0, 0)),
    ((0.0, -0.04, 0.27), (45, 0, 0)),
    ((0.06, 0.05, 0.27), (35, -35, 30)),
    ((-0.06, -0.05, 0.27), (-35, 35, -30)),
    ((0.06, -0.05, 0.27), (-35, -35, 0)),
    ((-0.06, 0.05, 0.27), (35, 35, 0)),
]
GAINS = {0: 0.55, 1: 1.0, 2: 0.45, 3: 0.8}  # R G B MONO: a gray board through the filters
SUPERSAMPLE = 3


def rotation(degrees) -> np.ndarray:
    ax, ay, az = np.deg2rad(degrees)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rx @ ry @ rz


def render_views(poses, K, dist, color_filter="RGBG", seed=0) -> np.ndarray:
    """Raw 10-bit frames [N, H, W] of DEFAULT_BOARD, antialiased (3 x 3 samples a pixel), through
    the color filter, with read noise."""
    b = DEFAULT_BOARD
    px_per_m = 2500.0
    margin = 40  # texture pixels of white around the squares
    size = (round(b.cols * b.square_m * px_per_m), round(b.rows * b.square_m * px_per_m))
    texture = b.cv().generateImage(size, marginSize=0, borderBits=1)
    texture = cv2.copyMakeBorder(texture, margin, margin, margin, margin, cv2.BORDER_CONSTANT, 255)
    # where each sample of each pixel looks, as a normalized undistorted ray: one map for all
    s = SUPERSAMPLE
    v, u = np.mgrid[0 : H * s, 0 : W * s].astype(np.float64)
    pix = np.stack([(u - (s - 1) / 2) / s, (v - (s - 1) / 2) / s], -1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    rx, ry = cv2.undistortPoints(pix, K, dist, criteria=criteria).reshape(-1, 2).T
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W]
    gain = np.vectorize(GAINS.get)(pixel_channels(xx, yy, color_filter))
    frames = []
    for centre, angles in poses:
        R = rotation(angles)
        t = np.asarray(centre) - R @ [b.cols * b.square_m / 2, b.rows * b.square_m / 2, 0]
        # the board plane's points (x, y, 0) -> camera rays: a homography; invert it per ray
        to_board = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], t]))
        qx, qy, qz = (m[0] * rx + m[1] * ry + m[2] for m in to_board)
        # texel centres are at integer coordinates: board point 0 is texel -0.5 (+ margin)
        maps = [
            (q / qz * px_per_m + margin - 0.5).astype(np.float32).reshape(H * s, W * s)
            for q in (qx, qy)
        ]
        fine = cv2.remap(texture, *maps, cv2.INTER_LINEAR, borderValue=128).astype(np.float32)
        image = cv2.resize(fine, (W, H), interpolation=cv2.INTER_AREA) / 255.0
        raw = 40 + 800 * (0.04 + 0.85 * image) * gain + rng.normal(0, 2.0, (H, W))
        frames.append(np.clip(np.round(raw), 0, 1023).astype(np.uint16))
    return np.stack(frames)


@pytest.fixture(scope="module")
def views() -> tuple[np.ndarray, np.ndarray]:
    frames = render_views(POSES, K_TRUE, DIST_TRUE)
    return frames, np.arange(len(frames), dtype=np.int64) * 40_000


def relative_error(K: np.ndarray) -> np.ndarray:
    """|fx, fy, cx, cy - truth| / truth."""
    pick = [(0, 0), (1, 1), (0, 2), (1, 2)]
    return np.array([abs(K[i] / K_TRUE[i] - 1) for i in pick])


def test_recovers_known_intrinsics(views):
    frames, t = views
    r = calibrate_intrinsics(frames, t, "RGBG", DEFAULT_BOARD)
    assert (r.width, r.height) == (W, H)
    assert relative_error(r.K).max() < 0.005, r.K
    assert r.rms_px < 0.3
    assert r.dist.shape == (5,) and r.dist[4] == 0.0
    np.testing.assert_allclose(r.dist[:2], DIST_TRUE[:2], atol=0.02)
    assert len(r.per_view) == len(POSES) and not r.rejected
    assert all(e < 0.5 and n >= MIN_CORNERS for _, e, n in r.per_view)
    assert [v[0] for v in r.per_view] == list(t)
    assert r.frames_seen == r.frames_with_board == len(POSES)
    assert np.isfinite(r.std).all() and (r.std < 1.0).all()


def test_without_the_distortion_model_the_fit_is_worse(views):
    """'none' fits a pinhole: no coefficients, and the distortion shows in the error."""
    frames, t = views
    r = calibrate_intrinsics(frames, t, "RGBG", DEFAULT_BOARD, distortion_model="none")
    assert r.dist.shape == (0,) and np.isfinite(r.K).all()
    assert r.rms_px > 1.0


def test_pinhole_camera_with_the_none_model():
    frames = render_views(POSES[:8], K_TRUE, np.zeros(5), color_filter="MONO", seed=1)
    t = np.arange(len(frames), dtype=np.int64)
    r = calibrate_intrinsics(frames, t, "MONO", DEFAULT_BOARD, distortion_model="none")
    assert relative_error(r.K).max() < 0.005 and r.rms_px < 0.3


def test_unusable_frames_are_rejected_with_why(views):
    frames, t = views
    black = np.zeros_like(frames[:1])
    mixed = np.concatenate([black, frames, frames[3:4]])  # a black frame and a repeated view
    times = np.arange(len(mixed), dtype=np.int64) * 1000
    r = calibrate_intrinsics(mixed, times, "RGBG", DEFAULT_BOARD)
    assert dict(r.rejected) == {
        0: "board not found",
        times[-1]: "too similar to a view already used",
    }
    assert r.frames_seen == len(mixed) and r.frames_with_board == len(mixed) - 1
    assert relative_error(r.K).max() < 0.005


def test_max_views_keeps_the_most_different(views):
    frames, t = views
    r = calibrate_intrinsics(frames, t, "RGBG", DEFAULT_BOARD, max_views=8)
    assert len(r.per_view) == 8
    assert [why for _, why in r.rejected] == ["not needed (8 views are enough)"] * (len(POSES) - 8)
    # the first view chosen has the most corners; the others spread: not 8 consecutive ones
    assert relative_error(r.K).max() < 0.01


def test_a_misdetected_view_is_dropped_and_the_rest_solved_again(views, monkeypatch):
    frames, t = views
    detect = intrinsics.detect_board
    calls = []

    def jittered(image, board):
        corners, ids = detect(image, board)
        calls.append(1)
        if len(calls) == 5:  # the fifth frame's corners jump by pixels
            corners = corners + np.random.default_rng(0).normal(0, 3.0, corners.shape)
        return corners, ids

    monkeypatch.setattr(intrinsics, "detect_board", jittered)
    r = calibrate_intrinsics(frames, t, "RGBG", DEFAULT_BOARD)
    assert len(r.rejected) == 1 and r.rejected[0][0] == t[4]
    assert r.rejected[0][1].startswith("reprojection ") and "x the median" in r.rejected[0][1]
    assert relative_error(r.K).max() < 0.005 and r.rms_px < 0.3


def test_views_with_few_corners_are_rejected(views, monkeypatch):
    frames, t = views
    detect = intrinsics.detect_board
    calls = []

    def partial(image, board):
        corners, ids = detect(image, board)
        calls.append(1)
        return (corners[:5], ids[:5]) if len(calls) <= 2 else (corners, ids)

    monkeypatch.setattr(intrinsics, "detect_board", partial)
    r = calibrate_intrinsics(frames, t, "RGBG", DEFAULT_BOARD)
    assert r.rejected == [(t[0], "only 5 corners (need 8)"), (t[1], "only 5 corners (need 8)")]
    assert r.frames_with_board == len(POSES) and len(r.per_view) == len(POSES) - 2


@pytest.mark.parametrize(
    "make",
    [
        pytest.param(lambda n: np.zeros((n, H, W), np.uint16), id="black"),
        pytest.param(lambda n: np.full((n, H, W), 1023, np.uint16), id="saturated"),
        pytest.param(
            lambda n: np.random.default_rng(0).integers(0, 1024, (n, H, W)).astype(np.uint16),
            id="noise",
        ),
    ],
)
def test_frames_without_a_board_raise_a_clear_error(make):
    frames = make(4)
    with pytest.raises(CalibrationError) as e:
        calibrate_intrinsics(frames, np.arange(4, dtype=np.int64), "RGBG", DEFAULT_BOARD)
    message = str(e.value)
    assert "found in 0 of 4 frames" in message and "--board" in message
    assert "\n" not in message
    assert isinstance(e.value, ValueError)


def test_too_few_views_say_how_many_were_seen(views):
    frames, t = views
    few = np.concatenate([frames[:3], np.zeros_like(frames[:2])])
    with pytest.raises(CalibrationError, match=r"found in 3 of 5 frames.*3 views are usable"):
        calibrate_intrinsics(few, np.arange(5, dtype=np.int64), "RGBG", DEFAULT_BOARD)


def test_bad_arguments():
    frames = np.zeros((2, H, W), np.uint16)
    t = np.arange(2, dtype=np.int64)
    with pytest.raises(InputError, match="distortion model"):
        calibrate_intrinsics(frames, t, "RGBG", DEFAULT_BOARD, distortion_model="fisheye")
    with pytest.raises(InputError, match="N times"):
        calibrate_intrinsics(frames, t[:1], "RGBG", DEFAULT_BOARD)
    with pytest.raises(InputError, match="0..1023"):
        calibrate_intrinsics(frames + 2000, t, "RGBG", DEFAULT_BOARD)
    with pytest.raises(InputError, match="color filter"):
        frame_to_gray(frames[0], "RGGB")
    with pytest.raises(InputError, match="uint8"):
        detect_board(frames[0], DEFAULT_BOARD)


def test_gray_image_of_a_mosaic_is_flat():
    """A uniform surface through the Bayer filter comes out one gray level; black stays black."""
    yy, xx = np.mgrid[0:H, 0:W]
    gain = np.vectorize(GAINS.get)(pixel_channels(xx, yy, "GBGR"))
    mosaic = np.round(700 * gain).astype(np.uint16)
    gray = frame_to_gray(mosaic, "GBGR")
    assert gray.dtype == np.uint8 and gray.shape == (H, W)
    assert gray.min() == gray.max() == 255
    assert not frame_to_gray(np.zeros((H, W), np.uint16), "GBGR").any()


def test_detect_board_finds_every_corner_where_it_is(views):
    frames, _ = views
    corners, ids = detect_board(frame_to_gray(frames[0], "RGBG"), DEFAULT_BOARD)
    assert corners.dtype == np.float64 and corners.shape == (DEFAULT_BOARD.corners, 2)
    assert sorted(ids) == list(range(DEFAULT_BOARD.corners))
    # the truth: the board's corners through the first pose, K and the distortion
    b = DEFAULT_BOARD
    obj = b.cv().getChessboardCorners()[ids]
    centre, angles = POSES[0]
    R = rotation(angles)
    t = np.asarray(centre) - R @ [b.cols * b.square_m / 2, b.rows * b.square_m / 2, 0]
    expected, _ = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t, K_TRUE, DIST_TRUE)
    error = np.linalg.norm(corners - expected.reshape(-1, 2), axis=1)
    assert np.median(error) < 0.15 and error.max() < 0.5
    empty_corners, empty_ids = detect_board(np.full((H, W), 128, np.uint8), DEFAULT_BOARD)
    assert empty_corners.shape == (0, 2) and empty_ids.shape == (0,)
