import subprocess
import sys

import aedat
import h5py
import numpy as np
import pytest

from evcap.errors import ForeignFormatError, OutputExistsError
from evcap.importers.aedat4 import import_aedat4, read_layout
from evcap.session import Session


def decode_reference(path):
    """Everything in the file, straight from the aedat decoder (absolute times)."""
    events, frames, imu, triggers = [], [], [], []
    for packet in aedat.Decoder(str(path)):
        if "events" in packet:
            events.append(packet["events"])
        elif "frame" in packet:
            frames.append(packet["frame"])
        elif "imus" in packet:
            imu.append(packet["imus"])
        elif "triggers" in packet:
            triggers.append(packet["triggers"])
    return np.concatenate(events), frames, np.concatenate(imu), np.concatenate(triggers)


@pytest.fixture(scope="module")
def imported(tmp_path_factory, sample_aedat4):
    out = tmp_path_factory.mktemp("import") / "sample.h5"
    summary = import_aedat4(sample_aedat4, out)
    return sample_aedat4, out, summary


def test_real_recording_imports_bit_exact(imported):
    src, out, summary = imported
    assert (summary.events, summary.frames, summary.imu, summary.triggers) == (
        78_830,
        59,
        2_363,
        236,
    )
    ev_ref, frames_ref, imu_ref, trig_ref = decode_reference(src)
    with Session.open(out) as s:
        assert (s.sensor.sensor, s.sensor.serial) == ("DAVIS346", "00000002")
        assert (s.sensor.width, s.sensor.height, s.sensor.color_filter) == (346, 260, "MONO")
        assert (s.n_events, s.n_frames, s.n_imu, s.n_triggers) == (78_830, 59, 2_363, 236)
        offset = s.sensor.t_offset_us
        ev = s.events()
        np.testing.assert_array_equal(ev.x, ev_ref["x"])
        np.testing.assert_array_equal(ev.y, ev_ref["y"])
        np.testing.assert_array_equal(ev.t + offset, ev_ref["t"].astype(np.int64))
        np.testing.assert_array_equal(ev.p, ev_ref["p"].astype(np.uint8))
        assert 0.5 < ev.p.mean() < 0.55  # the file's ~52 % ON

        fr = s.frames()
        np.testing.assert_array_equal(fr.data >> 2, np.stack([f["pixels"] for f in frames_ref]))
        np.testing.assert_array_equal(fr.t + offset, [f["exposure_begin_t"] for f in frames_ref])
        np.testing.assert_array_equal(fr.exposure_us, 500)

        imu = s.imu()
        np.testing.assert_array_equal(imu.t + offset, imu_ref["t"].astype(np.int64))
        np.testing.assert_allclose(imu.accel[:, 1], imu_ref["accelerometer_y"] * 9.80665, rtol=1e-6)
        # DV's (libcaer's) axes into the camera's: x and z negated
        np.testing.assert_allclose(imu.gyro[:, 2], -np.deg2rad(imu_ref["gyroscope_z"]), rtol=1e-6)
        np.testing.assert_allclose(
            imu.accel[:, 0], -imu_ref["accelerometer_x"] * 9.80665, rtol=1e-6
        )
        assert np.linalg.norm(imu.accel, axis=1).mean() == pytest.approx(9.8, abs=0.3)
        # gravity (the accelerometer reads "up") then says the camera is pitched about 15 deg
        # down, as its frames show it: the horizon about 75 px above the image's centre
        up = imu.accel.mean(0) / np.linalg.norm(imu.accel.mean(0))
        assert np.degrees(np.arcsin(-up[2])) == pytest.approx(15, abs=2)

        trig = s.triggers()
        np.testing.assert_array_equal(trig.t + offset, trig_ref["t"].astype(np.int64))
        np.testing.assert_array_equal(trig.kind, trig_ref["source"])
        # t = 0 is the earliest timestamp in the file
        assert min(int(ev.t[0]), int(fr.t[0]), int(imu.t[0]), int(trig.t[0])) == 0
    with h5py.File(out) as f:
        assert f["frames"].attrs["precision_bits"] == 8
        assert f.attrs["source_file"] == src.name


