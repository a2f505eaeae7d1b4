"""AEDAT 2.0 files without an '# AEChip:' line (jAER's DVS128 recordings of before ~2016): the
chip from --chip or from the address range, and where it came from said."""

import subprocess
import sys

import h5py
import numpy as np
import pytest
from test_aedat2 import davis_dvs_address, dvs128_address

from evcap.app.cli import main
from evcap.errors import ForeignFormatError, InputError
from evcap.importers.aedat2 import import_aedat2
from evcap.session import Session


def headerless_file(path, address, t, chip_class=None):
    """The magic line, comment lines (an '# AEChip:' line only if ``chip_class``), then
    big-endian (int32 address, int32 timestamp) records."""
    lines = [b"#!AER-DAT2.0", b"# This is a raw AE data file - do not edit"]
    if chip_class is not None:
        lines.append(b"# AEChip: " + chip_class.encode())
    lines.append(b"# created Mon Mar 02 10:11:12 CET 2015")
    records = np.stack([np.asarray(address), np.asarray(t)], axis=1).astype(">u4")
    path.write_bytes(b"\r\n".join(lines) + b"\r\n" + records.tobytes())
    return path


# events at the sensor's corners, both polarities
X = np.array([0, 127, 0, 127, 64, 3])
Y = np.array([0, 0, 127, 127, 10, 100])
P = np.array([1, 0, 0, 1, 1, 0])
T = np.array([1_000, 1_010, 1_025, 1_100, 2_000, 2_500])


@pytest.fixture
def dvs128(tmp_path):
    return headerless_file(tmp_path / "dvs128.aedat", dvs128_address(X, Y, P), T)


