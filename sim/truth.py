"""The ground truth of a simulated recording, kept apart from its hardware-replay fixture.

A fixture (hw-fixtures/) carries only what the camera sends; a session recorded from it through
the driver has no /gt. The truth file beside the fixture (``truth.h5``) keeps what the
evaluation needs of the simulated session's /gt and /poses, small:

- ``/gt``: ``t`` (int64 us) and ``T_world_cam`` [N, 4, 4] (camera-to-world, OpenCV axes) of the
  ground-truth frames along the path, ``K`` [3, 3]; the held-out views: ``test_T_world_cam``
  [V, 4, 4] and their ``test_radiance`` [V, H, W, 3] (linear RGB), ``test_depth`` [V, H, W]
  (camera z, 0 where no surface), ``test_normal`` [V, H, W, 3] (camera axes),
  ``test_base_color`` [V, H, W, 3] and ``test_roughness`` [V, H, W]; the images in float16,
  all gzip-compressed with the shuffle filter; the attributes of the session's /gt; where the
  session has them, ``test_relit_radiance`` and ``relight_environment`` (the second light).
- ``/poses``: the simulated trajectory (``t``, ``T_world_cam``, 500 per second), to align
  estimated poses with.

``write_truth(session, truth)`` makes it from a simulated session; ``copy_truth(truth,
session)`` adds its /gt (images back in float32) to a session, e.g. one recorded from the
fixture, so that ``evcap reconstruct`` renders and scores the held-out views
(evcap.recon.evaluate.test_views) and the estimated poses can be compared with the truth. (A
simulated session itself reads as a truth file too.)
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from evcap.errors import InputError, InputNotFoundError, SessionFormatError
from evcap.session import write_group

GT_POSES = ("t", "T_world_cam", "K", "test_T_world_cam")  # kept as they are (float64, int64)
GT_IMAGES = ("test_radiance", "test_depth", "test_normal", "test_base_color", "test_roughness")
GT_OPTIONAL = ("relight_environment", "test_relit_radiance")  # kept where the session has them
TRUTH_VERSION = 1  # of the truth file's layout (root attribute ``truth_version``)
_COMPRESSION = {"compression": "gzip", "compression_opts": 9, "shuffle": True}


def write_truth(session_path: str | Path, truth_path: str | Path) -> None:
    """Write the truth file of a simulated session (its /gt and /poses; see the module)."""
    session_path, truth_path = Path(session_path), Path(truth_path)
    with h5py.File(session_path, "r") as f:
        if "gt" not in f or "poses" not in f:
            raise InputError(f"{session_path} has no /gt and /poses: not a simulated session")
        gt, poses = f["gt"], f["poses"]
        missing = [k for k in GT_POSES + GT_IMAGES if k not in gt]
        if missing:
            raise InputError(
                f"{session_path}: /gt has no {', '.join(missing)} (the scene needs [gt] "
                "test_views > 0)"
            )
        data = {k: gt[k][()] for k in GT_POSES + GT_IMAGES + GT_OPTIONAL if k in gt}
        gt_attrs = dict(gt.attrs)
        trajectory = {k: poses[k][()] for k in ("t", "T_world_cam")}
        pose_attrs = dict(poses.attrs)
    truth_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = truth_path.with_name(truth_path.name + ".tmp")
    with h5py.File(tmp, "w", track_order=True) as out:
        out.attrs["truth_version"] = TRUTH_VERSION
        out.attrs["source"] = session_path.name
        g = out.create_group("gt")
        for key in GT_POSES:
            g.create_dataset(key, data=data[key])
        for key in GT_IMAGES + GT_OPTIONAL:
            if key in data:
                a = data[key].astype(np.float16)
                g.create_dataset(key, data=a, chunks=(1, *a.shape[1:]), **_COMPRESSION)
        for key, value in gt_attrs.items():
            g.attrs[key] = value
        p = out.create_group("poses")
        for key, value in trajectory.items():
            p.create_dataset(key, data=value, **_COMPRESSION)
        for key, value in pose_attrs.items():
            p.attrs[key] = value
    tmp.replace(truth_path)


def read_truth(truth_path: str | Path) -> tuple[dict, dict, dict, dict]:
    """(/gt datasets, /gt attributes, /poses datasets, /poses attributes) of a truth file,
    images as float32."""
    truth_path = Path(truth_path)
    if not truth_path.is_file():
        raise InputNotFoundError(f"no truth file at {truth_path}")
    try:
        f = h5py.File(truth_path, "r")
    except OSError as e:
        raise SessionFormatError(f"{truth_path} is not a truth file: {e}") from None
    with f:
        if "gt" not in f or "poses" not in f:
            raise SessionFormatError(f"{truth_path} is not a truth file (no /gt and /poses)")
        gt = f["gt"]
        missing = [k for k in GT_POSES + GT_IMAGES if k not in gt]
        if missing:
            raise SessionFormatError(f"{truth_path}: /gt has no {', '.join(missing)}")
        data = {k: gt[k][()] for k in GT_POSES}
        data.update({k: gt[k][()].astype(np.float32) for k in GT_IMAGES + GT_OPTIONAL if k in gt})
        poses = {k: f["poses"][k][()] for k in ("t", "T_world_cam")}
        return data, dict(gt.attrs), poses, dict(f["poses"].attrs)


def copy_truth(
    truth_path: str | Path,
    session_path: str | Path,
    *,
    poses: bool = False,
    replace: bool = False,
) -> None:
    """Add the truth file's /gt to a (closed) session; with ``poses``, its simulated trajectory
    as the session's /poses too (replacing what is there: the reconstruction then runs on the
    true poses). ``replace``: replace a /gt the session already has (else SessionFormatError).
    The session must show the same image size as the truth."""
    data, attrs, trajectory, pose_attrs = read_truth(truth_path)
    session_path = Path(session_path)
    if not session_path.is_file():
        raise InputNotFoundError(f"no session at {session_path}")
    with h5py.File(session_path, "r") as f:
        size = (int(f.attrs.get("height", -1)), int(f.attrs.get("width", -1)))
    if data["test_depth"].shape[1:] != size:
        raise InputError(
            f"{truth_path} is the truth of a {data['test_depth'].shape[2]} x "
            f"{data['test_depth'].shape[1]} camera, {session_path} is {size[1]} x {size[0]}"
        )
    attrs["truth_file"] = Path(truth_path).name
    write_group(session_path, "gt", data, attrs, replace=replace)
    if poses:
        write_group(session_path, "poses", trajectory, pose_attrs, replace=True)
