"""/poses: the camera's trajectory (docs/session-format.md), a timestamped track interpolated at
any time (position linearly, rotation by slerp). ``Poses`` is the one reader and writer of the
group: `evcap poses`, the simulator and the demo write it; the reconstruction, the report and
the benches read it. Times are int64 microseconds; only the fraction between two poses is a
float, so that long recordings keep their precision."""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field

import h5py
import numpy as np

from evcap.errors import InputError
from evcap.hdf5_attributes import read_attributes
from evcap.records._group import Source, array, find_group, optional, path_of, where
from evcap.rotations import quat_to_rotmat, rotmat_to_quat, slerp
from evcap.session import write_group

GROUP = "poses"
FRAME = "camera-to-world, OpenCV camera axes"
INTERPOLATION = "linear position, slerp rotation"


@dataclass
class Poses:
    """Camera-to-world transforms at increasing times, and where they came from."""

    t: np.ndarray  # [N] int64 microseconds, increasing
    T_world_cam: np.ndarray  # [N, 4, 4] camera-to-world, OpenCV camera axes
    source: str = "unknown"  # "ground truth", "evcap poses (...)"
    scale: str = "scene units"  # or "arbitrary (...)": structure from motion has none
    points_xyz: np.ndarray | None = None  # [P, 3] the scene points they were found with
    notes: dict = field(default_factory=dict)  # more attributes: how they were found

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, np.int64)
        self.T_world_cam = np.asarray(self.T_world_cam, np.float64)
        if self.T_world_cam.shape != (len(self.t), 4, 4):
            raise InputError(
                f"poses: {len(self.t)} times but transforms of shape {self.T_world_cam.shape}"
            )
        if len(self.t) < 2:
            raise InputError("poses: at least two timestamped poses are needed")
        if np.any(np.diff(self.t) <= 0):
            raise InputError("poses: times must increase")
        if not np.isfinite(self.T_world_cam).all():
            raise InputError("poses: transforms hold NaN or infinity")
        self._q = rotmat_to_quat(self.T_world_cam[:, :3, :3])

    @property
    def arbitrary_scale(self) -> bool:
        return self.scale.startswith("arbitrary")

    def replace(self, **changes) -> Poses:
        """A copy with some fields changed (``notes`` updated, not replaced)."""
        notes = {**self.notes, **changes.pop("notes", {})}
        return dataclasses.replace(self, notes=notes, **changes)

    # -- reading -----------------------------------------------------------------------------

    @staticmethod
    def present(source: Source) -> bool:
        return find_group(source, GROUP) is not None

    @classmethod
    def read(cls, source: Source) -> Poses:
        """The trajectory of ``source``; InputError naming what to run when it has none."""
        g = find_group(source, GROUP)
        if g is None:
            raise InputError(
                f"{path_of(source)} has no camera poses (/{GROUP}); run `evcap poses` on it first"
            )
        place = where(source, GROUP)
        a = read_attributes(g)
        for key in ("frame", "interpolation"):
            a.pop(key, None)
        try:
            return cls(
                array(g, "t", place, np.int64, (None,)),
                array(g, "T_world_cam", place, np.float64, (None, 4, 4)),
                source=str(a.pop("source", "unknown")),
                scale=str(a.pop("scale", "scene units")),
                points_xyz=optional(g, "points_xyz", place, np.float64, (None, 3)),
                notes=a,
            )
        except KeyError as e:
            raise InputError(f"{place} has no dataset {e}") from None
        except InputError as e:
            raise InputError(f"{place}: {e}") from None

    @classmethod
    def read_file(cls, path: str | os.PathLike) -> Poses:
        """The /poses of the HDF5 file at ``path``: a session's, or a trajectory's own file."""
        try:
            f = h5py.File(path, "r")
        except OSError as e:
            raise InputError(f"{path}: not a readable HDF5 file ({e})") from None
        with f:
            return cls.read(f)

    # -- writing -----------------------------------------------------------------------------

    def write_file(self, path: str | os.PathLike) -> None:
        """Store as the /poses of a new HDF5 file of its own at ``path`` (replaced if there)."""
        h5py.File(path, "w").close()
        self.write(path)

    def write(self, path: str | os.PathLike, *, replace: bool = True) -> None:
        """Store as the /poses of the (closed) session, or other HDF5 file, at ``path``."""
        data = {"t": self.t, "T_world_cam": self.T_world_cam}
        if self.points_xyz is not None:
            data["points_xyz"] = np.asarray(self.points_xyz, np.float64)
        attrs = {
            **self.notes,
            "source": self.source,
            "scale": self.scale,
            "frame": FRAME,
            "interpolation": INTERPOLATION,
        }
        write_group(path, GROUP, data, attrs, replace=replace)

    # -- the track ---------------------------------------------------------------------------

    @property
    def start(self) -> int:
        return int(self.t[0])

    @property
    def end(self) -> int:
        return int(self.t[-1])

    def at(self, t_us: np.ndarray | int) -> np.ndarray:
        """Camera-to-world transforms [..., 4, 4] at the given times (inside the track)."""
        t_us = np.asarray(t_us, np.int64)
        if np.any(t_us < self.t[0]) or np.any(t_us > self.t[-1]):
            raise InputError(
                f"poses cover {self.t[0]}..{self.t[-1]} us; asked for a time outside them"
            )
        i = np.clip(np.searchsorted(self.t, t_us, side="right") - 1, 0, len(self.t) - 2)
        s = (t_us - self.t[i]).astype(np.float64) / (self.t[i + 1] - self.t[i]).astype(np.float64)
        out = np.zeros(t_us.shape + (4, 4))
        out[..., 3, 3] = 1
        p0, p1 = self.T_world_cam[i, :3, 3], self.T_world_cam[i + 1, :3, 3]
        out[..., :3, 3] = p0 + s[..., None] * (p1 - p0)
        out[..., :3, :3] = quat_to_rotmat(slerp(self._q[i], self._q[i + 1], s))
        return out
