"""Writing the Event-Camera Dataset's text layout, for the tests of evcap.importers.event_text:
from arrays (the round trips) and from a session (the must-show: a simulated recording made an
ECD sequence)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evcap.records import Calibration, Poses
from evcap.rotations import rotmat_to_quat
from evcap.session import Session


def seconds(t_us: np.ndarray) -> list[str]:
    """Microseconds as ECD's decimal seconds, exactly (6 decimals)."""
    s, us = np.divmod(np.asarray(t_us, np.int64), 1_000_000)
    return [f"{a}.{b:06d}" for a, b in zip(s.tolist(), us.tolist(), strict=True)]


def write_events(path: Path, t_us, x, y, p) -> None:
    lines = [
        f"{t} {a} {b} {c}\n"
        for t, a, b, c in zip(seconds(t_us), list(x), list(y), list(p), strict=True)
    ]
    path.write_text("".join(lines))


def write_rows(path: Path, t_us, values: np.ndarray) -> None:
    """``t v1 v2 ...`` lines, the values written so that they read back exactly (repr)."""
    path.write_text(
        "".join(
            " ".join([t, *(repr(float(v)) for v in row)]) + "\n"
            for t, row in zip(seconds(t_us), np.asarray(values), strict=True)
        )
    )


def write_calib(path: Path, K: np.ndarray, dist: np.ndarray) -> None:
    k = np.zeros(5)
    k[: len(dist)] = dist
    values = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *k]
    path.write_text(" ".join(repr(float(v)) for v in values) + "\n")


def write_groundtruth(path: Path, t_us, T_world_cam: np.ndarray) -> None:
    q = rotmat_to_quat(T_world_cam[:, :3, :3])  # (w, x, y, z)
    write_rows(path, t_us, np.concatenate([T_world_cam[:, :3, 3], q[:, [1, 2, 3, 0]]], axis=1))


def export_session(session: Path, folder: Path) -> None:
    """The session's events, calibration and poses as an ECD sequence (absolute times: t +
    t_offset_us), without its frames or IMU samples."""
    folder.mkdir(parents=True, exist_ok=True)
    with Session.open(session) as s:
        offset = s.sensor.t_offset_us
        ev = s.events()
        write_events(folder / "events.txt", ev.t + offset, ev.x, ev.y, ev.p)
        K, _, dist = Calibration.read(s).intrinsics()
        write_calib(folder / "calib.txt", K, dist)
        poses = Poses.read(s)
        write_groundtruth(folder / "groundtruth.txt", poses.t + offset, poses.T_world_cam)
