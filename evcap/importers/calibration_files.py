"""Camera calibration files of other tools, in and out: ROS camera_info YAML
(camera_calibration), Kalibr camchain YAML (with the camera-IMU transform and time shift),
VINS-Mono / VINS-Fusion YAML, and iniVation DV's calibration XML (OpenCV FileStorage).

``read_calibration_file`` tells the format by the file's content, takes one camera of a file
that holds several (cam0 unless told), and checks what it reads; ``check_size`` holds it against
a sensor; ``write_calibration_file`` writes one camera in any of the formats. `evcap calibrate
--intrinsics` and `--export` (evcap.calib) and the simulator's `[camera] calibration` read and
write through here.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from evcap.atomic_write import write_text_atomic
from evcap.errors import InputError, InputNotFoundError, OutputExistsError
from evcap.importers import (
    _calibration_dv,
    _calibration_kalibr,
    _calibration_ros,
    _calibration_vins,
)
from evcap.importers.camera_calibration import CameraCalibration, pick_camera

__all__ = [
    "DEFAULT_YAML_FORMAT",
    "FORMATS",
    "CameraCalibration",
    "check_size",
    "export_format",
    "read_calibration_file",
    "render_calibration",
    "write_calibration_file",
]

FORMATS = {
    "kalibr": _calibration_kalibr.FORMAT,
    "ros": _calibration_ros.FORMAT,
    "vins": _calibration_vins.FORMAT,
    "dv": _calibration_dv.FORMAT,
}
YAML_FORMATS = ("kalibr", "ros", "vins")
# Kalibr's camchain: the one YAML format that holds all evcap knows of the camera's geometry (both
# distortion models, the camera-IMU transform and time shift), and what VIO and event tools
# (ESVIO, Ultimate SLAM, e2calib's users) take as their input
DEFAULT_YAML_FORMAT = "kalibr"
EXPECTED = (
    "a ROS camera_info (camera_matrix, distortion_model, ...), a Kalibr camchain (cam0: "
    "intrinsics, distortion_coeffs, resolution, ...), a VINS file (model_type, "
    "projection_parameters, ...) or DV's calibration XML"
)


def read_calibration_file(path: str | Path, camera: str | None = None) -> CameraCalibration:
    """The calibration of one camera in the file at ``path`` (``camera``: its name in the file,
    or cam0, cam1, ... by position; default the first). InputError naming the problem when
    the file is not a calibration evcap reads, holds no such camera, or holds bad numbers."""
    path = Path(path)
    if not path.is_file():
        raise InputNotFoundError(f"{path}: no such file")
    source = path.name
    with path.open("rb") as f:
        head = f.read(256).lstrip()
    if path.suffix.lower() == ".xml" or head.startswith(b"<"):
        cal = _calibration_dv.read(path, source, camera)
    else:
        cal = _from_yaml(path, load_yaml(path), camera)
    return _with_notes(cal)


def check_size(cal: CameraCalibration, width: int, height: int, target: str) -> None:
    """InputError unless ``cal`` is for ``width`` x ``height`` images (the sensor of
    ``target``)."""
    if (cal.width, cal.height) != (width, height):
        raise InputError(
            f"{cal.describe()} is a calibration of {cal.width} x {cal.height} images; the sensor "
            f"of {target} is {width} x {height}: another camera's, or of scaled or cropped images"
        )


def export_format(path: str | Path, fmt: str | None = None) -> str:
    """The format a file at ``path`` is written in: by its extension (.xml: DV's; .yaml/.yml:
    ``fmt``, default Kalibr's camchain)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".xml":
        if fmt not in (None, "dv"):
            raise InputError(
                f"{path}: an .xml file is DV's calibration; --format {fmt} writes .yaml"
            )
        return "dv"
    if suffix in (".yaml", ".yml"):
        if fmt is not None and fmt not in YAML_FORMATS:
            raise InputError(f"--format {fmt}: the YAML formats are {', '.join(YAML_FORMATS)}")
        return fmt or DEFAULT_YAML_FORMAT
    raise InputError(
        f"{path}: write .yaml (Kalibr camchain, ROS camera_info or VINS: --format) or .xml (DV)"
    )


def write_calibration_file(
    cal: CameraCalibration,
    path: str | Path,
    fmt: str | None = None,
    *,
    name: str = "camera",
    overwrite: bool = False,
) -> tuple[str, list[str]]:
    """Write ``cal`` to ``path`` in ``fmt`` (see ``export_format``), the camera named ``name``
    where the format names it. Returns the format and what of ``cal`` the format has no place
    for."""
    fmt = export_format(path, fmt)
    if Path(path).exists() and not overwrite:
        raise OutputExistsError(f"{path} exists: give --force to replace it")
    text, left_out = render_calibration(cal, fmt, name)
    write_text_atomic(path, text)
    return fmt, left_out


def render_calibration(cal: CameraCalibration, fmt: str, name: str) -> tuple[str, list[str]]:
    """``cal`` as the text of a ``fmt`` file, and what of it the format has no place for;
    InputError naming the way out when the format cannot hold it."""
    left_out = []
    if cal.skew != 0 and fmt in ("kalibr", "vins"):
        raise InputError(
            f"the camera matrix has a skew ({cal.skew:g}) that {FORMATS[fmt]} cannot hold: "
            "export it as ROS camera_info (--format ros) or DV's XML (.xml)"
        )
    if cal.T_cam_imu is not None and fmt in ("ros", "dv"):
        left_out.append(
            f"the camera-IMU transform and time shift: {FORMATS[fmt]} has no place for them"
        )
    if fmt == "kalibr":
        text = _calibration_kalibr.write(cal)
    elif fmt == "ros":
        text = _calibration_ros.write(cal, name)
    elif fmt == "vins":
        text = _calibration_vins.write(cal, name)
    else:
        text = _calibration_dv.write(cal, name)
    return text, left_out


def load_yaml(path: Path) -> object:
    """A YAML file as Python values: OpenCV's YAML too (its `%YAML:1.0` directive dropped, its
    `!!opencv-matrix` read as a mapping of rows, cols, dt and data)."""
    import yaml

    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{path.name} is not a text file: not a calibration evcap reads") from None
    if text.lstrip().startswith("%YAML"):  # OpenCV's directive (`%YAML:1.0`) is not YAML's
        text = text.lstrip().split("\n", 1)[1] if "\n" in text.lstrip() else ""
    loader = type("Loader", (yaml.SafeLoader,), {})
    loader.add_constructor(
        "tag:yaml.org,2002:opencv-matrix", lambda ld, node: ld.construct_mapping(node, deep=True)
    )
    try:
        return yaml.load(text, Loader=loader)  # noqa: S506 (a SafeLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise InputError(
            f"{path.name} is not YAML evcap can read ({problem}{where}); expected {EXPECTED}"
        ) from None