def test_cli_with_chip_imports_a_headerless_dvs128_file(dvs128, tmp_path):
    out = tmp_path / "s.h5"
    r = subprocess.run(
        [sys.executable, "-m", "evcap", "import", str(dvs128), "-o", str(out), "--chip", "DVS128"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert "6 events" in r.stdout and "(AEDAT 2.0, DVS128)" in r.stdout
    assert "chip DVS128 (from --chip; the file states none)" in r.stdout
    with Session.open(out) as s:
        assert (s.sensor.sensor, s.sensor.width, s.sensor.height) == ("DVS128", 128, 128)
        ev = s.events()
        np.testing.assert_array_equal(ev.x, X)
        np.testing.assert_array_equal(ev.y, Y)
        np.testing.assert_array_equal(ev.p, P)
        np.testing.assert_array_equal(ev.t, T - T[0])
    with h5py.File(out, "r") as f:
        assert f.attrs["source_chip_from"] == "--chip"
        assert "source_chip_class" not in f.attrs  # the file names none


def test_without_chip_dvs128_is_inferred_and_said(dvs128, tmp_path, capsys):
    assert main(["import", str(dvs128), "-o", str(tmp_path / "s.h5")]) == 0
    out = capsys.readouterr().out
    assert "chip DVS128 (inferred from the address range; pass --chip to choose)" in out
    with Session.open(tmp_path / "s.h5") as s:
        assert (s.sensor.width, s.sensor.height, s.n_events) == (128, 128, 6)
        np.testing.assert_array_equal(s.events().x, X)
    with h5py.File(tmp_path / "s.h5", "r") as f:
        assert f.attrs["source_chip_from"] == "address range"


def test_a_headerless_davis346_file_is_inferred(tmp_path):
    x, y, p = np.array([0, 345, 200]), np.array([0, 259, 190]), np.array([1, 0, 1])
    aps = (1 << 31) | (100 << 22) | (300 << 12) | 500  # an APS reset read inside 346 x 260
    imu = (1 << 31) | (3 << 10) | (0x7FFF << 12)  # IMU records are not pixels
    src = headerless_file(
        tmp_path / "d.aedat",
        np.concatenate([davis_dvs_address(x, y, p, 346, 260), [aps, imu]]),
        [10, 20, 30, 40, 50],
    )
    summary = import_aedat2(src, tmp_path / "s.h5")
    assert summary.source == "AEDAT 2.0, DAVIS346" and summary.events == 3
    assert summary.notes == [
        "chip DAVIS346 (inferred from the address range; pass --chip to choose)"
    ]
    with Session.open(tmp_path / "s.h5") as s:
        assert (s.sensor.width, s.sensor.height) == (346, 260)
        np.testing.assert_array_equal(s.events().x, x)
        np.testing.assert_array_equal(s.events().y, y)


def test_a_headerless_davis240_file_is_inferred(tmp_path):
    address = davis_dvs_address(np.array([0, 239]), np.array([179, 0]), np.array([1, 0]), 240, 180)
    src = headerless_file(tmp_path / "d.aedat", address, [10, 20])
    assert import_aedat2(src, tmp_path / "s.h5").source == "AEDAT 2.0, DAVIS240"
    with Session.open(tmp_path / "s.h5") as s:
        assert (s.sensor.width, s.sensor.height) == (240, 180)


def test_chip_overriding_the_header_says_so(tmp_path, capsys):
    src = headerless_file(
        tmp_path / "o.aedat",
        dvs128_address(X, Y, P),
        T,
        chip_class="eu.seebetter.ini.chips.davis.DAVIS240C",
    )
    out = tmp_path / "s.h5"
    assert main(["import", str(src), "-o", str(out), "--chip", "DVS128"]) == 0
    captured = capsys.readouterr()
    assert "chip DVS128 (from --chip)" in captured.out
    assert (
        "warning: the file states chip eu.seebetter.ini.chips.davis.DAVIS240C; DVS128 from "
        "--chip is used instead" in captured.err
    )
    with h5py.File(out, "r") as f:
        assert f.attrs["source_chip_from"] == "--chip"
        assert f.attrs["source_chip_class"] == "eu.seebetter.ini.chips.davis.DAVIS240C"
    with Session.open(out) as s:
        assert (s.sensor.sensor, s.sensor.width, s.n_events) == ("DVS128", 128, 6)


def test_the_header_chip_is_recorded_as_such(tmp_path):
    src = headerless_file(
        tmp_path / "h.aedat", dvs128_address(X, Y, P), T, "ch.unizh.ini.jaer.chip.retina.DVS128"
    )
    summary = import_aedat2(src, tmp_path / "s.h5")
    assert summary.notes == [] and summary.warnings == []
    with h5py.File(tmp_path / "s.h5", "r") as f:
        assert f.attrs["source_chip_from"] == "header"
    summary = import_aedat2(src, tmp_path / "s2.h5", chip="DVS128")
    assert summary.notes == ["chip DVS128 (from --chip, as the file states)"]
    assert summary.warnings == []


def test_an_unknown_chip_name_is_a_clear_error(dvs128, tmp_path, capsys):
    assert main(["import", str(dvs128), "-o", str(tmp_path / "s.h5"), "--chip", "DVS640"]) == 2
    err = capsys.readouterr().err
    assert "--chip 'DVS640' is not a jAER chip class evcap knows" in err
    assert "DVS128" in err and "DAVIS240" in err and "Davis346" in err
    assert not (tmp_path / "s.h5").exists()


def test_chip_is_refused_for_other_containers(tmp_path):
    from evcap.importers.detect import import_recording

    src = tmp_path / "e.txt"
    src.write_text("0.1 1 2 1\n0.2 3 4 0\n")
    with pytest.raises(InputError, match="--chip is not for"):
        import_recording(src, tmp_path / "s.h5", chip="DVS128")


def test_addresses_that_fit_no_chip_ask_for_chip(tmp_path):
    # x 400 fits neither DAVIS240 nor DAVIS346
    address = davis_dvs_address(np.array([400]), np.array([5]), np.array([1]), 1024, 260)
    src = headerless_file(tmp_path / "n.aedat", address, [10])
    with pytest.raises(ForeignFormatError) as e:
        import_aedat2(src, tmp_path / "s.h5")
    message = str(e.value)
    assert "no '# AEChip:' header line and its addresses fit none of the chips" in message
    assert "pass --chip" in message and "DVS128" in message and "DAVIS240" in message
    assert not (tmp_path / "s.h5").exists()
    empty = headerless_file(tmp_path / "empty.aedat", np.zeros(0, int), np.zeros(0, int))
    with pytest.raises(ForeignFormatError, match="no records; pass --chip"):
        import_aedat2(empty, tmp_path / "s.h5")
