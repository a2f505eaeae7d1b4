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
its samples (evcap.sim.events), so all the sensor effects apply but the footprint: the images
already hold each pixel's area (rendered with a pixel filter, or scaled down by area), and the
warped frames carry it along.

Held-out views: those of a second transforms file (``held_out``), never used for events;
otherwise every 8th image of the sequence (which is then not used for the events).

Truth: the images' alpha is the object's mask; depth comes from the dataset's depth renders
(NeRF-Synthetic's encoding, see decode_depth), normals from that depth (the release's normal
renders hold the world normal clipped to [0, 1] through a tone curve: its negative components
are lost). Held-out views without depth renders get both drawn in from the path's views
(splat_truth).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evcap.errors import InputError, InputNotFoundError
from evcap.events import Events
from evcap.images import srgb_to_linear
from evcap.records import GroundTruth, Poses, TruthViews
from evcap.session import SensorInfo, SessionWriter
from evcap.sim.events import PixelArray
from evcap.sim.sensor import ChannelMap, true_calibration
from evcap.sim.sensor_profiles import SensorProfile, sensor_profile
from evcap.sim.simulate import EPOCH_US

BLENDER_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
DEPTH_RANGE_M = 8.0  # NeRF-Synthetic's depth renders: v = 1 - distance / 8
DEPTH_STEP_M = DEPTH_RANGE_M / 255  # their 8-bit quantization


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
    h, w = _read(images[0], scale)[0].shape[:2]
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


def _read(
    path: Path, scale: float, background: float = 1.0
) -> tuple[np.ndarray, np.ndarray | None]:
    """An image as linear RGB, RGBA composited over a gray level ``background`` (linear);
    and its alpha (None without one)."""
    img = _image(path, scale)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    rgb = srgb_to_linear(img[..., 2::-1] if img.shape[2] >= 3 else img)
    if img.shape[2] != 4:
        return rgb, None
    alpha = img[..., 3]
    return rgb * alpha[..., None] + background * (1 - alpha[..., None]), alpha


def depth_render(image: Path) -> Path | None:
    """The dataset's depth render of an image (NeRF-Synthetic: ``r_7_depth_0186.png`` beside
    ``r_7.png``), if there is one."""
    found = sorted(image.parent.glob(f"{image.stem}_depth_*.png"))
    return found[0] if found else None


