"""The Event-Camera Dataset's text layout (evcap.importers.event_text): exact round trips of
every file, the sensor's size, bad lines; and a simulated recording made an ECD sequence, then
imported, described and posed by the command line."""

import json
import subprocess
import sys

import cv2
import h5py
import numpy as np
import pytest
from text_ecd import export_session, write_calib, write_events, write_groundtruth, write_rows

from evcap.errors import InputError, OutputExistsError
from evcap.importers import event_text
from evcap.importers.event_text import import_event_text
from evcap.records import Calibration, Poses
from evcap.rotations import exp_so3
from evcap.session import Session

START_US = 1468940145_246984  # a Unix time: 2016-07-19


def random_events(rng, n: int, width: int = 240, height: int = 180, start: int = START_US):
    t = start + np.sort(rng.integers(0, 2_000_000, n))
    t[0] = start
    return t, rng.integers(0, width, n), rng.integers(0, height, n), rng.integers(0, 2, n)


@pytest.fixture
def sequence(tmp_path):
    """An ECD sequence of every file: events, 3 images (the first before the first event),
    IMU samples, calibration and ground truth; and what was written."""
    rng = np.random.default_rng(7)
    folder = tmp_path / "seq"
    (folder / "images").mkdir(parents=True)
    t, x, y, p = random_events(rng, 5000)
    write_events(folder / "events.txt", t, x, y, p)

    frame_t = START_US + np.array([-20_000, 100_000, 600_000])
    images = rng.integers(0, 256, (3, 180, 240), dtype=np.uint8)
    lines = []
    for i, (ft, image) in enumerate(zip(frame_t, images, strict=True)):
        name = f"images/frame_{i:08d}.png"
        cv2.imwrite(str(folder / name), image)
        lines.append(f"{ft // 1_000_000}.{ft % 1_000_000:06d} {name}\n")
    (folder / "images.txt").write_text("".join(lines))

    imu_t = START_US + np.arange(-3000, 1_000_000, 1000)
    imu = rng.normal(0, 1, (len(imu_t), 6)).astype(np.float32)  # float32: exact in the session
    write_rows(folder / "imu.txt", imu_t, imu)

    K = np.array([[199.092366542, 0, 132.192071378], [0, 198.82882047, 110.712660011], [0, 0, 1]])
    dist = np.array([-0.368436311798, 0.150947243557, -0.000296130534385, -0.000759431726241, 0])
    write_calib(folder / "calib.txt", K, dist)

    pose_t = START_US + np.arange(-5000, 1_500_000, 5000)
    T = np.tile(np.eye(4), (len(pose_t), 1, 1))
    T[:, :3, :3] = exp_so3(rng.normal(0, 1, (len(pose_t), 3)))
    T[:, :3, 3] = rng.normal(0, 1, (len(pose_t), 3))
    write_groundtruth(folder / "groundtruth.txt", pose_t, T)
    truth = {
        "events": (t, x, y, p),
        "frames": (frame_t, images),
        "imu": (imu_t, imu),
        "calib": (K, dist),
        "poses": (pose_t, T),
    }
    return folder, truth


