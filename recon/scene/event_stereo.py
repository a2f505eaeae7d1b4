"""Where the events say there is structure: a multi-view stereo from the events and the poses
alone (EMVS, Rebecq et al., IJCV 2018), as stage I's start.

An edge that moves across the sensor makes events along its image; each event's ray, cast from
where the camera was when it fired, passes through the edge. Cast into the depth planes of a
reference view (a disparity-space volume), the rays of many events cross where the edge is:
each pixel's depth is where its rays are densest, kept where that density stands out from its
neighbourhood's (adaptive threshold). Reference views every stretch of the path; their points
merged, and kept where other reference views, with none of its events, found one near (one
view's noise is alone).

What lies at infinity (a horizon, the ground of an environment) casts parallel rays: they are
densest at the farthest plane, and the points there belong to the background, not to the
Gaussians. Nothing is drawn at random: where no event was, no point is.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np
import torch

from evcap.errors import InputError
from evcap.events import Events
from evcap.recon.scene.neighbours import nearest
from evcap.recon.scene.optics import SensorOptics
from evcap.recon.scene.volume import SceneVolume
from evcap.records import Poses


@dataclass(frozen=True)
class StereoConfig:
    """The events' multi-view stereo (event_stereo)."""

    references: int = 12
    """Reference views, evenly along the path; each takes the events of the stretch around it."""
    overlap: float = 2.0
    """A reference view's stretch, in units of the spacing between reference views."""
    planes: int = 96
    """Depth planes of a reference view, evenly in inverse depth over the scene's volume."""
    max_events: int = 2_000_000
    """At most this many of a stretch's events cast (evenly spaced in time)."""
    contrast: float = 1.5
    """A pixel is kept where its rays' density is this many times its neighbourhood's."""
    agree: float = 0.02
    """A point is kept where other reference views found one within this share of the
    volume's radius ..."""
    witnesses: int = 2
    """... at least this many of them, none sharing an event with its own view."""
    aperture: float = 0.0
    """A pixel is kept only where the camera's translations over the stretch move it across
    its edge: the root of the share of the image motion's second moment along the edge's
    normal at least this (|cos| of the normal and the motion where the stretch moves one way;
    0: every edge). An edge along the motion moves along itself (the aperture problem): its
    rays meet anywhere, often just before the cameras."""

    def __post_init__(self) -> None:
        if self.references < 2 or self.planes < 8 or self.max_events < 1:
            raise InputError("init.stereo needs references >= 2, planes >= 8, max_events >= 1")
        if self.overlap <= 0 or self.contrast < 1 or self.agree <= 0 or self.witnesses < 1:
            raise InputError(
                "init.stereo needs overlap > 0, contrast >= 1, agree > 0 and witnesses >= 1"
            )
        if not 0 <= self.aperture < 1:
            raise InputError("init.stereo.aperture is a cosine in [0, 1)")


@dataclass
class StereoPoints:
    points: np.ndarray  # [N, 3] world
    confidence: np.ndarray  # [N]: the rays' density at the point over its neighbourhood's
    views: int  # reference views that found any


CAST_BINS_US = 1000  # the events of each millisecond cast from one pose


def event_stereo(
    events: Callable[[int, int], Events],
    span: tuple[int, int],
    track: Poses,
    optics: SensorOptics,
    volume: SceneVolume,
    config: StereoConfig = StereoConfig(),
) -> StereoPoints:
    """The structure the events show over ``span`` (us; within the track), as world points
    (see the module's text). ``events(t0, t1)``: the events with t0 <= t < t1 (a session's
    ``events``: each stretch read alone)."""
    start, end = int(span[0]), int(span[1])
    if end <= start:
        return StereoPoints(np.zeros((0, 3)), np.zeros(0), 0)
    rays = _pixel_rays(optics)
    spacing = (end - start) / config.references
    found: list[tuple[np.ndarray, np.ndarray, int]] = []
    for r in range(config.references):
        t_ref = start + (r + 0.5) * spacing
        half = 0.5 * config.overlap * spacing
        stretch = events(int(max(start, t_ref - half)), int(min(end, t_ref + half)))
        pts, conf = _reference_points(stretch, track, optics, rays, volume, config, int(t_ref))
        found.append((pts, conf, r))
    # views whose stretches share no event: each a separate witness
    apart = int(np.ceil(config.overlap))
    return _agreeing(found, config.agree * volume.radius, apart, config.witnesses)