def rays(K: np.ndarray, h: int, w: int) -> np.ndarray:
    """[H, W, 3] camera-frame directions with z = 1."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([(xx - K[0, 2]) / K[0, 0], (yy - K[1, 2]) / K[1, 1], np.ones_like(xx)], -1)


def decode_depth(path: Path, scale: float, K: np.ndarray) -> np.ndarray:
    """A depth render as camera z [H, W] (0 where it has no surface). NeRF-Synthetic's 8-bit
    renders hold v = 1 - distance / DEPTH_RANGE_M, the distance along the ray from the camera
    centre, 0 where nothing was hit (docs/reconstruction.md says how this was established).
    Scaled down, the distance is averaged over the pixels that have a surface."""
    import cv2

    v = _image(path, 1.0)
    v = v[..., 0] if v.ndim == 3 else v
    hit = (v > 0).astype(np.float64)
    distance = DEPTH_RANGE_M * (1.0 - v) * hit
    if scale != 1.0:
        size = (round(v.shape[1] * scale), round(v.shape[0] * scale))
        area = cv2.resize(hit, size, interpolation=cv2.INTER_AREA)
        distance = cv2.resize(distance, size, interpolation=cv2.INTER_AREA)
        hit = area > 0.99  # no pixel straddles the silhouette
        distance = np.where(hit, distance / np.maximum(area, 1e-9), 0.0)
    r = rays(K, *distance.shape)
    return (distance / np.linalg.norm(r, axis=-1)).astype(np.float32)


def normals_from_depth(
    z: np.ndarray, K: np.ndarray, step: int = 2, smooth_px: float = 1.5
) -> np.ndarray:
    """Camera-frame unit normals [H, W, 3] of a depth map, from central differences over
    ``step`` pixels of its back-projected points, facing the camera; 0 within ``step`` pixels
    of the silhouette and where the surface is not smooth (a depth step between parts). The
    depth is first smoothed over ``smooth_px`` (a Gaussian within the surface, left out across
    steps of more than 3 %): 8-bit depth is a staircase."""
    import cv2

    surface = z > 0
    hit = surface.astype(np.float32)
    blur = cv2.GaussianBlur((z * hit).astype(np.float32), (0, 0), smooth_px)
    blur /= np.maximum(cv2.GaussianBlur(hit, (0, 0), smooth_px), 1e-6)
    z = np.where(np.abs(blur - z) < 0.03 * z, blur, z) * hit
    p = rays(K, *z.shape) * z[..., None]
    dx = np.roll(p, -step, 1) - np.roll(p, step, 1)
    dy = np.roll(p, -step, 0) - np.roll(p, step, 0)
    n = np.cross(dx, dy)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    n *= -np.sign((n * p).sum(-1, keepdims=True))
    # One-sided differences that disagree by more than 3x: a fold or a step, not a surface.
    fwd = np.linalg.norm(np.roll(p, -step, 1) - p, axis=-1) + np.linalg.norm(
        np.roll(p, -step, 0) - p, axis=-1
    )
    back = np.linalg.norm(p - np.roll(p, step, 1), axis=-1) + np.linalg.norm(
        p - np.roll(p, step, 0), axis=-1
    )
    smooth = np.maximum(fwd, back) < 3 * np.minimum(fwd, back) + 4 * DEPTH_STEP_M
    kernel = np.ones((2 * step + 1, 2 * step + 1), np.uint8)
    inside = cv2.erode(surface.astype(np.uint8), kernel) > 0
    return np.where((inside & smooth)[..., None], n, 0).astype(np.float32)


def view_truth(
    image: Path, K: np.ndarray, scale: float, background: float
) -> dict[str, np.ndarray]:
    """What a view's files give as truth: ``radiance`` (linear), ``mask`` (alpha > 0.5, for
    RGBA images), ``depth`` (camera z) and ``normal`` (camera axes, from the depth) where the
    view has a depth render."""
    rgb, alpha = _read(image, scale, background)
    truth = {"radiance": rgb.astype(np.float32)}
    if alpha is not None:
        truth["mask"] = alpha > 0.5
    depth = depth_render(image)
    if depth is not None:
        truth["depth"] = decode_depth(depth, scale, K)
        truth["normal"] = normals_from_depth(truth["depth"], K)
    return truth


def splat_truth(
    T_world_cam: np.ndarray,
    K: np.ndarray,
    mask: np.ndarray,
    sources: list[tuple[np.ndarray, dict[str, np.ndarray]]],
) -> dict[str, np.ndarray]:
    """Depth and normal truth of a view without depth render, from the views that have one
    (pose, truth): their surface points and normals drawn into it, the nearest per pixel. Kept
    only inside ``mask`` and where the nearest point is no farther than the 3 x 3
    neighbourhood's nearest plus 3 %: a point seen through a gap between drawn points lies
    behind the surface. Pixels left without one stay 0 (not scored), and so do the normals
    the sources did not determine."""
    import cv2

    h, w = mask.shape
    zbuf = np.full(h * w, np.inf)
    nbuf = np.zeros((h * w, 3))
    world_to_cam = np.linalg.inv(T_world_cam)
    for T, truth in sources:
        ok = truth["depth"] > 0
        p = rays(K, h, w)[ok] * truth["depth"][ok][:, None]
        to_target = world_to_cam @ T
        q = p @ to_target[:3, :3].T + to_target[:3, 3]
        n = truth["normal"][ok] @ to_target[:3, :3].T
        front = q[:, 2] > 1e-6
        q, n = q[front], n[front]
        # Each point covers the 2 x 2 pixels around it: no gaps between neighbours.
        x = np.floor(q[:, 0] / q[:, 2] * K[0, 0] + K[0, 2]).astype(np.int64)
        y = np.floor(q[:, 1] / q[:, 2] * K[1, 1] + K[1, 2]).astype(np.int64)
        u = np.concatenate([x, x + 1, x, x + 1])
        v = np.concatenate([y, y, y + 1, y + 1])
        z, n = np.tile(q[:, 2], 4), np.tile(n, (4, 1))
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        pix, z, n = v[inside] * w + u[inside], z[inside], n[inside]
        order = np.argsort(-z)  # nearest last: it wins the assignment
        pix, z, n = pix[order], z[order], n[order]
        nearer = z < zbuf[pix]
        zbuf[pix[nearer]] = z[nearer]
        nbuf[pix[nearer]] = n[nearer]
    zbuf = zbuf.reshape(h, w)
    finite = np.where(np.isfinite(zbuf), zbuf, 1e9).astype(np.float32)
    local_min = cv2.erode(finite, np.ones((3, 3), np.uint8))
    keep = mask & np.isfinite(zbuf) & (zbuf <= 1.03 * local_min)
    return {
        "depth": np.where(keep, zbuf, 0).astype(np.float32),
        "normal": np.where(keep[..., None], nbuf.reshape(h, w, 3), 0).astype(np.float32),
    }


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


def _held_out(
    data: PosedImages, held_out: Path | None, scale: float, test_views: int
) -> tuple[np.ndarray, PosedImages | None]:
    """Which of the path's views make events, and the held-out views: ``test_views`` of the
    held-out file's views, evenly spread; without one, every 8th view of the path (then not
    used for events)."""
    n = len(data.images)
    if held_out is not None:
        other = read_transforms(held_out, scale)
        if not np.allclose(other.K, data.K, rtol=1e-6):
            raise InputError(f"{held_out}: its camera's intrinsics differ from the path's")
        pick = np.unique(np.linspace(0, len(other.images) - 1, test_views).round().astype(int))
        test = PosedImages([other.images[i] for i in pick], other.poses[pick], other.K)
        return np.arange(n), test if test_views > 0 else None
    held = np.arange(n) % 8 == 7
    if test_views <= 0 or not held.any():
        return np.arange(n), None
    pick = np.flatnonzero(held)[:test_views]
    test = PosedImages([data.images[i] for i in pick], data.poses[pick], data.K)
    return np.flatnonzero(~held), test


def _nearest(
    T: np.ndarray, poses: np.ndarray, truth: list[dict], count: int = 24
) -> list[tuple[np.ndarray, dict]]:
    """The ``count`` path views whose viewing directions are nearest T's."""
    cos = (poses[:, :3, 2] * T[:3, 2]).sum(-1)
    return [(poses[i], truth[i]) for i in np.argsort(-cos)[:count]]


