"""Events from a posed image sequence (ESIM/v2e style): `evcap simulate --from-images`.

Reads the NeRF-Synthetic layout: a transforms JSON (camera_angle_x, or fl_x/fl_y/cx/cy; frames
with file_path and a camera-to-world transform_matrix in Blender/OpenGL axes) and its images.
The frames, in their order, are the camera's path, one every 1/fps seconds.

Where two consecutive images are too far apart for the threshold model (a point moves more
than ``max_step_px`` pixels), frames are interpolated between them: dense optical flow (OpenCV's
DIS, both ways, on the images' luminance), then for each intermediate time a in (0, 1) the
pixel x takes (1 - a) * A(x - a * F_ab(x)) + a * B(x - (1 - a) * F_ba(x)): both images warped
back along straight-line motion and blended (in linear radiance). Poses in between are
interpolated (position linearly, rotation by slerp). The pixel model then runs on the frames as
its samples (evcap.sim.events), so all the sensor effects apply.

Held-out views: with transforms_train.json, the images of transforms_test.json beside it;
otherwise every 8th image of the sequence (which is then not used for the events).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evcap.errors import InputError, InputNotFoundError
from evcap.events import Events
from evcap.session import SensorInfo, SessionWriter, write_group
from evcap.sim.events import PixelArray
from evcap.sim.lighting import srgb_to_linear
from evcap.sim.sensor import ChannelMap
from evcap.sim.simulate import EPOCH_US

BLENDER_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class PosedImages:
    images: list[Path]
    poses: np.ndarray  # [N, 4, 4] camera-to-world, OpenCV axes
    K: np.ndarray


def read_transforms(path: Path, scale: float = 1.0) -> PosedImages:
    if not path.is_file():
        raise InputNotFoundError(f"{path}: no such transforms file")
    try:
        doc = json.loads(path.read_text())
        frames = doc["frames"]
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise InputError(f"{path}: not a NeRF-style transforms file ({e})") from None
    images, poses = [], []
    for i, f in enumerate(frames):
        name = path.parent / f["file_path"]
        if not name.suffix:
            name = name.with_suffix(".png")
        if not name.exists():
            raise InputNotFoundError(f"{path}: frame {i}: image {name} not found")
        images.append(name)
        m = np.asarray(f["transform_matrix"], np.float64)
        if m.shape != (4, 4):
            raise InputError(f"{path}: frame {i}: transform_matrix must be 4 x 4")
        poses.append(m @ BLENDER_TO_OPENCV)
    if len(images) < 2:
        raise InputError(f"{path}: needs at least two frames")
    h, w = _read(images[0], scale).shape[:2]
    if "fl_x" in doc:
        fx, fy = doc["fl_x"] * scale, doc.get("fl_y", doc["fl_x"]) * scale
        cx, cy = (
            doc.get("cx", (w - 1) / 2 / scale) * scale,
            doc.get("cy", (h - 1) / 2 / scale) * scale,
        )
    elif "camera_angle_x" in doc:
        fx = fy = 0.5 * w / np.tan(0.5 * float(doc["camera_angle_x"]))
        cx, cy = (w - 1) / 2, (h - 1) / 2
    else:
        raise InputError(f"{path}: needs camera_angle_x or fl_x")
    return PosedImages(images, np.array(poses), np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]))


def _image(path: Path, scale: float) -> np.ndarray:
    """An image file as stored (BGR or BGRA or gray), scaled to [0, 1]."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{path}: cannot read the image")
    if scale != 1.0:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return img.astype(np.float64) / (65535.0 if img.dtype == np.uint16 else 255.0)


def _read(path: Path, scale: float, background: float = 1.0) -> np.ndarray:
    """An image as linear RGB (RGBA composited on a gray level ``background``)."""
    img = _image(path, scale)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    rgb = srgb_to_linear(img[..., 2::-1] if img.shape[2] >= 3 else img)
    if img.shape[2] == 4:
        alpha = img[..., 3:4]
        rgb = rgb * alpha + background * (1 - alpha)
    return rgb


def _maps(images: list[Path], scale: float) -> dict[str, np.ndarray]:
    """The dataset's own depth and normal images (NeRF-Synthetic names them
    ``r_7_depth_0000.png``, ``r_7_normal_0000.png``), when every image has one; values in
    [0, 1] exactly as stored (NeRF-Synthetic depth is not metric)."""
    out = {}
    for kind in ("depth", "normal"):
        names = [p.with_name(f"{p.stem}_{kind}_0000.png") for p in images]
        if not names or not all(n.exists() for n in names):
            continue
        maps = []
        for n in names:
            img = _image(n, scale).astype(np.float32)
            if kind == "depth":
                maps.append(img[..., 0] if img.ndim == 3 else img)
            else:
                maps.append(img[..., 2::-1] if img.ndim == 3 else np.repeat(img[..., None], 3, 2))
        out[f"{kind}_image"] = np.stack(maps)
    return out


def _flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    import cv2

    def gray(x):
        return np.clip(np.sqrt(x @ [0.2126, 0.7152, 0.0722]) * 255, 0, 255).astype(np.uint8)

    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(gray(a), gray(b), None)


def _warp(img: np.ndarray, flow: np.ndarray, amount: float) -> np.ndarray:
    """img sampled at x - amount * flow(x)."""
    import cv2

    h, w = img.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    return cv2.remap(
        img.astype(np.float32),
        xx - amount * flow[..., 0],
        yy - amount * flow[..., 1],
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )


