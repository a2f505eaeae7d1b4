"""A simulated session as a hardware-replay fixture: its events, frames and IMU samples
encoded into the DAVIS346's USB stream (evcap.acquire.encoder), so that it can be recorded
through the real driver (`evcap record --device replay:DIR`).

A fixture's expected content (what a correct driver records from it) is written beside it
(hw-fixtures/README.md). A *compact* fixture, for a long simulated recording, keeps the events
and the frames' pixels as SHA-256 digests in expected.json (``digests``) instead of arrays in
expected.npz, which then holds the small streams only (IMU, frame times, triggers): the
fixture's size is then about its bulk.bin. ``check_fixture`` records a fixture through the
driver and compares what comes out with that expected content, either form.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
from pathlib import Path

import numpy as np

from evcap.acquire.decoder import Geometry
from evcap.acquire.encoder import StreamEncoder
from evcap.acquire.fixture import FixtureContent, write_fixture
from evcap.errors import InputError
from evcap.session import Session

COLOR_FILTER_CODES = {"MONO": 0, "RGBG": 1, "GRGB": 2, "GBGR": 3, "BGRG": 4}
DIGESTED = ("events_x", "events_y", "events_t", "events_p", "frames_data")
SIMULATED_IMU_FLIP = (True, False, True)  # the IMU orientation register's x, y, z flips
"""The arrays a compact fixture keeps as digests (the large ones)."""


def array_digest(a: np.ndarray) -> str:
    """SHA-256 of an array's dtype (little-endian), shape and values (C order)."""
    a = np.ascontiguousarray(a)
    a = a.astype(a.dtype.newbyteorder("<"), copy=False)
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
    return h.hexdigest()


def write_session_fixture(
    session_path: str | Path,
    folder: str | Path,
    *,
    serial: str | None = None,
    description: str | None = None,
    compact: bool = False,
    about: dict | None = None,
) -> dict:
    """Encode the session's streams into the fixture folder (its expected content beside);
    returns expected.json's content. ``serial``: the USB serial (at most 8 characters; default
    the first 8 of the session's); ``description``: device.toml's comment and expected.json's
    (default "simulated: NAME"); ``compact``: digests for the events and frames (see the
    module); ``about``: more entries for expected.json (e.g. what the fixture was made
    from)."""
    folder = Path(folder)
    with Session.open(session_path) as s:
        sensor = s.sensor
        events, frames, imu = s.events(), s.frames(), s.imu()
    serial = sensor.serial[:8] if serial is None else serial
    if not 0 < len(serial) <= 8:
        raise InputError(f"a fixture's serial has 1 to 8 characters, not {serial!r}")
    # The simulated camera's IMU orientation register flips x and z: its registers then hold
    # the simulator's camera-axis values as they are (libcaer's axes have x and z the other
    # way, evcap.streams.LIBCAER_TO_CAMERA), as the fixtures made before that was known do.
    geometry = Geometry(
        dvs_columns=sensor.width,
        dvs_rows=sensor.height,
        aps_columns=sensor.width,
        aps_rows=sensor.height,
        imu_flip=SIMULATED_IMU_FLIP,
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
        "3.1": 4 * SIMULATED_IMU_FLIP[0] + 2 * SIMULATED_IMU_FLIP[1] + SIMULATED_IMU_FLIP[2],
    }
    write_fixture(
        folder,
        serial=serial,
        bulk=bulk,
        content=content,
        color_filter=COLOR_FILTER_CODES[sensor.color_filter],
        registers=registers,
        description=description or f"simulated: {Path(session_path).name}",
    )
    summary = json.loads((folder / "expected.json").read_text())
    summary.update(about or {})
    if compact:
        arrays = content.arrays(imu_flip=SIMULATED_IMU_FLIP)
        summary["digests"] = {k: array_digest(arrays[k]) for k in DIGESTED}
        with open(folder / "expected.npz", "wb") as f:
            np.savez_compressed(f, **{k: v for k, v in arrays.items() if k not in DIGESTED})
    (folder / "expected.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def recorded_arrays(session_path: str | Path) -> dict[str, np.ndarray]:
    """A session's streams under the names of expected.npz (triggers sorted by time, then
    kind: the driver does not keep the order of triggers at equal times)."""
    with Session.open(session_path) as s:
        ev, fr, imu, tr = s.events(), s.frames(), s.imu(), s.triggers()
    order = np.lexsort((tr.kind, tr.t))
    return {
        "events_x": ev.x.astype(np.uint16),
        "events_y": ev.y.astype(np.uint16),
        "events_t": ev.t.astype(np.int64),
        "events_p": ev.p.astype(np.uint8),
        "frames_data": fr.data.astype(np.uint16),
        "frames_t": fr.t.astype(np.int64),
        "frames_exposure_us": fr.exposure_us.astype(np.int64),
        "imu_t": imu.t.astype(np.int64),
        "imu_accel": imu.accel,
        "imu_gyro": imu.gyro,
        "imu_temperature": imu.temperature,
        "triggers_t": tr.t[order].astype(np.int64),
        "triggers_kind": tr.kind[order].astype(np.uint8),
    }


def check_fixture(folder: str | Path) -> list[str]:
    """Record the fixture through the real driver (the replay backend) and compare with its
    expected content (expected.json, expected.npz, digests): what differs, one line each
    (nothing: all matches)."""
    from evcap.acquire.device import Davis346
    from evcap.acquire.recorder import Recorder

    folder = Path(folder)
    summary = json.loads((folder / "expected.json").read_text())
    expected = dict(np.load(folder / "expected.npz"))
    problems = []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "recorded.h5"
        with Davis346.open(f"replay:{folder}") as cam:
            result = Recorder(cam, out).run()
        ended = getattr(result, "end_reason", None)
        if ended != "end of replay":
            return [f"{folder.name}: the recording ended with {ended!r}, not the end of replay"]
        with Session.open(out) as s:
            got_serial, got_filter = s.sensor.serial, s.sensor.color_filter
        got = recorded_arrays(out)
    if got_serial != summary["serial"]:
        problems.append(f"{folder.name}: serial {got_serial!r}, expected {summary['serial']!r}")
    if got_filter != summary["color_filter"]:
        want = summary["color_filter"]
        problems.append(f"{folder.name}: color filter {got_filter}, expected {want}")
    counts = {
        "events": got["events_t"].size,
        "frames": got["frames_t"].size,
        "imu_samples": got["imu_t"].size,
        "triggers": got["triggers_t"].size,
    }
    for name, n in counts.items():
        if n != summary[name]:
            problems.append(f"{folder.name}: {n} {name}, expected {summary[name]}")
    for name, digest in summary.get("digests", {}).items():
        if array_digest(got[name]) != digest:
            problems.append(f"{folder.name}: {name} differs from its digest")
    for name, want in expected.items():
        have = got[name]
        same = have.shape == want.shape and (
            np.allclose(have, want, rtol=1e-6)
            if want.dtype.kind == "f"
            else np.array_equal(have, want)
        )
        if not same:
            problems.append(f"{folder.name}: {name} differs from expected.npz")
    return problems
