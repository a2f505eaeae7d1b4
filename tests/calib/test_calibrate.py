"""`evcap calibrate` end to end on a small simulated calibration session with known truth: the
group it writes, --apply-to, --report, --print-board, the errors a person meets, and the
simulator taking a measured sensor."""

import json
import shutil

import h5py
import numpy as np
import pytest

from evcap.app.cli import main
from evcap.calib.calibrate import SKIPPABLE, calibrate, write_calibration
from evcap.errors import CalibrationError
from evcap.records import Calibration
from evcap.session import SensorInfo, Session, SessionWriter
from evcap.sim.scene import load_scene
from evcap.sim.simulate import simulate

BOARD = "charuco:5x4:0.04:0.03:DICT_4X4_50"  # the board of the board_session fixture


def truth(path):
    with h5py.File(path, "r") as f:
        g = f["gt"]
        hot = np.zeros(g["threshold_on"].shape, bool).ravel()
        hot[g.attrs["hot_pixels"]] = True
        return (
            g["K"][()],
            g["threshold_on"][()],
            g["threshold_off"][()],
            hot.reshape(g["threshold_on"].shape),
        )


def copy_session(src, dst, frames: bool = True, events: int | None = None):
    """The same recording, without its frames or with only its first events."""
    with Session.open(src) as s:
        sensor, ev, fr = s.sensor, s.events(), s.frames()
    if events is not None:
        ev = ev.select(np.arange(len(ev)) < events)
    with SessionWriter(dst, sensor) as w:
        w.append_events(ev)
        if frames:
            w.append_frames(fr)
    return dst


