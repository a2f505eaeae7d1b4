"""Recording the hardware-replay fixtures, and the recorder under faults."""

import ast
import inspect
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import usb.core

from evcap.acquire import protocol as P
from evcap.acquire import recorder as recorder_module
from evcap.acquire.device import Davis346, DeviceSpec
from evcap.acquire.recorder import END_REASONS, NORMAL_ENDS, Recorder, RecordOptions
from evcap.errors import DeviceError, DeviceLostError, DevicePermissionError, FirmwareError
from evcap.session import Session
from evcap.sim.fixture import recorded_arrays

FIXTURES = Path(__file__).resolve().parents[2] / "hw-fixtures"
NAMES = ["color-scene", "disconnect", "timeouts-stall", "corrupted", "davis346-sample"]


def assert_expected_content(session_path: Path, fixture: Path) -> None:
    exp = np.load(fixture / "expected.npz")
    summary = json.loads((fixture / "expected.json").read_text())
    with Session.open(session_path) as s:
        assert s.sensor.serial == summary["serial"]
        assert s.sensor.color_filter == summary["color_filter"]
        counters = json.loads(s.attrs["decoder_counters"]) if summary["counters"] else {}
    got = recorded_arrays(session_path)  # triggers sorted: at equal times the order is not kept
    assert set(exp) == set(got)
    for name, want in exp.items():
        if want.dtype.kind == "f":
            np.testing.assert_allclose(got[name], want, rtol=1e-6, err_msg=name)
        else:
            np.testing.assert_array_equal(got[name], want, err_msg=name)
    for name, value in summary["counters"].items():
        assert counters[name] == value, name


@pytest.mark.parametrize("name", NAMES)
def test_recording_each_fixture_gives_its_expected_content(tmp_path, name):
    if not (FIXTURES / name).exists():
        pytest.skip(f"{name} is made from ../shared, which is missing")
    out = tmp_path / "s.h5"
    with Davis346.open(f"replay:{FIXTURES / name}") as cam:
        recorder = Recorder(cam, out)
        if name == "disconnect":
            with pytest.raises(DeviceLostError, match="camera was lost"):
                recorder.run()
            assert recorder.result.end_reason == "camera lost"
        else:
            result = recorder.run()
            assert result.end_reason == "end of replay"
    assert_expected_content(out, FIXTURES / name)


def test_timeouts_and_stall_are_recovered(tmp_path):
    with Davis346.open(f"replay:{FIXTURES / 'timeouts-stall'}") as cam:
        result = Recorder(cam, tmp_path / "s.h5").run()
        assert cam.backend.clear_halt_calls >= 2  # at start, and after the stall
    assert result.reader["stalls"] == 1 and result.reader["timeouts"] >= 5


def test_session_metadata_and_configuration(tmp_path):
    biases = tmp_path / "b.toml"
    biases.write_text(
        "[biases]\nOnBn = { coarse = 6, fine = 200 }\n[settings]\naps_exposure_us = 8000\n"
    )
    from evcap.acquire.bias_file import load_bias_file

    codes, settings = load_bias_file(biases)
    with Davis346.open(f"replay:{FIXTURES / 'color-scene'}") as cam:
        Recorder(cam, tmp_path / "s.h5", RecordOptions(biases=codes, settings=settings)).run()
        writes = cam.backend.writes
        regs = cam.backend.registers
    on_code = P.coarse_fine_code(6, 200, n_type=True)
    assert (5, 11, on_code) in writes
    assert (2, 12, 8000 * 30) in writes  # exposure in ADC cycles
    # the start sequence ends with the run flags on; stop turns them off again
    assert writes.index((0, 3, 1)) < writes.index((9, 0, 1)) < writes.index((1, 3, 1))
    assert regs[P.DVS_RUN] == regs[P.USB_RUN] == regs[P.MUX_RUN] == 0
    with Session.open(tmp_path / "s.h5") as s:
        a = s.attrs
        assert s.complete and a["sensor"] == "Color-DAVIS346" and a["serial"] == "00000042"
        assert (a["firmware_version"], a["logic_version"], a["chip"]) == (6, 18, "DAVIS346B")
        assert json.loads(a["biases"])["OnBn"] == on_code
        assert json.loads(a["settings"])["aps_exposure_us"] == 8000
        assert json.loads(a["device_dropped_events"]) == {
            "mux_dvs_dropped": 0,
            "mux_extinput_dropped": 0,
            "dvs_dropped": 0,
        }
        assert a["host_dropped_events"] == 0 and a["end_reason"] == "end of replay"
        assert abs(a["t_offset_us"] / 1e6 - time.time()) < 60


