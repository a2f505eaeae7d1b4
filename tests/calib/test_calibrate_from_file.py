"""`evcap calibrate --intrinsics FILE` and `--export FILE`, end to end: on a tiny simulated
recording with a calibration file made for it, and on the real DAVIS346 recording with a real
DAVIS346's Kalibr camchain, through `evcap import` and `evcap poses`."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from evcap.app.cli import main
from evcap.calib.calibrate import calibrate
from evcap.importers.calibration_files import (
    CameraCalibration,
    read_calibration_file,
    write_calibration_file,
)
from evcap.records import Calibration
from evcap.session import Session, SessionWriter
from evcap.sim.scene import load_scene
from evcap.sim.simulate import simulate

DATA = Path(__file__).resolve().parents[1] / "data" / "davis346-calibrations"
KALIBR = DATA / "arclab_esvio_kalibr_camchain-imucam.yaml"
SHIFT_S = 0.0019438323735646128  # that camchain's timeshift_cam_imu


def read(path: Path) -> Calibration:
    with Session.open(path) as s:
        return Calibration.read(s)


@pytest.fixture(scope="module")
def simulated(tiny_scene, tmp_path_factory) -> Path:
    """A tiny simulated recording (48 x 36, 0.3 s) with APS frames and an IMU, and its true
    calibration."""
    scene = tiny_scene(
        extra="[aps]\nfps = 40\nexposure_us = 2000\n[imu]\nrate_hz = 1000\n"
        "[gt]\nfps = 10\ntest_views = 0"
    )
    path = tmp_path_factory.mktemp("from_file") / "sim.h5"
    simulate(load_scene(scene), path)
    return path


@pytest.fixture
def session(simulated, tmp_path) -> Path:
    """A copy of the simulated recording without its /calibration."""
    path = Path(shutil.copy(simulated, tmp_path / "s.h5"))
    with h5py.File(path, "r+") as f:
        del f["calibration"]
    return path


@pytest.fixture
def camchain(simulated, tmp_path) -> Path:
    """A Kalibr camchain for the simulated camera: its true intrinsics, a distortion, and the
    real camchain's camera-IMU transform and time shift."""
    truth = read(simulated)
    real = read_calibration_file(KALIBR)
    cal = CameraCalibration(
        width=48,
        height=36,
        K=truth.K,
        distortion_model="radtan",
        dist=np.array([-0.05, 0.01, 0.0005, -0.0002]),
        T_cam_imu=real.T_cam_imu,
        timeshift_cam_imu_s=real.timeshift_cam_imu_s,
    )
    path = tmp_path / "camchain.yaml"
    write_calibration_file(cal, path, "kalibr")
    return path


