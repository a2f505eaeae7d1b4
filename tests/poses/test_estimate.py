"""`evcap poses` end to end on a small simulated recording (the hand-held board session of
tests/conftest.py): frames made and exported, /poses replaced by the estimate."""

import shutil

import h5py
import numpy as np
import pytest

from evcap.app.cli import main
from evcap.errors import InputError
from evcap.poses.estimate import estimate_poses
from evcap.records import Poses
from evcap.session import Session
from evcap.trajectory_alignment import pose_errors


def test_poses_from_the_events(board_session, tmp_path, capsys):
    session = shutil.copy(board_session, tmp_path / "s.h5")
    with Session.open(board_session) as s:
        truth = Poses.read(s)
    frames = tmp_path / "frames"
    assert main(["poses", str(session), "--export-frames", str(frames)]) == 0
    out = capsys.readouterr().out
    assert "frames registered" in out and "scale arbitrary" in out
    with h5py.File(session, "r") as f:
        g = f["poses"]
        assert g.attrs["source"].startswith("evcap poses")
        t, T = g["t"][()], g["T_world_cam"][()]
        made = int(g.attrs["frames"])
        assert g.attrs["registered"] == len(t) >= 0.4 * made  # the first: no history yet
        points = g["points_xyz"][()]
        assert points.shape == (int(g.attrs["points"]), 3) and np.isfinite(points).all()
        assert g.attrs["orientations"] == "orientations from the frames"  # no IMU here
    assert len(list(frames.glob("*.png"))) == made
    # the estimate is a rigid path like the truth (a similarity maps one onto the other up to
    # the error); its accuracy is measured on full-size scenes in bench/poses.py, and run_sfm's
    # on rendered frames in test_sfm.py
    e = pose_errors(T, truth.at(t), by="poses")
    assert np.isfinite(e["rotation_rms_deg"]) and e["scale"] > 0
    # the points are in the poses' world: the board lies in front of the cameras
    middle = T[len(T) // 2]
    depth = (points - middle[:3, 3]) @ middle[:3, 2]
    assert np.median(depth) > 0


def test_a_session_without_intrinsics_is_refused(board_session, tmp_path):
    session = shutil.copy(board_session, tmp_path / "s.h5")
    with h5py.File(session, "r+") as f:
        del f["calibration"]
    with pytest.raises(InputError, match="evcap calibrate"):
        estimate_poses(session)


def test_bad_rate_is_refused(board_session):
    with pytest.raises(InputError, match="--rate"):
        estimate_poses(board_session, rate_hz=-3)


def test_an_unknown_frame_kind_is_refused(board_session):
    with pytest.raises(InputError, match="unknown frame kind 'sift'; known: filter"):
        estimate_poses(board_session, kind="sift")


def _frames_and_imu(aps_hz: float, turn_deg_per_s: float, imu: bool = True):
    from evcap.streams import Frames, ImuSamples

    t = np.arange(0, 1_000_000, int(1e6 / aps_hz), dtype=np.int64)
    frames = Frames(np.zeros((len(t), 4, 4), np.uint16), t, np.full(len(t), 4000))
    ti = np.arange(0, 1_000_001, 1000, dtype=np.int64) if imu else np.zeros(0, np.int64)
    gyro = np.zeros((len(ti), 3), np.float32)
    gyro[:, 1] = np.radians(turn_deg_per_s)
    zeros = np.zeros((len(ti), 3), np.float32)
    return frames, ImuSamples(ti, zeros, gyro, np.zeros(len(ti), np.float32))


@pytest.mark.parametrize(
    ("aps_hz", "turn_deg_per_s", "imu", "usable"),
    [
        (25, 30.0, True, True),  # 1.2 deg between frames: the hand-held sweep
        (10, 60.0, True, False),  # 6 deg: the demo's orbit, the filter would ghost
        (50, 60.0, True, True),
        (25, 0.0, False, True),  # without the IMU, by the rate alone
        (10, 0.0, False, False),
    ],
)
def test_aps_frames_are_used_when_the_motion_between_them_is_small(
    aps_hz, turn_deg_per_s, imu, usable
):
    from evcap.poses.estimate import aps_frames_usable

    frames, samples = _frames_and_imu(aps_hz, turn_deg_per_s, imu)
    ok, why = aps_frames_usable(frames, samples)
    assert ok is usable and why