def interpolate(a: np.ndarray, b: np.ndarray, max_step_px: float) -> list[tuple[float, np.ndarray]]:
    """Intermediate frames (fraction, image) between images a and b, enough that no pixel
    moves more than max_step_px between consecutive ones."""
    f_ab, f_ba = _flow(a, b), _flow(b, a)
    motion = float(np.percentile(np.linalg.norm(f_ab, axis=2), 99.9))
    n = int(np.ceil(motion / max_step_px)) - 1
    out = []
    for k in range(1, n + 1):
        s = k / (n + 1)
        frame = (1 - s) * _warp(a, f_ab, s) + s * _warp(b, f_ba, 1 - s)
        out.append((s, frame.astype(np.float64)))
    return out


def simulate_from_images(
    transforms: str | Path,
    output: str | Path,
    *,
    fps: float = 30.0,
    color_filter: str = "RGBG",
    threshold: float = 0.2,
    effects: dict | None = None,
    scale: float = 1.0,
    max_step_px: float = 1.0,
    dark_level: float = 1e-3,
    test_views: int = 8,
    seed: int = 0,
    overwrite: bool = False,
    progress: Callable[[float, float], None] | None = None,
) -> int:
    """Events from the posed images into the session ``output``; returns the event count."""
    transforms, output = Path(transforms), Path(output)
    if output.exists() and not overwrite:
        raise InputError(f"{output} exists; choose another name or pass --force")
    data = read_transforms(transforms, scale)
    test = None
    sibling = transforms.with_name("transforms_test.json")
    if transforms.name == "transforms_train.json" and sibling.exists():
        test = read_transforms(sibling, scale)
        test = PosedImages(test.images[:test_views], test.poses[:test_views], test.K)
        keep = np.arange(len(data.images))
    else:
        held = np.arange(len(data.images)) % 8 == 7
        if test_views > 0 and held.any():
            test = PosedImages(
                [p for p, h in zip(data.images, held, strict=True) if h],
                data.poses[held][:test_views],
                data.K,
            )
            test.images = test.images[:test_views]
        keep = np.flatnonzero(~held) if test_views > 0 else np.arange(len(data.images))
    images = [data.images[i] for i in keep]
    poses = data.poses[keep]
    first = _read(images[0], scale)
    h, w = first.shape[:2]
    rng = np.random.default_rng(seed)
    channels = ChannelMap(w, h, color_filter)
    pixels = PixelArray(w * h, threshold, threshold, effects or {}, rng)
    sensor = SensorInfo("simulated", w, h, color_filter, "SIM-images", EPOCH_US)
    n_events = 0
    gt_t = []
    gt_radiance = []
    with SessionWriter(
        output, sensor, attrs={"source_file": str(transforms)}, overwrite=overwrite
    ) as writer:
        prev = first
        pixels.start(channels.log(prev.reshape(-1, 3), dark_level), 0.0)
        gt_t.append(0)
        gt_radiance.append(prev.astype(np.float32))
        period = 1e6 / fps
        for k in range(1, len(images)):
            cur = _read(images[k], scale)
            t0, t1 = (k - 1) * period, k * period
            frames = [(0.0, prev)] + interpolate(prev, cur, max_step_px) + [(1.0, cur)]
            times = np.array([t0 + s * (t1 - t0) for s, _ in frames])
            values = np.stack([channels.log(f.reshape(-1, 3), dark_level) for _, f in frames], 1)
            n_pix = w * h
            offsets = np.arange(n_pix + 1) * len(frames)
            et, epx, ep = pixels.events(
                np.tile(times, n_pix), values.ravel(), offsets, np.arange(n_pix)
            )
            nt, npx, np_ = pixels.noise(t0, t1)
            et, epx, ep = pixels.degrade(
                np.concatenate([et, nt]), np.concatenate([epx, npx]), np.concatenate([ep, np_])
            )
            order = np.argsort(et, kind="stable")
            et = np.clip(np.floor(et[order]), t0, t1 - 1).astype(np.int64)
            writer.append_events(
                Events(epx[order] % w, epx[order] // w, et, ep[order], w, h, color_filter)
            )
            n_events += len(et)
            gt_t.append(int(round(t1)))
            gt_radiance.append(cur.astype(np.float32))
            prev = cur
            if progress:
                progress(k, len(images) - 1)
    datasets = {
        "t": np.array(gt_t, np.int64),
        "radiance": np.stack(gt_radiance),
        "T_world_cam": poses,
        "K": data.K,
        "threshold_on": pixels.con.reshape(h, w).astype(np.float32),
        "threshold_off": pixels.coff.reshape(h, w).astype(np.float32),
        **_maps(images, scale),
    }
    if test is not None and len(test.images):
        datasets["test_T_world_cam"] = test.poses
        datasets["test_radiance"] = np.stack(
            [_read(p, scale).astype(np.float32) for p in test.images]
        )
        datasets.update({f"test_{k}": v for k, v in _maps(test.images, scale).items()})
    write_group(
        output,
        "gt",
        datasets,
        {
            "source": "evcap simulate --from-images",
            "images": str(transforms),
            "radiance": "linear RGB from the sRGB images",
            "depth_image": "the dataset's depth images in [0, 1], as stored (not metric)",
            "normal_image": "the dataset's normal images, RGB in [0, 1], as stored",
        },
    )
    write_group(
        output,
        "poses",
        {"t": np.array(gt_t, np.int64), "T_world_cam": poses},
        {
            "source": "ground truth",
            "frame": "camera-to-world, OpenCV camera axes",
            "interpolation": "linear position, slerp rotation",
        },
    )
    write_group(
        output,
        "calibration",
        {
            "K": data.K,
            "dist": np.zeros(0),
            "threshold_on": datasets["threshold_on"],
            "threshold_off": datasets["threshold_off"],
            "hot_pixels": np.zeros((h, w), np.uint8),
        },
        {
            "source": "ground truth",
            "distortion_model": "none",
            "width": w,
            "height": h,
            "rms_reprojection_px": 0.0,
        },
    )
    return n_events
