"""`evcap poses` end to end on a small simulated recording (the hand-held board session of
tests/conftest.py): frames made and exported, /poses replaced by the estimate."""

import shutil

import h5py
import numpy as np
import pytest

from evcap.cli import main
from evcap.errors import InputError
from evcap.poses.align import pose_errors
from evcap.poses.estimate import estimate_poses
from evcap.poses.track import PoseTrack
from evcap.session import Session


def test_poses_from_the_events(board_session, tmp_path, capsys):
    session = shutil.copy(board_session, tmp_path / "s.h5")
    with Session.open(board_session) as s:
        truth = PoseTrack.from_session(s)
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
    assert len(list(frames.glob("*.png"))) == made
    # the estimate is a rigid path like the truth (a similarity maps one onto the other up to
    # the error); its accuracy is measured on full-size scenes in bench/poses.py, and run_sfm's
    # on rendered frames in test_sfm.py
    e = pose_errors(T, truth.at(t), by="poses")
    assert np.isfinite(e["rotation_rms_deg"]) and e["scale"] > 0


def test_a_session_without_intrinsics_is_refused(board_session, tmp_path):
    session = shutil.copy(board_session, tmp_path / "s.h5")
    with h5py.File(session, "r+") as f:
        del f["calibration"]
    with pytest.raises(InputError, match="evcap calibrate"):
        estimate_poses(session)


def test_bad_rate_is_refused(board_session):
    with pytest.raises(InputError, match="--rate"):
        estimate_poses(board_session, rate_hz=-3)