def test_device_side_drop_counters_are_recorded(fixture_copy, tmp_path):
    path = fixture_copy("color-scene")
    with open(path / "device.toml", "a") as f:
        f.write('"0.83" = 1\n"0.84" = 5\n"1.85" = 0\n"1.86" = 42\n')
    with Davis346.open(f"replay:{path}") as cam:
        result = Recorder(cam, tmp_path / "s.h5").run()
    assert result.device_dropped == {
        "mux_dvs_dropped": (1 << 32) + 5,
        "mux_extinput_dropped": 0,
        "dvs_dropped": 42,
    }


def test_no_aps_no_imu(tmp_path):
    with Davis346.open(f"replay:{FIXTURES / 'color-scene'}") as cam:
        Recorder(cam, tmp_path / "s.h5", RecordOptions(aps=False, imu=False)).run()
        regs = cam.backend.registers
        assert (2, 4, 1) not in cam.backend.writes and (3, 2, 1) not in cam.backend.writes
    assert regs[P.APS_RUN] == 0


# -- the CLI, as a user runs it ------------------------------------------------------------------


def evcap(*args, **kw):
    return subprocess.run(
        [sys.executable, "-m", "evcap", *args], capture_output=True, text=True, **kw
    )


def test_cli_record_replay(tmp_path):
    out = tmp_path / "s.h5"
    r = evcap(
        "record", "--device", f"replay:{FIXTURES / 'color-scene'}", "-o", str(out), "--no-tui"
    )
    assert r.returncode == 0, r.stderr
    assert "60,000 events, 15 frames, 3,000 IMU samples" in r.stdout
    assert_expected_content(out, FIXTURES / "color-scene")
    r = evcap("record", "--device", f"replay:{FIXTURES / 'color-scene'}", "-o", str(out))
    assert r.returncode == 2 and "exists" in r.stderr  # never overwritten unasked


def test_cli_disconnect_keeps_everything_before_and_fails(tmp_path):
    out = tmp_path / "s.h5"
    r = evcap("record", "--device", f"replay:{FIXTURES / 'disconnect'}", "-o", str(out))
    assert r.returncode == 1
    assert "camera was lost" in r.stderr and "Traceback" not in r.stderr
    assert_expected_content(out, FIXTURES / "disconnect")


def test_a_flaky_cables_bytes_give_a_short_session_and_a_warning(tmp_path, fixture_copy):
    # random bytes for the stream: before wrap jumps were bounded, 658 kB made a month-long
    # millisecond index and the kernel killed the recorder; 4 kB made a MemoryError
    path = fixture_copy("corrupted")
    rng = np.random.default_rng(1)
    (path / "bulk.bin").write_bytes(rng.integers(0, 256, 658_000, np.uint8).tobytes())
    (path / "transfers.u32").unlink()
    out = tmp_path / "s.h5"
    r = evcap("record", "--device", f"replay:{path}", "-o", str(out), "--no-tui")
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    assert "malformed" in r.stderr and "USB cable" in r.stderr
    with Session.open(out) as s:
        assert s.time_range()[1] - s.time_range()[0] < 3600e6
        assert json.loads(s.attrs["decoder_counters"])["timestamp_jumps"] > 10_000


def idle_fixture(fixture_copy) -> Path:
    """color-scene, then a camera that stays quiet (timeouts) for minutes."""
    path = fixture_copy("color-scene")
    size = (path / "bulk.bin").stat().st_size
    (path / "faults.toml").write_text(
        f'[[fault]]\nat_byte = {size}\nkind = "timeout"\ncount = 100000\n'
    )
    return path


def wait_for_events(path: Path, n: int, timeout_s: float = 30) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if path.exists():
            try:
                with Session.open(path, validate=False) as s:
                    if s.n_events >= n:
                        return
            except Exception:
                pass
        time.sleep(0.2)
    raise AssertionError(f"{path} did not reach {n} events")