def test_every_file_round_trips_exactly(sequence, tmp_path):
    folder, truth = sequence
    out = tmp_path / "s.h5"
    summary = import_event_text(folder, out)
    assert (summary.events, summary.frames, summary.imu) == (5000, 2, 1000)
    inferred = "DAVIS240C (inferred from the coordinates)"
    assert summary.source == f"ECD text (Event-Camera Dataset), {inferred}"
    with Session.open(out) as s:
        assert s.sensor.sensor == inferred
        assert (s.sensor.width, s.sensor.height, s.sensor.color_filter) == (240, 180, "MONO")
        assert s.sensor.t_offset_us == START_US  # Unix times: the absolute start is kept
        t, x, y, p = truth["events"]
        ev = s.events()
        np.testing.assert_array_equal(ev.t, t - START_US)
        np.testing.assert_array_equal(ev.x, x)
        np.testing.assert_array_equal(ev.y, y)
        np.testing.assert_array_equal(ev.p, p)

        frame_t, images = truth["frames"]
        frames = s.frames()
        np.testing.assert_array_equal(frames.t, frame_t[1:] - START_US)  # the first: before
        np.testing.assert_array_equal(frames.data, images[1:].astype(np.uint16) << 2)
        np.testing.assert_array_equal(frames.exposure_us, 0)
        assert "exposure is unknown" in s.attrs["source_frames"]

        imu_t, imu = truth["imu"]
        samples = s.imu()
        np.testing.assert_array_equal(samples.t, imu_t[3:] - START_US)
        np.testing.assert_array_equal(samples.accel, imu[3:, :3])
        np.testing.assert_array_equal(samples.gyro, imu[3:, 3:])
        assert np.isnan(samples.temperature).all()

        K, dist = truth["calib"]
        cal = Calibration.read(s)
        assert cal.source == "calib.txt (ECD)" and cal.distortion_model == "radtan"
        np.testing.assert_array_equal(cal.K, K)
        np.testing.assert_array_equal(cal.dist, dist)

        pose_t, T = truth["poses"]
        poses = Poses.read(s)
        assert poses.source == "groundtruth.txt (ECD)" and poses.scale == "metres"
        np.testing.assert_array_equal(poses.t, pose_t[1:] - START_US)
        np.testing.assert_array_equal(poses.T_world_cam[:, :3, 3], T[1:, :3, 3])
        np.testing.assert_allclose(poses.T_world_cam, T[1:], atol=1e-12)

        left_out = {"images.txt": 1, "imu.txt": 3, "groundtruth.txt": 1}  # lines before t = 0
        assert json.loads(s.attrs["source_left_out"]) == left_out
        assert json.loads(s.attrs["source_files"]) == [
            "events.txt",
            "images.txt",
            "imu.txt",
            "calib.txt",
            "groundtruth.txt",
        ]


def test_events_alone_relative_times_and_the_file_named(tmp_path):
    """ECD's own times start near 0 and have 9 decimals: not Unix times, t_offset_us 0."""
    folder = tmp_path / "seq"
    folder.mkdir()
    (folder / "events.txt").write_text(
        "0.003811000 33 39 1\n0.003820000 158 145 0\n0.0038205 158 145 1\n7 0 0 0"  # no \n
    )
    out = tmp_path / "s.h5"
    assert import_event_text(folder / "events.txt", out).events == 4
    with Session.open(out) as s:
        assert s.sensor.t_offset_us == 0
        # t = 0 at the first event; 0.0038205 rounds to the nearest microsecond
        np.testing.assert_array_equal(s.events().t, [0, 9, 10, 7_000_000 - 3811])
        assert s.groups == ["events", "frames", "imu", "settings_log", "triggers"]


@pytest.mark.parametrize(
    ("text", "us"),
    [
        ("1468940145.246984", 1468940145246984),
        ("0.000000000", 0),
        ("12", 12_000_000),
        ("3.5", 3_500_000),
        ("0.0000005", 1),
        ("0.0000004999", 0),
        ("99999999999.999999", 99999999999999999),
    ],
)
def test_times_are_read_from_their_digits(text, us):
    assert event_text._micros(text) == us
    buf = np.frombuffer(f"{text} 1 2 1\n".encode(), np.uint8)
    t, x, y, p = (np.zeros(2, d) for d in (np.int64, np.uint16, np.uint16, np.uint8))
    assert event_text._parse_lines(buf, 10, 10, 0, t, x, y, p)[:3] == (1, 1, 0)
    assert t[0] == us


@pytest.mark.parametrize(
    ("x_max", "y_max", "sensor", "size"),
    [
        (127, 127, "DVS128", (128, 128)),
        (128, 20, "DAVIS240C", (240, 180)),
        (239, 179, "DAVIS240C", (240, 180)),
        (300, 10, "DAVIS346", (346, 260)),
    ],
)
def test_the_size_is_the_smallest_known_sensor_holding_the_events(
    tmp_path, x_max, y_max, sensor, size
):
    (tmp_path / "events.txt").write_text(f"1.0 {x_max} 0 1\n1.1 0 {y_max} 0\n")
    import_event_text(tmp_path, tmp_path / "s.h5")
    with Session.open(tmp_path / "s.h5") as s:
        assert s.sensor.sensor == f"{sensor} (inferred from the coordinates)"
        assert (s.sensor.width, s.sensor.height) == size


