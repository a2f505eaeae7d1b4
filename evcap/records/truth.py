"""/gt: the truth a simulator rendered, or a dataset's renders (docs/session-format.md).
``GroundTruth`` is the one reader and writer of the group: the simulator and the truth files
write it, the evaluation, the report and the benches read it."""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field

import numpy as np

from evcap.errors import InputError
from evcap.hdf5_attributes import read_attributes
from evcap.records._group import Source, array, find_group, optional, path_of, where
from evcap.records.poses import Poses
from evcap.session import write_group

GROUP = "gt"
HELD_OUT = "test_"  # the held-out views' datasets: test_T_world_cam, test_radiance, ...
MAP_NOTES = {
    "radiance": "linear RGB, before the color filter",
    "depth": "z in the camera frame (OpenCV axes); 0 where no surface",
    "normal": "unit, in the camera frame (OpenCV axes: x right, y down, z forward); 0 where no "
    "surface",
    "base_color": "linear RGB albedo; 0 where no surface",
    "roughness": "GGX roughness; 0 where no surface",
    "visibility": "direct irradiance received / direct irradiance if nothing blocked (environment"
    " without the bounce, sun, point lights): the shadow factor, 1 unshadowed; 0 where no surface",
    "indirect": "linear RGB radiance added by one bounce of diffuse light (color bleeding):"
    " base_color / pi * bounced irradiance; 0 without lighting.indirect or surface",
    "mask": "the object's pixels",
    "relit_radiance": "the held-out views under relight_environment instead",
}
ENVIRONMENT_NOTE = (
    "linear RGB radiance on a latitude-longitude grid of world directions (z up, azimuth from "
    "+x, top row the zenith): the second light"
)


@dataclass
class TruthViews:
    """The truth at a set of camera poses: whichever maps the source has (None otherwise), each
    with one item per view."""

    T_world_cam: np.ndarray  # [N, 4, 4] camera-to-world, OpenCV axes
    radiance: np.ndarray | None = None  # [N, H, W, 3] float32 linear RGB
    depth: np.ndarray | None = None  # [N, H, W] camera z; 0 where no surface
    normal: np.ndarray | None = None  # [N, H, W, 3] unit, camera axes; 0 where no surface
    base_color: np.ndarray | None = None  # [N, H, W, 3]
    roughness: np.ndarray | None = None  # [N, H, W]
    visibility: np.ndarray | None = None  # [N, H, W] shadow factor, 1 unshadowed
    indirect: np.ndarray | None = None  # [N, H, W, 3] radiance from one diffuse bounce
    mask: np.ndarray | None = None  # [N, H, W] bool: the object's pixels (images with alpha)
    relit_radiance: np.ndarray | None = None  # [N, H, W, 3] under the second light

    def __post_init__(self) -> None:
        self.T_world_cam = np.asarray(self.T_world_cam, np.float64).reshape(-1, 4, 4)
        for name, value in self.maps().items():
            if len(value) != len(self.T_world_cam):
                raise InputError(
                    f"truth: {len(value)} {name} images for {len(self.T_world_cam)} views"
                )

    def __len__(self) -> int:
        return len(self.T_world_cam)

    def maps(self) -> dict[str, np.ndarray]:
        """The maps it has, by name."""
        names = [f.name for f in dataclasses.fields(self) if f.name != "T_world_cam"]
        return {n: getattr(self, n) for n in names if getattr(self, n) is not None}

    def __getitem__(self, index: slice | np.ndarray) -> TruthViews:
        return TruthViews(self.T_world_cam[index], **{k: v[index] for k, v in self.maps().items()})

    def without(self, *names: str) -> TruthViews:
        return dataclasses.replace(self, **{n: None for n in names})

    def object_mask(self) -> np.ndarray | None:
        """The object's pixels: the mask (images with alpha), else where the depth has a
        surface; None when it has neither."""
        if self.mask is not None:
            return self.mask.astype(bool)
        return self.depth > 0 if self.depth is not None else None


