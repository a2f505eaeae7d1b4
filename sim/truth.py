"""The ground truth of a simulated recording, kept apart from its hardware-replay fixture.

A fixture (hw-fixtures/) carries only what the camera sends; a session recorded from it through
the driver has no /gt. The truth file beside the fixture (``truth.h5``) keeps what the
evaluation needs of the simulated session's ground truth and trajectory, small: an HDF5 file
with the root attributes ``truth_version`` and ``source`` (the session's name), and

- its ground truth (evcap.records.GroundTruth, written with half=True: the images in float16,
  gzip 9): the times and poses of the views along the path (no images), K, the held-out views
  with the maps of HELD_OUT_MAPS (and, where the session has them, the relit radiance and the
  second light), the attributes of the session's;
- its trajectory (evcap.records.Poses, 500 per second), to align estimated poses with.

``write_truth(session, truth)`` makes it from a simulated session; ``copy_truth(truth,
session)`` adds its ground truth (images back in float32) to a session, e.g. one recorded from
the fixture, so that ``evcap reconstruct`` renders and scores the held-out views
(evcap.recon.evaluate.views.test_views) and the estimated poses can be compared with the truth. (A
simulated session itself reads as a truth file too.)
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import h5py

from evcap.atomic_write import atomic_path
from evcap.errors import InputError, InputNotFoundError, SessionFormatError
from evcap.records import GroundTruth, Poses, TruthViews

HELD_OUT_MAPS = ("radiance", "depth", "normal", "base_color", "roughness")  # the evaluation's
KEPT_MAPS = (*HELD_OUT_MAPS, "relit_radiance")  # the last where the session has it
TRUTH_VERSION = 1  # of the truth file's layout (root attribute ``truth_version``)


def write_truth(session_path: str | Path, truth_path: str | Path) -> None:
    """Write the truth file of a simulated session (see the module)."""
    session_path, truth_path = Path(session_path), Path(truth_path)
    with h5py.File(session_path, "r") as f:
        if not (GroundTruth.present(f) and Poses.present(f)):
            raise InputError(
                f"{session_path} has no ground truth and poses: not a simulated session"
            )
        truth, trajectory = GroundTruth.read(f), Poses.read(f)
    missing = _missing_maps(truth)
    if missing:
        raise InputError(
            f"{session_path}: its held-out views have no {', '.join(missing)} (the scene needs "
            "[gt] test_views > 0)"
        )
    held = truth.held_out_views()
    kept = {k: v for k, v in held.maps().items() if k in KEPT_MAPS}
    # the thresholds and the path's images stay in the session: the evaluation needs neither
    small = dataclasses.replace(
        truth,
        path=TruthViews(truth.path.T_world_cam),
        held_out=TruthViews(held.T_world_cam, **kept),
        threshold_on=None,
        threshold_off=None,
    )
    with atomic_path(truth_path) as partial:
        with h5py.File(partial, "w", track_order=True) as out:
            out.attrs["truth_version"] = TRUTH_VERSION
            out.attrs["source"] = session_path.name
        small.write(partial, half=True)
        trajectory.write(partial)


def read_truth(truth_path: str | Path) -> tuple[GroundTruth, Poses]:
    """The ground truth (images as float32) and trajectory of a truth file."""
    truth_path = Path(truth_path)
    if not truth_path.is_file():
        raise InputNotFoundError(f"no truth file at {truth_path}")
    try:
        f = h5py.File(truth_path, "r")
    except OSError as e:
        raise SessionFormatError(f"{truth_path} is not a truth file: {e}") from None
    with f:
        if not (GroundTruth.present(f) and Poses.present(f)):
            raise SessionFormatError(
                f"{truth_path} is not a truth file (no ground truth and poses)"
            )
        truth, trajectory = GroundTruth.read(f), Poses.read(f)
    missing = _missing_maps(truth)
    if missing:
        raise SessionFormatError(f"{truth_path}: its held-out views have no {', '.join(missing)}")
    return truth, trajectory


def copy_truth(
    truth_path: str | Path,
    session_path: str | Path,
    *,
    poses: bool = False,
    replace: bool = False,
) -> None:
    """Add the truth file's ground truth to a (closed) session; with ``poses``, its simulated
    trajectory as the session's poses too (replacing what is there: the reconstruction then
    runs on the true poses). ``replace``: replace ground truth the session already has (else
    SessionFormatError). The session must show the same image size as the truth."""
    truth, trajectory = read_truth(truth_path)
    session_path = Path(session_path)
    if not session_path.is_file():
        raise InputNotFoundError(f"no session at {session_path}")
    with h5py.File(session_path, "r") as f:
        size = (int(f.attrs.get("height", -1)), int(f.attrs.get("width", -1)))
    depth = truth.held_out_views().depth
    if depth.shape[1:] != size:
        raise InputError(
            f"{truth_path} is the truth of a {depth.shape[2]} x {depth.shape[1]} camera, "
            f"{session_path} is {size[1]} x {size[0]}"
        )
    truth.notes["truth_file"] = Path(truth_path).name
    truth.write(session_path, replace=replace)
    if poses:
        trajectory.write(session_path, replace=True)


def _missing_maps(truth: GroundTruth) -> list[str]:
    """The maps of HELD_OUT_MAPS the truth's held-out views lack (all without such views)."""
    return [k for k in HELD_OUT_MAPS if k not in truth.held_out_views().maps()]