def test_a_given_size_and_color_filter_are_used(tmp_path):
    for name, line in (("a", "1.0 639 479 1\n"), ("b", "1.0 3 4 1\n")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "events.txt").write_text(line)
    a, b = tmp_path / "a", tmp_path / "b"
    import_event_text(a, tmp_path / "a.h5", width=640, height=480, color_filter="RGBG")
    import_event_text(b, tmp_path / "b.h5", width=346, height=260)
    with Session.open(tmp_path / "a.h5") as sa, Session.open(tmp_path / "b.h5") as sb:
        assert (sa.sensor.sensor, sa.sensor.width, sa.sensor.height) == ("unknown", 640, 480)
        assert sa.sensor.color_filter == "RGBG"
        assert (sb.sensor.sensor, sb.sensor.width, sb.sensor.height) == ("DAVIS346", 346, 260)
    with pytest.raises(InputError, match=r"line 1: expected x inside the sensor \(x < 320\)"):
        import_event_text(a, tmp_path / "c.h5", width=320, height=480)
    with pytest.raises(InputError, match="outside every known sensor"):
        import_event_text(a, tmp_path / "d.h5")
    with pytest.raises(InputError, match="both the width and the height"):
        import_event_text(a, tmp_path / "e.h5", width=640)
    with pytest.raises(OutputExistsError):
        import_event_text(a, tmp_path / "a.h5")


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ("1.000300 3 4", "the polarity, 0 or 1"),
        ("1.000300 3 4 2", "the polarity, 0 or 1"),
        ("1.000300 3 4 -1", "the polarity, 0 or 1"),
        ("1,000300 3 4 1", "a time in seconds"),
        ("1.5e-3 3 4 1", "a time in seconds"),
        ("t x y p", "a time in seconds"),
        ("1.000300 3.5 4 1", "x, a column"),
        ("1.000300 3 -4 1", "y, a row"),
        ("1.000300 3 4 1 0", "the end of the line"),
        ("1.000300", "x, a column"),
        ("1.000300 3 4 1x", "the polarity, 0 or 1"),
        ("1.000100 3 4 1", "times in order"),
        ("1.000300 3 400000 1", "y, a row"),
    ],
)
def test_a_bad_line_is_named(tmp_path, line, expected):
    good = ["1.000100 1 2 1", "1.000200 1 2 0", "", "1.000200 5 6 1"]
    events = tmp_path / "events.txt"
    events.write_text("\n".join([*good, line, "1.000400 1 1 1"]) + "\n")
    with pytest.raises(InputError) as e:
        import_event_text(tmp_path, tmp_path / "s.h5")
    message = str(e.value)
    assert "\n" not in message
    assert message.startswith(f"{events}: line 5: expected {expected}")
    assert repr(line) in message
    assert not (tmp_path / "s.h5").exists() and not (tmp_path / "s.h5.partial").exists()


def test_bad_lines_of_the_other_files_are_named(sequence, tmp_path):
    folder, _ = sequence
    imu = folder / "imu.txt"
    lines = imu.read_text().splitlines()
    lines[9] = lines[9].rsplit(" ", 1)[0]
    imu.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=rf"^{imu}: line 10: expected 7 fields 't ax ay"):
        import_event_text(folder, tmp_path / "s.h5")
    lines[9] = "1468940145.3 a b c d e f"
    imu.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=rf"^{imu}: line 10: expected numbers"):
        import_event_text(folder, tmp_path / "s.h5")
    imu.unlink()
    (folder / "calib.txt").write_text("199.0 198.8 132.1 110.7\n")
    with pytest.raises(InputError, match="calib.txt: expected one line of 9 numbers"):
        import_event_text(folder, tmp_path / "s.h5")
    (folder / "calib.txt").unlink()
    (folder / "images.txt").write_text("1468940145.4 images/missing.png\n")
    with pytest.raises(InputError, match=r"images.txt: line 1: .*missing.png does not exist"):
        import_event_text(folder, tmp_path / "s.h5")
    assert not (tmp_path / "s.h5").exists()