def _pixel_rays(optics: SensorOptics) -> np.ndarray:
    """[H * W, 3] each sensor pixel's ray (x/z, y/z, 1) through its lens; hot pixels NaN."""
    xy = optics.undistorted()
    rays = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    rays[optics.hot_pixels.ravel()] = np.nan
    return rays


def _depth_range(volume: SceneVolume, T_ref: np.ndarray) -> tuple[float, float]:
    """The reference camera's depths that the volume spans."""
    if not volume.converging:
        return volume.near, volume.far
    distance = float((volume.center - T_ref[:3, 3]) @ T_ref[:3, 2])
    return max(distance - volume.radius, 0.05 * distance), distance + volume.radius


def _reference_points(
    stretch: Events,
    track: Poses,
    optics: SensorOptics,
    rays: np.ndarray,
    volume: SceneVolume,
    config: StereoConfig,
    t_ref: int,
) -> tuple[np.ndarray, np.ndarray]:
    """The points [N, 3] and confidences [N] one reference view at ``t_ref`` finds."""
    if len(stretch) < 100:
        return np.zeros((0, 3)), np.zeros(0)
    keep = np.linspace(0, len(stretch) - 1, min(len(stretch), config.max_events)).astype(np.int64)
    t = stretch.t[keep]
    pixel = stretch.y[keep].astype(np.int64) * optics.width + stretch.x[keep]
    # each millisecond's events from the pose at its middle, relative to the reference view
    bins = ((t - t[0]) // CAST_BINS_US).astype(np.int64)
    mids = t[0] + (np.arange(bins[-1] + 1) + 0.5) * CAST_BINS_US
    mids = np.minimum(mids, t[-1]).astype(np.int64)  # the last bin may be short
    T_ref = track.at(t_ref)
    poses = np.linalg.inv(T_ref)[None] @ track.at(mids)
    near, far = _depth_range(volume, T_ref)
    depths = 1 / np.linspace(1 / near, 1 / far, config.planes)
    density = np.zeros((config.planes, optics.height, optics.width), np.float32)
    _cast(
        rays[pixel],
        bins,
        poses[:, :3, :3].copy(),
        poses[:, :3, 3].copy(),
        depths,
        optics.K,
        density,
    )
    focus = _focus(density)
    chosen = _chosen(focus, len(depths), config.contrast)
    if config.aperture > 0:  # the stretch's positions, in the reference camera
        chosen &= _across_the_motion(focus[2], poses[:, :3, 3], optics.K, config.aperture)
    return _peaks(focus, depths, T_ref, optics.K, chosen)


@numba.njit(cache=True, parallel=True)
def _cast(rays, bins, rotations, shifts, depths, K, density):
    """Add each event's ray to the planes' density where it crosses them (nearest pixel)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    height, width = density.shape[1], density.shape[2]
    for i in numba.prange(len(depths)):  # each thread owns its planes: no write is shared
        z = depths[i]
        for e in range(len(rays)):
            if np.isnan(rays[e, 0]):
                continue
            R, s = rotations[bins[e]], shifts[bins[e]]
            dx = R[0, 0] * rays[e, 0] + R[0, 1] * rays[e, 1] + R[0, 2]
            dy = R[1, 0] * rays[e, 0] + R[1, 1] * rays[e, 1] + R[1, 2]
            dz = R[2, 0] * rays[e, 0] + R[2, 1] * rays[e, 1] + R[2, 2]
            if abs(dz) < 1e-9:
                continue
            along = (z - s[2]) / dz
            if along <= 0:  # the plane lies behind the event's camera
                continue
            u = fx * (s[0] + along * dx) / z + cx
            v = fy * (s[1] + along * dy) / z + cy
            col, row = int(np.floor(u + 0.5)), int(np.floor(v + 0.5))
            if 0 <= col < width and 0 <= row < height:
                density[i, row, col] += 1.0


def _focus(density: np.ndarray) -> tuple[np.ndarray, ...]:
    """(the density smoothed in each plane, each pixel's densest plane, its density there,
    that density's neighbourhood mean)."""
    import cv2

    smooth = np.stack([cv2.GaussianBlur(d, (0, 0), 0.8) for d in density])
    best = smooth.argmax(0)
    peak = np.take_along_axis(smooth, best[None], 0)[0]
    around = cv2.GaussianBlur(peak, (0, 0), 5.0)
    return smooth, best, peak, around


def _chosen(focus: tuple[np.ndarray, ...], planes: int, contrast: float) -> np.ndarray:
    """The pixels whose rays peak in depth and stand out from their neighbourhood; none at the
    ends of the depth range (at infinity or too near)."""
    _, best, peak, around = focus
    # a floor: a pixel crossed by a few stray rays is not structure
    floor = np.percentile(peak[peak > 0], 50) if (peak > 0).any() else np.inf
    chosen = (peak > contrast * around) & (peak > floor)
    return chosen & (best > 0) & (best < planes - 1)


def _across_the_motion(
    peak: np.ndarray, shifts: np.ndarray, K: np.ndarray, aperture: float
) -> np.ndarray:
    """The pixels whose edge (a ridge of ``peak``; its normal n the structure tensor's first
    eigenvector) the stretch's translations ``shifts`` [B, 3] (the reference camera's frame)
    move a point across: sqrt(n^T M n / trace M) >= ``aperture``, M the sum over the shifts
    of the image motion's outer product (|cos| of n and the motion where it has one
    direction; a path that turns within the stretch crosses more edges)."""
    import cv2

    gx = cv2.Sobel(peak, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(peak, cv2.CV_32F, 0, 1)
    jxx, jxy, jyy = (cv2.GaussianBlur(g, (0, 0), 1.5) for g in (gx * gx, gx * gy, gy * gy))
    angle = 0.5 * np.arctan2(2 * jxy, jxx - jyy)
    rows, cols = np.indices(peak.shape)
    x, y = (cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1]
    # a point's image moves with a translation t along (t_x - x t_z, t_y - y t_z) / z: M's
    # entries from the shifts' second moments
    S = shifts.T @ shifts
    m11 = K[0, 0] ** 2 * (S[0, 0] - 2 * x * S[0, 2] + x * x * S[2, 2])
    m22 = K[1, 1] ** 2 * (S[1, 1] - 2 * y * S[1, 2] + y * y * S[2, 2])
    m12 = K[0, 0] * K[1, 1] * (S[0, 1] - x * S[1, 2] - y * S[0, 2] + x * y * S[2, 2])
    c, s = np.cos(angle), np.sin(angle)
    across = c * c * m11 + 2 * c * s * m12 + s * s * m22
    return np.sqrt(np.maximum(across, 0) / np.maximum(m11 + m22, 1e-24)) >= aperture


def _peaks(
    focus: tuple[np.ndarray, ...],
    depths: np.ndarray,
    T_ref: np.ndarray,
    K: np.ndarray,
    chosen: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """World points where the ``chosen`` pixels' rays peak in depth, and how much their
    density stands out from their neighbourhood's."""
    smooth, best, peak, around = focus
    rows, cols = np.nonzero(chosen)
    i = best[rows, cols]
    # the peak between planes: a parabola through the density at the plane and its two
    # neighbours, in inverse depth (where the planes are even)
    below, at, above = (smooth[i + k, rows, cols] for k in (-1, 0, 1))
    curve = below - 2 * at + above
    offset = np.where(curve < 0, 0.5 * (below - above) / np.where(curve < 0, curve, -1), 0.0)
    inverse = 1 / depths
    step = inverse[1] - inverse[0]
    z = 1 / (inverse[i] + np.clip(offset, -0.5, 0.5) * step)
    x = (cols - K[0, 2]) / K[0, 0] * z
    y = (rows - K[1, 2]) / K[1, 1] * z
    camera = np.stack([x, y, z], 1)
    world = camera @ T_ref[:3, :3].T + T_ref[:3, 3]
    return world, (peak / np.maximum(around, 1e-9))[rows, cols]


def _agreeing(
    found: list[tuple[np.ndarray, np.ndarray, int]], within: float, apart: int, witnesses: int
) -> StereoPoints:
    """The points of all reference views that ``witnesses`` other views, each at least
    ``apart`` views away, found one near."""
    views = sum(1 for pts, _, _ in found if len(pts))
    points = np.concatenate([f[0] for f in found])
    confidence = np.concatenate([f[1] for f in found])
    view = np.concatenate([np.full(len(f[0]), f[2]) for f in found])
    if len(points) < 2:
        return StereoPoints(points, confidence, views)
    k = min(16, len(points))
    tensor = torch.from_numpy(points)
    distances, indices = nearest(tensor, tensor, k)
    other = (np.abs(view[indices] - view[:, None]) >= apart) & (distances <= within)
    # the distinct views among a point's witnesses
    seen = np.where(other, view[indices], -1)
    seen.sort(1)
    distinct = ((seen[:, 1:] != seen[:, :-1]) & (seen[:, 1:] >= 0)).sum(1) + (seen[:, 0] >= 0)
    keep = distinct >= witnesses
    return StereoPoints(points[keep], confidence[keep], views)