def test_layout_walk(imported):
    src, _, _ = imported
    layout = read_layout(src)
    assert layout.compression == "LZ4" and len(layout.packets) == 708
    assert "DAVIS346_00000002" in layout.info_xml


@pytest.mark.parametrize("keep", [5, 20, 1000, 3_000_000, 6_122_043 + 100, -1])
def test_truncated_aedat4_gives_a_clear_error(imported, tmp_path, keep):
    src, _, _ = imported
    data = src.read_bytes()
    cut = tmp_path / "cut.aedat4"
    cut.write_bytes(data[:keep])
    out = tmp_path / "out.h5"
    with pytest.raises(ForeignFormatError, match="truncated|not an AEDAT 4"):
        import_aedat4(cut, out)
    assert not out.exists() and not (tmp_path / "out.h5.partial").exists()


def test_not_aedat4(tmp_path):
    bad = tmp_path / "bad.aedat4"
    bad.write_bytes(b"#!AER-DAT2.0\r\n# jAER\r\n" + bytes(100))
    with pytest.raises(ForeignFormatError, match="AEDAT 2.0"):
        import_aedat4(bad, tmp_path / "o.h5")
    bad.write_bytes(b"hello world")
    with pytest.raises(ForeignFormatError, match="not an AEDAT 4 file"):
        import_aedat4(bad, tmp_path / "o.h5")


def test_corrupt_packet_length(imported, tmp_path):
    src, _, _ = imported
    data = bytearray(src.read_bytes())
    first = read_layout(src).packets[3][0]
    data[first + 4 : first + 8] = (10**8).to_bytes(4, "little")
    bad = tmp_path / "bad.aedat4"
    bad.write_bytes(bytes(data))
    with pytest.raises(ForeignFormatError, match=f"packet at byte {first} claims"):
        import_aedat4(bad, tmp_path / "o.h5")


def test_existing_output_is_kept(imported, tmp_path):
    src, _, _ = imported
    out = tmp_path / "o.h5"
    out.write_text("keep me")
    with pytest.raises(OutputExistsError):
        import_aedat4(src, out)
    assert out.read_text() == "keep me"


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "evcap", *args], capture_output=True, text=True)


def test_cli_import_and_info(imported, tmp_path):
    src, _, _ = imported
    out = tmp_path / "s.h5"
    r = run_cli("import", str(src), "-o", str(out))
    assert r.returncode == 0, r.stderr
    assert "78,830 events, 59 frames, 2,363 IMU samples, 236 triggers" in r.stdout
    r = run_cli("info", str(out), "--json")
    assert r.returncode == 0, r.stderr
    import json

    info = json.loads(r.stdout)
    assert info["events"] == 78_830 and info["sensor"] == "DAVIS346"
    assert info["duration_s"] == pytest.approx(2.364, abs=0.01)
    assert info["on_fraction"] == pytest.approx(0.523, abs=0.005)
    assert info["groups"] == ["events", "frames", "imu", "settings_log", "triggers"]
    r = run_cli("info", str(out))
    assert "DAVIS346 00000002" in r.stdout and "78,830" in r.stdout


@pytest.mark.parametrize(
    "make, args, message",
    [
        (None, ("info", "{d}/missing.h5"), "no such file"),
        (None, ("import", "{d}/missing.aedat4", "-o", "{d}/o.h5"), "no such file"),
        (
            lambda d: (d / "x.aedat4").write_text("nope"),
            ("import", "{d}/x.aedat4", "-o", "{d}/o.h5"),
            "not a recording evcap knows",
        ),
        (
            lambda d: (d / "x.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(40)),
            ("info", "{d}/x.h5"),
            "x.h5",
        ),
    ],
)
def test_cli_bad_input_exits_2_without_traceback(tmp_path, make, args, message):
    if make:
        make(tmp_path)
    r = run_cli(*(a.format(d=tmp_path) for a in args))
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and message in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_cli_truncated_session(imported, tmp_path):
    _, out, _ = imported
    cut = tmp_path / "cut.h5"
    cut.write_bytes(out.read_bytes()[: out.stat().st_size // 2])
    r = run_cli("info", str(cut))
    assert r.returncode == 2 and "truncated" in r.stderr and "Traceback" not in r.stderr