def test_lines_across_blocks(tmp_path, monkeypatch):
    """Blocks end inside lines, and lines are longer than blocks: every event is read once,
    and a bad line is named by its number in the file."""
    rng = np.random.default_rng(1)
    t, x, y, p = random_events(rng, 300)
    write_events(tmp_path / "events.txt", t, x, y, p)
    size = (tmp_path / "events.txt").stat().st_size
    for block in (7, 64, 1000):
        monkeypatch.setattr(event_text, "BLOCK_BYTES", block)
        out = tmp_path / f"s{block}.h5"
        calls: list[tuple[int, int]] = []
        import_event_text(tmp_path, out, progress=lambda *call, seen=calls: seen.append(call))
        done = [d for d, _ in calls]
        assert done == sorted(done) and calls[-1] == (2 * size, 2 * size)
        with Session.open(out) as s:
            np.testing.assert_array_equal(s.events().t, t - t[0])
            np.testing.assert_array_equal(s.events().x, x)
    lines = (tmp_path / "events.txt").read_text().splitlines()
    lines[236] = lines[236] + " 1"
    (tmp_path / "events.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="line 237: expected the end of the line"):
        import_event_text(tmp_path, tmp_path / "bad.h5")


def test_a_simulated_recording_as_an_ecd_sequence(tmp_path):
    """The issue's must-show: the demo's simulated recording (a Color-DAVIS346 orbiting a
    checkered sphere, replayed through the driver) exported as events.txt, calib.txt and
    groundtruth.txt (no frames), imported, then `evcap info` and `evcap poses` on it."""
    from evcap.acquire.device import Davis346
    from evcap.acquire.recorder import Recorder, RecordOptions
    from evcap.app.demo import FIXTURES, SCENE
    from evcap.records import GroundTruth

    recorded = tmp_path / "recorded.h5"
    with Davis346.open(f"replay:{FIXTURES / SCENE}") as camera:
        Recorder(camera, recorded, RecordOptions()).run()
    with h5py.File(FIXTURES / SCENE / "truth.h5") as f:
        truth, track = GroundTruth.read(f), Poses.read(f)
    Calibration(
        346, 260, "ground truth", K=truth.K, distortion_model="radtan", dist=truth.distortion
    ).write(recorded)
    track.write(recorded)
    export_session(recorded, tmp_path / "ecd")

    session = tmp_path / "imported.h5"
    # the text cannot tell the camera's color filter: the option does
    summary = import_event_text(tmp_path / "ecd", session, color_filter="RGBG")
    with Session.open(recorded) as r, Session.open(session) as s:
        assert summary.events == r.n_events == s.n_events
        assert s.sensor.sensor == "Color-DAVIS346 (inferred from the coordinates)"
        assert s.sensor.t_offset_us == r.sensor.t_offset_us + int(r.events(0, 1).t[0])
        np.testing.assert_array_equal(Poses.read(s).t, track.t)
        np.testing.assert_allclose(Poses.read(s).T_world_cam, track.T_world_cam, atol=1e-9)

    def evcap(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "evcap", *args], capture_output=True, text=True, timeout=300
        )

    info = evcap("info", str(session))
    assert info.returncode == 0, info.stderr
    assert "Color-DAVIS346 (inferred from the coordinates)" in info.stdout
    assert "384,359" in info.stdout
    poses = evcap("poses", str(session))
    assert poses.returncode == 0, poses.stderr
    assert "frames registered" in poses.stdout
    with Session.open(session) as s:
        estimate = Poses.read(s)
    assert estimate.source.startswith("evcap poses")
    assert estimate.notes["registered"] == len(estimate.t) >= 0.4 * estimate.notes["frames"]


def test_no_events_and_no_text_are_refused(tmp_path, monkeypatch):
    (tmp_path / "events.txt").write_text("\n  \n")
    with pytest.raises(InputError, match="holds no events"):
        import_event_text(tmp_path, tmp_path / "s.h5")
    with pytest.raises(FileNotFoundError, match="no such file"):
        import_event_text(tmp_path / "missing", tmp_path / "s.h5")
    monkeypatch.setattr(event_text, "BLOCK_BYTES", 8)
    monkeypatch.setattr(event_text, "MAX_LINE_BYTES", 64)
    (tmp_path / "events.txt").write_bytes(b"1.0 1 1 1\n" + bytes(range(11, 255)))
    with pytest.raises(InputError, match="line 2 is longer than 64 bytes"):
        import_event_text(tmp_path, tmp_path / "s.h5")