def test_calibrate_measures_the_simulated_sensor(board_session, tmp_path, capsys):
    other = copy_session(board_session, tmp_path / "other.h5")
    report = tmp_path / "report.png"
    code = main(
        [
            "calibrate",
            str(board_session),
            "--board",
            BOARD,
            "--apply-to",
            str(other),
            "--report",
            str(report),
        ]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "RMS reprojection" in out and "hot pixels" in out
    K_true, on_true, off_true, hot_true = truth(board_session)
    for path in (board_session, other):
        with h5py.File(path, "r") as f:
            g = f["calibration"]
            assert g.attrs["source"] == "evcap calibrate"
            K, on, off = g["K"][()], g["threshold_on"][()], g["threshold_off"][()]
            conf, hot = g["threshold_confidence"][()], g["hot_pixels"][()].astype(bool)
            rms = g.attrs["rms_reprojection_px"]
            for name in ("dist", "event_rate_hz", "view_rms_px"):
                assert np.isfinite(g[name][()]).all()
    # 1.2 s over a small sensor leave the focal length uncertain by about 1 % (the full-size
    # scene of bench/calibration.py reaches 0.5 %): the bounds are this scene's, and the
    # calibration says so
    assert "focal length uncertain" in out
    assert np.abs(np.diag(K)[:2] / np.diag(K_true)[:2] - 1).max() < 0.025
    assert np.abs(K[:2, 2] / K_true[:2, 2] - 1).max() < 0.01
    assert rms < 0.3
    good = conf >= 0.5
    assert good.mean() > 0.2
    err = np.concatenate([on[good] - on_true[good], off[good] - off_true[good]])
    assert np.sqrt(np.mean(err**2)) < 0.02
    found = hot & hot_true
    assert found.sum() / hot.sum() > 0.95 and found.sum() / hot_true.sum() > 0.95
    assert report.stat().st_size > 10_000


def test_a_bad_apply_to_target_leaves_every_session_as_it_was(board_session, tmp_path, capsys):
    session = copy_session(board_session, tmp_path / "board.h5")
    before = session.read_bytes()
    code = main(["calibrate", str(session), "--board", BOARD, "--apply-to", str(tmp_path / "x.h5")])
    assert code == 2 and "x.h5: no such file" in capsys.readouterr().err
    # a session from another sensor: found out only once the calibration is known
    other = tmp_path / "other.h5"
    with SessionWriter(other, SensorInfo("DAVIS346", 346, 260)):
        pass
    code = main(["calibrate", str(session), "--board", BOARD, "--apply-to", str(other)])
    assert code == 2 and "the calibration is for 200 x 150" in capsys.readouterr().err
    assert session.read_bytes() == before
    with h5py.File(other, "r") as f:
        assert "calibration" not in f


def test_the_simulator_takes_a_measured_sensor(board_session, tiny_scene, tmp_path):
    """A scene whose [sensor] names a calibrated session gets its thresholds and hot pixels."""
    scene = tiny_scene(
        width=200,
        height=150,
        fx=160.0,
        effects=f'calibration = "{board_session}"',
        trajectory='kind = "static"\nposition = [0, -2, 0]\nlook_at = [0, 0, 0]\nduration_s = 0.1',
        extra="[gt]\nfps = 10\ntest_views = 0",
    )
    out = tmp_path / "measured.h5"
    simulate(load_scene(scene), out)
    with h5py.File(board_session, "r") as f:
        cal = f["calibration"]
        on, hot = cal["threshold_on"][()], cal["hot_pixels"][()]
    with h5py.File(out, "r") as f:
        assert np.array_equal(f["gt/threshold_on"][()], on)
        assert np.array_equal(f["calibration/hot_pixels"][()], hot)
        assert json.loads(f.attrs["effects"])["hot_pixels"]["count"] == int(hot.sum())


def test_no_board_in_view_is_a_clear_error(board_session, capsys):
    code = main(["calibrate", str(board_session), "--board", "charuco:7x5:0.04:0.03:DICT_5X5_100"])
    err = capsys.readouterr().err
    assert code == 2 and "board was found in 0 of" in err


def test_no_frames_and_few_events_is_a_clear_error(board_session, tmp_path):
    few = copy_session(board_session, tmp_path / "few.h5", frames=False, events=500)
    with pytest.raises(CalibrationError, match="500 events"):
        calibrate(few)


def test_without_frames_thresholds_balance_the_counts_and_noise_is_measured(
    board_session, tmp_path
):
    """(Finding the board in event frames needs the full sensor: bench/calibration.py.)"""
    blind = copy_session(board_session, tmp_path / "blind.h5", frames=False)
    cal = calibrate(blind, skip=frozenset({"intrinsics"}))
    assert "event counts" in cal.threshold_source and cal.thresholds is None
    # the simulated thresholds are the same for ON and OFF: so is their ratio
    assert cal.threshold_on.mean() / cal.threshold_off.mean() == pytest.approx(1.0, abs=0.05)
    assert any("no APS frames" in w for w in cal.warnings)
    hot_true = truth(board_session)[3]
    assert (cal.noise.hot_pixels == hot_true).all()


def test_skipped_parts_keep_what_the_session_held(board_session, tmp_path):
    """What is skipped is kept from the session's calibration (here the simulator's truth) and
    written again beside the noise measured anew."""
    session = shutil.copy(board_session, tmp_path / "s.h5")
    with Session.open(session) as s:
        before = Calibration.read(s)
    cal = calibrate(session, skip=frozenset(SKIPPABLE))
    assert cal.intrinsics_source == cal.threshold_source == f"kept ({before.source})"
    write_calibration([session], cal)
    with Session.open(session) as s:
        after = Calibration.read(s)
    assert after.source == "evcap calibrate"
    assert after.notes["intrinsics_source"] == cal.intrinsics_source
    assert np.array_equal(after.K, before.K) and np.array_equal(after.dist, before.dist)
    assert after.distortion_model == before.distortion_model
    assert np.array_equal(after.threshold_on, before.threshold_on)
    assert np.array_equal(after.threshold_off, before.threshold_off)
    assert np.array_equal(after.hot(), cal.noise.hot_pixels)


def test_print_board_alone(tmp_path, capsys):
    png = tmp_path / "board.png"
    assert main(["calibrate", "--print-board", str(png)]) == 0
    assert "280 x 200 mm" in capsys.readouterr().out and png.exists()
