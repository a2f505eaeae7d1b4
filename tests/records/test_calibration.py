"""/calibration: one reader and writer, and a damaged group refused the same way by every step."""

import re
import subprocess
import sys

import numpy as np
import pytest

from evcap.errors import InputError
from evcap.events import Events
from evcap.records import Calibration, read_intrinsics
from evcap.records.calibration import BoardViews
from evcap.session import SensorInfo, Session, SessionWriter, write_group

W, H = 40, 30
SENSOR = SensorInfo("simulated", W, H, "RGBG", "SIM0001", 1_700_000_000_000_000)


@pytest.fixture
def session(tmp_path):
    path = tmp_path / "s.h5"
    rng = np.random.default_rng(0)
    n = 5000
    t = np.cumsum(rng.integers(0, 50, n))
    with SessionWriter(path, SENSOR) as w:
        w.append_events(
            Events(
                rng.integers(0, W, n), rng.integers(0, H, n), t, rng.integers(0, 2, n), W, H, "RGBG"
            )
        )
    return path


def full_calibration() -> Calibration:
    rng = np.random.default_rng(1)
    return Calibration(
        width=W,
        height=H,
        source="evcap calibrate",
        K=np.array([[50.0, 0, 19.5], [0, 50.0, 14.5], [0, 0, 1]]),
        distortion_model="radtan",
        dist=np.array([-0.3, 0.1, 0.001, 0.0]),
        threshold_on=rng.uniform(0.1, 0.3, (H, W)),
        threshold_off=rng.uniform(0.1, 0.3, (H, W)),
        threshold_confidence=rng.uniform(0, 1, (H, W)),
        hot_pixels=rng.uniform(size=(H, W)) < 0.01,
        event_rate_hz=rng.uniform(0, 5, (H, W)),
        views=BoardViews(np.array([10, 20]), np.array([0.2, 0.3]), np.array([24, 30])),
        rms_reprojection_px=0.25,
        refractory_period_us=100.0,
        background_activity_hz=0.1,
        shot_noise_hz=0.01,
        notes={"intrinsics_source": "APS frames"},
    )


def test_round_trip(session):
    cal = full_calibration()
    cal.write(session)
    with Session.open(session) as s:
        back = Calibration.read(s)
        K, model, dist = read_intrinsics(s)
    assert model == "radtan" and np.array_equal(K, cal.K) and np.array_equal(dist, cal.dist)
    for name in ("threshold_on", "threshold_off", "threshold_confidence", "event_rate_hz"):
        assert np.array_equal(getattr(back, name), getattr(cal, name).astype(np.float32))
    assert np.array_equal(back.hot_pixels, cal.hot_pixels)
    assert np.array_equal(back.views.corners, cal.views.corners)
    assert back.rms_reprojection_px == 0.25 and back.refractory_period_us == 100.0
    assert back.source == "evcap calibrate"
    assert back.notes["intrinsics_source"] == "APS frames"
    assert back.notes["hot_pixel_count"] == int(cal.hot_pixels.sum())


def test_thresholds_only(session):
    Calibration(W, H, "evcap calibrate", threshold_on=np.full((H, W), 0.2)).write(session)
    with Session.open(session) as s:
        cal = Calibration.read(s)
        with pytest.raises(InputError, match="no intrinsics"):
            cal.intrinsics()
        with pytest.raises(InputError, match="no per-pixel thresholds"):
            cal.thresholds()
    assert not cal.hot().any() and cal.hot().shape == (H, W)


def test_older_names_are_read(session):
    # sessions written before the names `dist` and `rms_reprojection_px`
    write_group(
        session,
        "calibration",
        {"K": np.eye(3) * 40 + np.diag([0, 0, -39]), "distortion": np.array([0.1, 0, 0, 0])},
        {"distortion_model": "radtan", "reprojection_error_px": 0.5},
    )
    with Session.open(session) as s:
        cal = Calibration.read(s)
    assert cal.dist[0] == 0.1 and cal.rms_reprojection_px == 0.5


@pytest.mark.parametrize(
    "datasets, attrs, message",
    [
        ({"threshold_on": np.full((H, W - 1), 0.2)}, {}, r"threshold_on should be 30 x 40"),
        ({"threshold_off": np.full((H, W), -0.2)}, {}, "must be positive"),
        ({"hot_pixels": np.zeros((2, 2))}, {}, "hot_pixels should be"),
        ({}, {"width": W + 1}, "the calibration is for 41 x 30, the sensor is 40 x 30"),
    ],
)
def test_bad_maps_are_refused(session, datasets, attrs, message):
    write_group(session, "calibration", datasets, attrs)
    with Session.open(session) as s, pytest.raises(InputError, match=message):
        Calibration.read(s)


def test_a_map_of_another_size_is_not_written():
    with pytest.raises(InputError, match="threshold_on is 39 x 30 pixels, the sensor 40 x 30"):
        Calibration(W, H, "x", threshold_on=np.ones((H, W - 1)))


@pytest.mark.parametrize(
    "datasets, attrs, message",
    [
        ({}, {}, "no intrinsics"),
        ({"K": np.eye(2)}, {}, r"not an intrinsic matrix .* shape \[2, 2\]"),
        ({"K": np.array([b"a", b"b", b"c"])}, {}, "not numbers"),
        ({"K": np.diag([300.0, np.nan, 1])}, {}, "NaN or infinite"),
        ({"K": np.eye(3), "dist": np.ones((2, 2))}, {}, "not a list of coefficients"),
        ({"K": np.eye(3)}, {"distortion_model": "fisheye9"}, "unknown distortion model"),
    ],
)
def test_bad_intrinsics_are_refused_by_every_step(session, datasets, attrs, message):
    # read by poses, the reconstruction and the simulator alike; `evcap poses` used to fail
    # with a traceback on a /calibration of the wrong type or shape
    write_group(session, "calibration", {"note": np.zeros(1), **datasets}, attrs)
    with Session.open(session) as s, pytest.raises(InputError, match=message):
        read_intrinsics(s)
    r = subprocess.run(
        [sys.executable, "-m", "evcap", "poses", str(session)], capture_output=True, text=True
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr and re.search(message, r.stderr)