def test_intrinsics_from_a_camchain_and_thresholds_from_the_recording(
    session, camchain, tmp_path, capsys
):
    other = shutil.copy(session, tmp_path / "other.h5")
    code = main(
        ["calibrate", str(session), "--intrinsics", str(camchain), "--apply-to", str(other)]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "intrinsics, camchain.yaml (Kalibr camchain, cam0): fx" in out
    assert "camera-IMU, camchain.yaml (Kalibr camchain, cam0): the IMU's axes 0.62 deg" in out
    assert "t_imu = t_cam + 1.944 ms" in out
    assert "thresholds ON/OFF (APS frames vs events)" in out  # measured, as ever
    file = read_calibration_file(camchain)
    for path in (session, other):
        cal = read(path)
        assert cal.source == "evcap calibrate"
        assert cal.notes["intrinsics_source"] == "camchain.yaml (Kalibr camchain, cam0)"
        assert cal.notes["camera_imu_source"] == "camchain.yaml (Kalibr camchain, cam0)"
        np.testing.assert_array_equal(cal.K, file.K)
        np.testing.assert_array_equal(cal.dist, file.dist)
        np.testing.assert_array_equal(cal.T_cam_imu, file.T_cam_imu)
        assert cal.timeshift_cam_imu_us == pytest.approx(SHIFT_S * 1e6, abs=1e-9)
        assert cal.threshold_on is not None and cal.hot_pixels is not None
        assert cal.notes["threshold_source"] == "APS frames vs events"


def test_a_later_calibration_keeps_the_camera_imu_transform(session, camchain, tmp_path):
    """A file without one (ROS camera_info) or intrinsics kept: the transform stays, still
    said to come from the camchain."""
    file = read_calibration_file(camchain)
    calibrate(session, intrinsics=file).record().write(session)
    ros = tmp_path / "ost.yaml"
    write_calibration_file(file, ros, "ros")
    for run in (
        calibrate(session, intrinsics=read_calibration_file(ros)),
        calibrate(session, skip=frozenset({"intrinsics"})),
    ):
        assert run.camera_imu_source == "camchain.yaml (Kalibr camchain, cam0)"
        np.testing.assert_array_equal(run.T_cam_imu, file.T_cam_imu)
        assert run.timeshift_cam_imu_us == pytest.approx(SHIFT_S * 1e6)
    assert run.intrinsics_source == "kept (evcap calibrate)"


@pytest.mark.parametrize(
    ("name", "fmt", "holds_imu"),
    [
        ("out.yaml", None, True),
        ("out.yaml", "kalibr", True),
        ("out.yaml", "vins", True),
        ("out.yaml", "ros", False),
        ("out.xml", None, False),
    ],
)
def test_export_reads_back_equal(session, camchain, tmp_path, capsys, name, fmt, holds_imu):
    assert main(["calibrate", str(session), "--intrinsics", str(camchain)]) == 0
    out = tmp_path / name
    flags = ["--format", fmt] if fmt else []
    assert main(["calibrate", str(session), "--export", str(out), *flags]) == 0
    said = capsys.readouterr().out
    stored, back = read(session), read_calibration_file(out)
    np.testing.assert_array_equal(back.K, stored.K)
    assert back.distortion_model == stored.distortion_model
    np.testing.assert_array_equal(back.dist[:4], stored.dist)
    assert not back.dist[4:].any()
    assert (back.width, back.height) == (48, 36)
    if holds_imu:
        np.testing.assert_allclose(back.T_cam_imu, stored.T_cam_imu, rtol=0, atol=1e-15)
        assert back.timeshift_cam_imu_s == pytest.approx(SHIFT_S, abs=1e-15)
    else:
        assert back.T_cam_imu is None
        assert "not written: the camera-IMU transform and time shift" in said
    # the file goes back into a session as it came out
    copy = shutil.copy(session, tmp_path / "again.h5")
    assert main(["calibrate", str(copy), "--intrinsics", str(out)]) == 0
    np.testing.assert_array_equal(read(copy).K, stored.K)


def test_import_and_export_in_one_go(session, camchain, tmp_path, capsys):
    out = tmp_path / "dv.xml"
    code = main(["calibrate", str(session), "--intrinsics", str(camchain), "--export", str(out)])
    assert code == 0
    said = capsys.readouterr().out
    assert "written to /calibration" in said and f"{out}: the calibration of" in said
    assert read_calibration_file(out).camera == "simulated_SIM_tiny"  # its sensor and serial


def test_a_davis346_calibration_on_another_sensor_is_refused(session, capsys):
    before = session.read_bytes()
    code = main(["calibrate", str(session), "--intrinsics", str(KALIBR)])
    err = capsys.readouterr().err
    assert code == 2
    assert "(Kalibr camchain, cam0) is a calibration of 346 x 260 images" in err
    assert "is 48 x 36" in err
    assert session.read_bytes() == before


def test_flags_that_do_not_go_together(session, camchain, tmp_path, capsys):
    k3 = tmp_path / "k3.yaml"
    k3.write_text(  # ROS camera_info with a k3, which Kalibr's radtan cannot hold
        "image_width: 346\nimage_height: 260\ndistortion_model: plumb_bob\n"
        "camera_matrix: {rows: 3, cols: 3, data: [250, 0, 173, 0, 250, 130, 0, 0, 1]}\n"
        "distortion_coefficients: {rows: 1, cols: 5, data: [-0.3, 0.1, 0, 0, 0.01]}\n"
    )
    cases = [
        (["--camera", "cam1"], "--camera picks a camera of an --intrinsics file"),
        (["--format", "ros"], "--format goes with --export"),
        (["--intrinsics", str(camchain), "--skip", "intrinsics"], "give one of them"),
        (
            ["--intrinsics", str(camchain), "--board", "charuco:5x4:0.04:0.03:DICT_4X4_50"],
            "--board",
        ),
        (["--intrinsics", str(camchain), "--export", str(camchain)], "replace the --intrinsics"),
        (["--export", str(tmp_path / "a.yaml"), "--skip", "thresholds"], "--export alone"),
        (["--export", str(tmp_path / "a.txt")], r"write \.yaml"),
        (["--export", str(tmp_path / "a.xml"), "--format", "vins"], r"an \.xml file is DV's"),
        (["--export", str(camchain)], "exists: give --force"),
        (["--export", str(tmp_path / "a.yaml")], "has no calibration"),  # none yet
        (["--intrinsics", str(DATA / "arclab_esvio_kalibr_imu.yaml")], "Kalibr IMU calibration"),
        (["--intrinsics", str(tmp_path / "none.yaml")], "none.yaml: no such file"),
        # what --export cannot write is said before the session's calibration is replaced
        (["--intrinsics", str(k3), "--export", str(tmp_path / "k.yaml")], "k3 is 0.01"),
    ]
    for flags, message in cases:
        assert main(["calibrate", str(session), *flags]) == 2, flags
        err = capsys.readouterr().err
        assert re.search(message, err) and len(err.strip().splitlines()) == 1, (flags, err)
    with Session.open(session) as s:
        assert not Calibration.present(s)


def test_too_few_events_take_the_datasheets_thresholds(session, camchain, tmp_path):
    few = tmp_path / "few.h5"
    with Session.open(session) as s:
        sensor, events = s.sensor, s.events()
    with SessionWriter(few, sensor) as w:
        w.append_events(events.select(np.arange(len(events)) < 300))
    run = calibrate(few, intrinsics=read_calibration_file(camchain))
    assert run.threshold_source.startswith("the datasheet's nominal values")
    assert "300 events are too few" in run.threshold_source
    np.testing.assert_allclose(run.threshold_on, np.log(1.143))
    np.testing.assert_allclose(run.threshold_off, np.log(1.225))
    assert "hot pixels and noise: not measured" in run.summary()
    run.record().write(few)
    assert json.loads(read(few).notes["warnings"])[0].startswith("300 events are too few")


def test_the_real_recording_import_calibrate_poses(sample_aedat4, tmp_path, capsys):
    """The bundled DV recording as a new user takes it: imported, calibrated with a real
    DAVIS346's Kalibr camchain (another unit of the same model), posed. The camera stands on a
    desk: poses ends with an error that says so (`--rate 5` keeps it to a few seconds; the
    default 25 Hz frames end the same way after a minute and a half)."""
    session = tmp_path / "real.h5"
    assert main(["import", str(sample_aedat4), "-o", str(session)]) == 0
    assert "78,830 events, 59 frames, 2,363 IMU samples" in capsys.readouterr().out
    assert main(["calibrate", str(session), "--intrinsics", str(KALIBR)]) == 0
    out = capsys.readouterr().out
    assert "intrinsics, arclab_esvio_kalibr_camchain-imucam.yaml (Kalibr camchain, cam0)" in out
    assert "thresholds: 59 APS frames against 78,830 events" in out
    assert "camera-IMU" in out and f"written to /calibration of {session}" in out
    assert main(["poses", str(session), "--rate", "5"]) == 2
    captured = capsys.readouterr()
    assert "IMU turned into the camera's axes and clock" in captured.out
    assert "t_imu = t_cam + 1.944 ms" in captured.out
    err = captured.err
    assert "structure from motion failed" in err and "the camera must move" in err
    assert "the IMU says the camera stood still" in err
    # the calibration goes out again, to DV's file
    xml = tmp_path / "calibration_camera_DAVIS346_00000002.xml"
    assert main(["calibrate", str(session), "--export", str(xml)]) == 0
    back = read_calibration_file(xml)
    assert back.camera == "DAVIS346_00000002"
    np.testing.assert_array_equal(back.K, read_calibration_file(KALIBR).K)


@pytest.mark.slow
def test_the_real_recording_at_the_default_frame_rate(sample_aedat4, tmp_path, capsys):
    """As above with `evcap poses`' defaults (25 Hz frames leaning on the APS frames): about a
    minute and a half of structure from motion, the same error."""
    session = tmp_path / "real.h5"
    assert main(["import", str(sample_aedat4), "-o", str(session)]) == 0
    assert main(["calibrate", str(session), "--intrinsics", str(KALIBR)]) == 0
    capsys.readouterr()
    assert main(["poses", str(session)]) == 2
    err = capsys.readouterr().err
    assert "the camera must move" in err and "the IMU says the camera stood still" in err
