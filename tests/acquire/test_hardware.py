"""The real camera path. Runs only with ``-m hardware`` and a DAVIS346 on USB; skipped otherwise.

.venv/bin/python -m pytest -m hardware tests/acquire/test_hardware.py
"""

import numpy as np
import pytest

from evcap.acquire.device import Davis346, DeviceSpec, find
from evcap.acquire.recorder import Recorder, RecordOptions
from evcap.errors import DeviceError
from evcap.session import Session

pytestmark = pytest.mark.hardware


@pytest.fixture(scope="module")
def camera():
    try:
        devices = find(DeviceSpec("usb"))
    except DeviceError as e:
        pytest.skip(f"no USB access: {e}")
    if not devices:
        pytest.skip("no DAVIS346 enumerates on USB")
    with Davis346.open("usb") as cam:
        yield cam


def test_device_information(camera):
    info = camera.info
    assert info.firmware >= 6 and info.logic == 18
    assert (info.geometry.width, info.geometry.height) == (346, 260)
    assert info.color_filter in ("MONO", "RGBG")
    assert info.clocks.adc > 0 and info.clocks.logic > 0


def test_short_recording(camera, tmp_path):
    out = tmp_path / "s.h5"
    result = Recorder(camera, out, RecordOptions(duration_s=2.0)).run()
    assert result.end_reason == "duration"
    with Session.open(out) as s:
        assert s.n_events > 0 and s.n_imu > 1000  # 1 kHz IMU
        assert s.n_frames >= 25  # 25 fps by default
        assert np.isfinite(s.imu().accel).all()
        g = np.linalg.norm(s.imu().accel, axis=1).mean()
        assert 8.5 < g < 11.0  # gravity, camera at rest or moved by hand
    assert sum(result.device_dropped.values()) == 0
    assert result.decoder["unknown_words"] == 0