def start_recording(out: Path, fixture: Path, **popen) -> subprocess.Popen:
    command = ["record", "--device", f"replay:{fixture}", "-o", str(out)]
    return subprocess.Popen([sys.executable, "-m", "evcap", *command], **popen)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_closes_the_session_complete(tmp_path, fixture_copy, sig):
    out = tmp_path / "s.h5"
    proc = start_recording(
        out, idle_fixture(fixture_copy), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    wait_for_events(out, 60_000)
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 0, stderr
    assert "(stopped;" in stdout
    with Session.open(out) as s:
        assert s.complete and s.n_events == 60_000 and s.attrs["end_reason"] == "stopped"


def test_a_slow_signal_handler_does_not_hang_the_wait_for_data():
    """A signal handled while the loop waits for USB data, taking longer than the wait:
    the wait still ends (SimpleQueue.get(timeout=) waited forever there on Python 3.11)."""
    code = (
        "import signal, time\n"
        "from evcap.acquire.reader import BulkReader\n"
        "signal.signal(signal.SIGALRM, lambda signum, frame: time.sleep(0.05))\n"
        "signal.setitimer(signal.ITIMER_REAL, 0.002)\n"
        "assert BulkReader(None, 1).take(0.01) == []\n"
        "print('returned')\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    assert r.returncode == 0 and "returned" in r.stdout, r.stderr


def test_kill_9_leaves_a_readable_file_with_what_was_flushed(tmp_path, fixture_copy):
    out = tmp_path / "s.h5"
    proc = start_recording(
        out, idle_fixture(fixture_copy), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    wait_for_events(out, 60_000)
    time.sleep(1.0)  # more than one flush interval: everything received is on disk
    proc.kill()
    proc.wait()
    with Session.open(out) as s:
        assert not s.complete
        assert s.n_events == 60_000 and s.n_frames == 15 and s.n_imu == 3000
    assert_expected_content(out, FIXTURES / "color-scene")


def small_disk(limit: int):
    """A process whose files cannot grow beyond ``limit`` bytes, as on a full disk."""
    import resource

    def setup():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

    return setup


def test_a_failing_disk_gives_a_clear_error(tmp_path):
    out = tmp_path / "s.h5"
    code = "import sys; from evcap.app.cli import main; sys.exit(main(sys.argv[1:]))"
    r = subprocess.run(
        [
            sys.executable,
            "-c",
            code,
            "record",
            "--device",
            f"replay:{FIXTURES / 'color-scene'}",
            "-o",
            str(out),
        ],
        capture_output=True,
        text=True,
        preexec_fn=small_disk(120_000),
    )
    assert r.returncode == 1, r.stderr
    assert "failed (File too large)" in r.stderr and "Traceback" not in r.stderr
    with Session.open(out) as s:  # readable, with whatever was flushed before (maybe nothing)
        exp = np.load(FIXTURES / "color-scene" / "expected.npz")
        np.testing.assert_array_equal(s.events().t, exp["events_t"][: s.n_events])


WRITE_UNTIL_FULL = r"""
import sys
import numpy as np
from evcap.events import Events
from evcap.errors import SessionWriteError
from evcap.session import SensorInfo, SessionWriter
rng = np.random.default_rng(0)
w = SessionWriter(sys.argv[1], SensorInfo("simulated", 346, 260))
t = 0
try:
    for _ in range(100):
        n = 50_000
        ts = t + np.cumsum(rng.integers(0, 20, n))
        t = int(ts[-1])
        x, y, p = rng.integers(0, 346, n), rng.integers(0, 260, n), rng.integers(0, 2, n)
        w.append_events(Events(x, y, ts, p, 346, 260))
        w.flush()
        print(w.events_flushed, flush=True)
except SessionWriteError as e:
    w.abort()
    print("error:", e)
"""


def test_disk_full_keeps_everything_flushed_before(tmp_path):
    out = tmp_path / "s.h5"
    r = subprocess.run(
        [sys.executable, "-c", WRITE_UNTIL_FULL, str(out)],
        capture_output=True,
        text=True,
        preexec_fn=small_disk(1_000_000),
    )
    lines = r.stdout.splitlines()
    assert r.returncode == 0 and lines[-1].startswith("error: writing"), r.stderr
    flushed = int(lines[-2])
    assert flushed >= 100_000
    rng = np.random.default_rng(0)  # the events the script wrote, again
    t = np.cumsum(rng.integers(0, 20, 50_000))
    with Session.open(out) as s:
        assert not s.complete
        assert s.n_events >= flushed  # a chunk written after the last flush may be there too
        np.testing.assert_array_equal(s.events_by_index(0, 50_000).t, t)


def test_recording_stops_cleanly_when_the_disk_is_almost_full(tmp_path, fixture_copy, monkeypatch):
    from evcap.errors import DiskFullError
    from evcap.session import SessionWriter

    monkeypatch.setattr(SessionWriter, "free_bytes", lambda self: 10 << 20)
    with Davis346.open(f"replay:{idle_fixture(fixture_copy)}") as cam:
        recorder = Recorder(cam, tmp_path / "s.h5")
        with pytest.raises(DiskFullError, match="only 10 MB left on the disk"):
            recorder.run()
    with Session.open(tmp_path / "s.h5") as s:
        assert s.complete and s.attrs["end_reason"] == "disk full"


# -- cameras that cannot be used ----------------------------------------------------------------


def test_wrong_firmware_and_logic(fixture_copy):
    path = fixture_copy("color-scene")
    toml = (path / "device.toml").read_text()
    (path / "device.toml").write_text(toml.replace("bcdDevice = 0x0006", "bcdDevice = 0x0005"))
    with pytest.raises(FirmwareError, match="firmware is version 5; evcap needs 6"):
        Davis346.open(f"replay:{path}")
    (path / "device.toml").write_text(toml + '"6.0" = 17\n')
    with pytest.raises(FirmwareError, match="logic is version 17"):
        Davis346.open(f"replay:{path}")
    r = evcap("devices", "--device", f"replay:{path}")
    assert r.returncode == 1 and "logic is version 17" in r.stderr


@pytest.mark.parametrize(
    "register, size",
    [
        ('"2.0" = 60000', "60000 x 260 pixels for its APS"),
        ('"1.0" = 0', "0 x 260 pixels for its DVS"),
    ],
)
def test_a_sensor_size_no_davis_has_is_the_cameras_fault(fixture_copy, tmp_path, register, size):
    path = fixture_copy("color-scene")
    (path / "device.toml").write_text((path / "device.toml").read_text() + register + "\n")
    r = evcap("record", "--device", f"replay:{path}", "-o", str(tmp_path / "s.h5"), "--no-tui")
    assert r.returncode == 1 and size in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not (tmp_path / "s.h5").exists()


def test_no_permission_says_how_to_fix_it(monkeypatch):
    from evcap.acquire.replay import ReplayBackend

    class Locked(ReplayBackend):
        def open_device(self, dev):  # libusb_open fails so without the udev rule
            raise usb.core.USBError("Access denied (insufficient permissions)", -3, 13)

    monkeypatch.setattr(DeviceSpec, "backend", lambda self: Locked(self.path))
    with pytest.raises(DevicePermissionError, match="udev rule"):
        Davis346.open(f"replay:{FIXTURES / 'color-scene'}")


def test_no_camera(tmp_path):
    r = evcap("record", "--device", "usb", "-o", str(tmp_path / "s.h5"))
    assert r.returncode == 1 and "no DAVIS346 found" in r.stderr, r.stderr
    assert not (tmp_path / "s.h5").exists()
    r = evcap("devices")
    assert r.returncode == 1 and "udev" in r.stderr
    r = evcap("record", "--device", "usb:0123", "-o", str(tmp_path / "s.h5"))
    assert "with serial 0123" in r.stderr


def test_no_libusb_says_how_to_get_one(monkeypatch):
    import usb.backend.libusb1

    monkeypatch.setattr(usb.backend.libusb1, "get_backend", lambda *a, **k: None)
    monkeypatch.setitem(sys.modules, "libusb_package", None)
    with pytest.raises(DeviceError, match="pip install libusb-package"):
        Davis346.open("usb")


def test_devices_lists_and_prints_the_udev_rule():
    r = evcap("devices", "--device", f"replay:{FIXTURES / 'color-scene'}")
    assert r.returncode == 0
    assert "Color-DAVIS346  serial 00000042  firmware 6  logic 18.1" in r.stdout
    assert "color filter RGBG" in r.stdout
    r = evcap("devices", "--udev")
    assert 'ATTR{idVendor}=="152a"' in r.stdout


def test_bad_device_names(tmp_path):
    r = evcap("record", "--device", "camera", "-o", str(tmp_path / "s.h5"))
    assert r.returncode == 2 and "usb, usb:SERIAL or replay:PATH" in r.stderr
    r = evcap("record", "--device", f"replay:{tmp_path / 'nope'}", "-o", str(tmp_path / "s.h5"))
    assert r.returncode == 2 and "not a folder" in r.stderr


def test_record_does_not_import_torch(tmp_path):
    code = (
        "import sys\nfrom evcap.app.cli import main\n"
        f"main(['record', '--device', 'replay:{FIXTURES / 'color-scene'}', '-o', "
        f"'{tmp_path / 's.h5'}'])\n"
        "print([m for m in ('torch', 'pycolmap', 'kornia', 'gsplat') if m in sys.modules])"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.stdout.strip().splitlines()[-1] == "[]", r.stderr


def test_real_sample_replay_matches_the_aedat_import(tmp_path, sample_aedat4):
    """The re-encoded real recording, recorded, equals the AEDAT 4 import of the original."""
    from evcap.importers.aedat4 import import_aedat4

    import_aedat4(sample_aedat4, tmp_path / "a.h5")
    with Davis346.open(f"replay:{FIXTURES / 'davis346-sample'}") as cam:
        Recorder(cam, tmp_path / "r.h5").run()
    with Session.open(tmp_path / "a.h5") as a, Session.open(tmp_path / "r.h5") as r:
        ea, er = a.events(), r.events()
        for k in "xyp":
            np.testing.assert_array_equal(getattr(ea, k), getattr(er, k))
        np.testing.assert_array_equal(ea.t, er.t)  # both relative to the earliest timestamp
        np.testing.assert_allclose(a.imu().accel, r.imu().accel, rtol=1e-6)
        np.testing.assert_array_equal(a.frames().data[29], r.frames().data[0])


def test_recordings_on_request_hold_contiguous_parts_of_the_stream(tmp_path, fixture_copy):
    """The monitor's way: recordings opened and closed while the camera runs, here in the
    middle of frames (a frame exposed before a recording starts keeps its time)."""
    exp = np.load(FIXTURES / "color-scene" / "expected.npz")
    paths = [tmp_path / "a.h5", tmp_path / "b.h5"]
    events: list = []
    bias = P.coarse_fine_code(3, 9, n_type=True)
    # paced, so that batches are small and the requests fall between them
    spec = DeviceSpec("replay", path=idle_fixture(fixture_copy), speed=4.0)
    with Davis346.open(spec) as cam:
        recorder = Recorder(cam, None, on_event=events.append)
        plan = [
            (5_000, lambda: recorder.start_recording(paths[0])),
            (20_000, recorder.stop_recording),
            (30_000, lambda: recorder.start_recording(paths[1])),
            (45_000, lambda: recorder.set_bias("OffBn", bias)),
            (60_000, recorder.stop),
        ]

        def on_tick():
            if plan and recorder.decoder.counters["events"] >= plan[0][0]:
                plan.pop(0)[1]()

        recorder.on_tick = on_tick
        result = recorder.run()
        clock_start = cam.clock_started_us
    assert result.path == paths[1]
    stopped = [e.result for e in events if type(e).__name__ == "RecordingStopped"]
    assert [r.end_reason for r in stopped] == ["stopped", "stopped"]
    for path in paths:
        with Session.open(path) as s:
            assert s.complete
            shift = s.sensor.t_offset_us - clock_start
            t = s.events().t + shift
            assert t.size > 5000
            start = int(np.searchsorted(exp["events_t"], t[0]))
            np.testing.assert_array_equal(t, exp["events_t"][start : start + len(t)])
            frames_t = s.frames().t + shift
            assert set(frames_t.tolist()) <= set(exp["frames_t"].tolist())
    with Session.open(paths[1]) as s:
        assert s.settings_log()[0][1:] == ("bias.OffBn", bias)


def _is_end_reason(target: ast.expr) -> bool:
    return isinstance(target, ast.Name | ast.Attribute) and (
        getattr(target, "id", None) == "end_reason" or getattr(target, "attr", None) == "end_reason"
    )


def test_every_end_reason_is_typed():
    """Every end reason the recorder sets is one of EndReason's, so none is added untyped."""
    set_reasons = []
    for node in ast.walk(ast.parse(inspect.getsource(recorder_module))):
        pairs = []
        if isinstance(node, ast.Assign):
            for target in node.targets:
                if isinstance(target, ast.Tuple) and isinstance(node.value, ast.Tuple):
                    pairs += zip(target.elts, node.value.elts, strict=False)
                else:
                    pairs.append((target, node.value))
        elif isinstance(node, ast.AnnAssign) and node.value is not None:
            pairs.append((node.target, node.value))
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "_close"
            and node.args
        ):
            pairs.append((ast.Name("end_reason"), node.args[0]))
        set_reasons += [
            value.value
            for target, value in pairs
            if _is_end_reason(target)
            and isinstance(value, ast.Constant)
            and isinstance(value.value, str)
        ]
    assert {"stopped", "disk full", "camera lost", "write failed"} <= set(set_reasons)
    assert set(set_reasons) <= set(END_REASONS)
    assert set(NORMAL_ENDS) <= set(END_REASONS)
