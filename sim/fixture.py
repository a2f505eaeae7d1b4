"""A simulated session as a hardware-replay fixture: its events, frames and IMU samples
encoded into the DAVIS346's USB stream (evcap.acquire.encoder), so that it can be recorded
through the real driver (`evcap record --device replay:DIR`)."""

from __future__ import annotations

from pathlib import Path

from evcap.acquire.decoder import Geometry
from evcap.acquire.encoder import StreamEncoder
from evcap.acquire.fixture import FixtureContent, write_fixture
from evcap.session import Session

COLOR_FILTER_CODES = {"MONO": 0, "RGBG": 1, "GRGB": 2, "GBGR": 3, "BGRG": 4}


def write_session_fixture(session_path: str | Path, folder: str | Path) -> None:
    """Encode the session's streams into the fixture folder (its expected content beside)."""
    with Session.open(session_path) as s:
        sensor = s.sensor
        events, frames, imu = s.events(), s.frames(), s.imu()
    geometry = Geometry(
        dvs_columns=sensor.width,
        dvs_rows=sensor.height,
        aps_columns=sensor.width,
        aps_rows=sensor.height,
        color_filter=sensor.color_filter,
    )
    encoder = StreamEncoder(geometry)
    raw = encoder.imu_raw(imu)
    bulk = encoder.encode(events, frames, imu_raw=(imu.t, raw))
    content = FixtureContent(sensor.width, sensor.height)
    content.add(events, frames, (imu.t, raw))
    registers = {
        "1.0": sensor.width,
        "1.1": sensor.height,
        "2.0": sensor.width,
        "2.1": sensor.height,
    }
    write_fixture(
        Path(folder),
        serial=sensor.serial[:8],
        bulk=bulk,
        content=content,
        color_filter=COLOR_FILTER_CODES[sensor.color_filter],
        registers=registers,
        description=f"simulated: {Path(session_path).name}",
    )