def _from_yaml(path: Path, doc: object, camera: str | None) -> CameraCalibration:
    source = path.name
    if not isinstance(doc, dict):
        raise InputError(f"{source} is not a camera calibration: expected {EXPECTED}")
    if _calibration_kalibr.camera_names(doc):
        return _calibration_kalibr.read(doc, source, camera)
    if "camera_matrix" in doc:
        return _calibration_ros.read(doc, source, camera)
    if _calibration_vins.is_camera(doc):
        return _calibration_vins.read(doc, source, camera)
    if _calibration_vins.calibration_files(doc):
        return _vins_fusion(path, doc, camera)
    imus = _calibration_kalibr.imu_names(doc)
    if imus:
        raise InputError(
            f"{source} is a Kalibr IMU calibration ({', '.join(imus)}: the IMU's noise), with no "
            "camera in it: give the camchain Kalibr wrote beside it (...-camchain-imucam.yaml)"
        )
    keys = ", ".join(str(k) for k in list(doc)[:8])
    raise InputError(f"{source} is not a camera calibration: expected {EXPECTED}; it has {keys}")


def _vins_fusion(path: Path, doc: dict, camera: str | None) -> CameraCalibration:
    """A VINS-Fusion configuration: the camera's intrinsics in the file its camN_calib names
    (beside it), the camera-IMU transform (body_T_camN) and td in the configuration."""
    keys = _calibration_vins.calibration_files(doc)
    names = [k.removesuffix("_calib") for k in keys]
    name = pick_camera(names, camera, path.name, "VINS-Fusion configuration")
    index = names.index(name)
    camera_file = path.parent / str(doc[keys[index]])
    if not camera_file.is_file():
        raise InputNotFoundError(
            f"{path.name}: {keys[index]} names {doc[keys[index]]}, not found (looked at "
            f"{camera_file})"
        )
    camera_doc = load_yaml(camera_file)
    if not isinstance(camera_doc, dict) or not _calibration_vins.is_camera(camera_doc):
        raise InputError(f"{camera_file.name} (named by {path.name}) is not a VINS camera file")
    cal = _calibration_vins.read(camera_doc, camera_file.name, None, doc, index)
    return dataclasses.replace(
        cal, camera=name, cameras=tuple(names), source=f"{path.name} + {camera_file.name}"
    )


def _with_notes(cal: CameraCalibration) -> CameraCalibration:
    """``cal`` with a warning where its principal point lies outside the image."""
    cx, cy = cal.K[0, 2], cal.K[1, 2]
    if 0 <= cx <= cal.width - 1 and 0 <= cy <= cal.height - 1:
        return cal
    note = (
        f"the principal point ({cx:.1f}, {cy:.1f}) lies outside the {cal.width} x {cal.height} "
        "image"
    )
    return dataclasses.replace(cal, warnings=(*cal.warnings, note))