def simulate_from_images(
    transforms: str | Path,
    output: str | Path,
    *,
    held_out: str | Path | None = None,
    background: float = 1.0,
    fps: float = 30.0,
    color_filter: str = "RGBG",
    threshold: float = 0.2,
    effects: dict | None = None,
    profile: str | SensorProfile | None = None,
    scale: float = 1.0,
    max_step_px: float = 1.0,
    dark_level: float = 1e-3,
    test_views: int = 8,
    seed: int = 0,
    overwrite: bool = False,
    progress: Callable[[float, float], None] | None = None,
) -> int:
    """Events from the posed images into the session ``output``; returns the event count.
    The camera moves through ``transforms``' views in order; ``held_out``, a second transforms
    file, gives the held-out views (see _held_out). RGBA images are composited over the gray
    level ``background`` (linear; 1 is the release's white). ``profile``: a named sensor
    (sim/sensor_profiles.py) whose thresholds and effects replace ``threshold`` and
    ``effects``."""
    transforms, output = Path(transforms), Path(output)
    if output.exists() and not overwrite:
        raise InputError(f"{output} exists; choose another name or pass --force")
    if not 0.0 <= background <= 1.0:
        raise InputError(f"background must be a gray level in [0, 1], not {background}")
    data = read_transforms(transforms, scale)
    keep, test = _held_out(data, None if held_out is None else Path(held_out), scale, test_views)
    images = [data.images[i] for i in keep]
    poses = data.poses[keep]
    first = view_truth(images[0], data.K, scale, background)
    h, w = first["radiance"].shape[:2]
    rng = np.random.default_rng(seed)
    channels = ChannelMap(w, h, color_filter)
    on = off = threshold
    if profile is not None:
        named = sensor_profile(profile)
        on, off, effects = named.threshold_on, named.threshold_off, named.effects
    effects = {k: v for k, v in (effects or {}).items() if k != "footprint"}
    pixels = PixelArray(w * h, on, off, effects, rng)
    sensor = SensorInfo("simulated", w, h, color_filter, "SIM-images", EPOCH_US)
    n_events = 0
    gt_t = [0]
    path_truth = [first]
    with SessionWriter(
        output, sensor, attrs={"source_file": str(transforms)}, overwrite=overwrite
    ) as writer:
        prev = first["radiance"].astype(np.float64)
        pixels.start(channels.log(prev.reshape(-1, 3), dark_level), 0.0)
        period = 1e6 / fps
        for k in range(1, len(images)):
            truth = view_truth(images[k], data.K, scale, background)
            cur = truth["radiance"].astype(np.float64)
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
            path_truth.append(truth)
            prev = cur
            if progress:
                progress(k, len(images) - 1)
    path = _views(poses, path_truth)
    held = None
    if test is not None:
        views = [view_truth(p, data.K, scale, background) for p in test.images]
        if path.depth is not None and "mask" in views[0] and not all("depth" in v for v in views):
            views = [
                {**v, **splat_truth(T, data.K, v["mask"], _nearest(T, poses, path_truth))}
                for v, T in zip(views, test.poses, strict=True)
            ]
        held = _views(test.poses, views)
    t = np.array(gt_t, np.int64)
    GroundTruth(
        source="evcap simulate --from-images",
        t=t,
        path=path,
        held_out=held,
        K=data.K,
        threshold_on=pixels.con.reshape(h, w).astype(np.float32),
        threshold_off=pixels.coff.reshape(h, w).astype(np.float32),
        notes={
            "images": str(transforms),
            "background": background,
            "held_out": str(held_out) if held_out is not None else "every 8th view of the path",
        },
    ).write(output)
    Poses(t, poses, source="ground truth").write(output)
    true_calibration(pixels, w, h, data.K).write(output)
    return n_events


def _views(poses: np.ndarray, truth: list[dict[str, np.ndarray]]) -> TruthViews:
    """The maps every view has (see view_truth), at each pose."""
    names = [n for n in ("radiance", "mask", "depth", "normal") if all(n in v for v in truth)]
    return TruthViews(poses, **{n: np.stack([v[n] for v in truth]) for n in names})