@dataclass
class GroundTruth:
    """The truth of a session: views along the camera path and held-out views."""

    source: str  # "evcap simulate", "evcap simulate --from-images"
    t: np.ndarray  # [N] int64 us: the times of the views along the path
    path: TruthViews  # read without its maps unless asked for (they are large)
    held_out: TruthViews | None = None
    K: np.ndarray | None = None  # 3 x 3
    distortion_model: str = "none"
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(0))
    threshold_on: np.ndarray | None = None  # [H, W] the thresholds the events were made with
    threshold_off: np.ndarray | None = None
    relight_environment: np.ndarray | None = None  # [h, 2h, 3] the held-out views' second light
    renderer_version: int = 1  # of the simulator's renderer that made it
    hot_pixels: np.ndarray | None = None  # flat indices of the hot pixels simulated
    notes: dict = field(default_factory=dict)  # more attributes: scene, seed, boards...

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, np.int64)
        if len(self.t) != len(self.path):
            raise InputError(f"truth: {len(self.t)} times for {len(self.path)} views on the path")

    def poses(self) -> Poses:
        """The path's views as a trajectory."""
        return Poses(self.t, self.path.T_world_cam, source="ground truth")

    def held_out_views(self) -> TruthViews:
        """The held-out views (none when the source has none)."""
        return self.held_out if self.held_out is not None else TruthViews(np.zeros((0, 4, 4)))

    # -- reading -----------------------------------------------------------------------------

    @staticmethod
    def present(source: Source) -> bool:
        return find_group(source, GROUP) is not None

    @classmethod
    def read(cls, source: Source, *, along_path: bool = False) -> GroundTruth:
        """The truth of ``source`` (images as float32); the maps along the path only with
        ``along_path``. InputError when it has none."""
        g = find_group(source, GROUP)
        if g is None:
            raise InputError(
                f"{path_of(source)} has no ground truth (/{GROUP}): only simulated sessions, or "
                "sessions given a truth file, have one"
            )
        place = where(source, GROUP)
        try:
            path = _views(g, "", place, along_path)
            held_out = _views(g, HELD_OUT, place, True) if f"{HELD_OUT}T_world_cam" in g else None
            a = read_attributes(g)
            hot = a.pop("hot_pixels", None)
            for name in (*MAP_NOTES, "relight_environment"):
                a.pop(name, None)
            return cls(
                source=str(a.pop("source", "unknown")),
                t=array(g, "t", place, np.int64, (None,)),
                path=path,
                held_out=held_out,
                K=optional(g, "K", place, shape=(3, 3)),
                distortion_model=str(a.pop("distortion_model", "none")),
                distortion=np.asarray(a.pop("distortion", np.zeros(0)), np.float64).ravel(),
                threshold_on=optional(g, "threshold_on", place, np.float32, (None, None)),
                threshold_off=optional(g, "threshold_off", place, np.float32, (None, None)),
                relight_environment=optional(
                    g, "relight_environment", place, np.float32, (None, None, 3)
                ),
                renderer_version=int(a.pop("renderer_version", 1)),
                hot_pixels=None if hot is None else np.asarray(hot, np.int64).ravel(),
                notes=a,
            )
        except KeyError as e:
            raise InputError(f"{place} has no dataset {e}") from None

    # -- writing -----------------------------------------------------------------------------

    def write(self, path: str | os.PathLike, *, replace: bool = False, half: bool = False) -> None:
        """Store as the /gt of the (closed) session, or other HDF5 file, at ``path``; with
        ``half``, the images in float16 (a truth file, small)."""
        data: dict[str, np.ndarray] = {"t": self.t, "T_world_cam": self.path.T_world_cam}
        for name, value in self.path.maps().items():
            data[name] = _image(value, half)
        if self.held_out is not None:
            data[f"{HELD_OUT}T_world_cam"] = self.held_out.T_world_cam
            for name, value in self.held_out.maps().items():
                data[f"{HELD_OUT}{name}"] = _image(value, half)
        for name in ("K", "threshold_on", "threshold_off"):
            if getattr(self, name) is not None:
                data[name] = getattr(self, name)
        attrs = {
            **self.notes,
            "source": self.source,
            "renderer_version": self.renderer_version,
            "distortion_model": self.distortion_model,
            "distortion": self.distortion,
        }
        if self.relight_environment is not None:
            data["relight_environment"] = _image(self.relight_environment, half)
            attrs["relight_environment"] = ENVIRONMENT_NOTE
        if self.hot_pixels is not None:
            attrs["hot_pixels"] = np.asarray(self.hot_pixels, np.int64)
        names = set(self.path.maps()) | set(self.held_out.maps() if self.held_out else ())
        attrs.update({n: MAP_NOTES[n] for n in sorted(names)})
        write_group(path, GROUP, data, attrs, replace=replace, compression_level=9 if half else 4)


def _views(g, prefix: str, place: str, maps: bool) -> TruthViews:
    T = array(g, f"{prefix}T_world_cam", place, np.float64, (None, 4, 4))
    if not maps:
        return TruthViews(T)
    found = {}
    for name in MAP_NOTES:
        if f"{prefix}{name}" in g:
            dtype = bool if name == "mask" else np.float32
            found[name] = array(g, f"{prefix}{name}", place, dtype)
    try:
        return TruthViews(T, **found)
    except InputError as e:
        raise InputError(f"{place}: {e}") from None


def _image(a: np.ndarray, half: bool) -> np.ndarray:
    if a.dtype == bool:
        return a
    return np.asarray(a, np.float16 if half else np.float32)
