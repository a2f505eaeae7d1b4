"""The event-derived edge map M_edge in [0, 1] that relaxes the TV smoothing at edges.

The events of a short slice are warped to a reference time with an optical flow v,
x' = x - (t - t_ref) v(x), and accumulated into an image of warped events (IWE). The flow is
one velocity per patch of a coarse grid, each chosen to maximise the variance (contrast) of its
own events' IWE (contrast maximisation, Gallego et al. 2018): a coarse grid search over
velocities, then finer local grids around the best. The map warps every event with the flow
interpolated bilinearly between patch centres, so that patches leave no seams.

Pixel centres are at integer coordinates; timestamps stay int64 microseconds until they are
made relative to t_ref.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

MIN_PATCH_EVENTS = 20  # fewer than this: the patch takes the median flow of the others
MAX_SEARCH_EVENTS = 4000  # per patch; a strided subset is enough to find its velocity
COARSE_STEPS = 5  # the coarse search: (2 * 5 + 1)^2 velocities up to the largest
REFINE_STEPS = 3  # each refinement: (2 * 3 + 1)^2 velocities, a third of the last spacing
REFINE_ROUNDS = 5
CHUNK_PIXELS = 1 << 22  # candidate images built at once, in pixels (float64: 32 MB)


def edge_map(
    xy: np.ndarray,
    t_us: np.ndarray,
    t_ref_us: int,
    width: int,
    height: int,
    *,
    patches: tuple[int, int] = (4, 3),
    blur_px: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The motion-compensated edge map ([height, width] float32 in [0, 1]) of events at pixel
    positions ``xy`` [E, 2] and times ``t_us`` [E], warped to ``t_ref_us``; and the flow
    ([rows, cols, 2] float64, px/s) of each patch of the ``patches`` = (cols, rows) grid."""
    cols, rows = patches
    flow = np.zeros((rows, cols, 2))
    xy, dt = _prepare(xy, t_us, t_ref_us)
    if len(dt) == 0:
        return np.zeros((height, width), np.float32), flow
    # events off the image (at -1 or cols, rows) join no patch
    col = np.clip(np.floor((xy[:, 0] + 0.5) * cols / width), -1, cols).astype(np.int64)
    row = np.clip(np.floor((xy[:, 1] + 0.5) * rows / height), -1, rows).astype(np.int64)
    dt_max = float(np.abs(dt).max())
    found = np.zeros((rows, cols), bool)
    # events all at t_ref say nothing of the velocity: the flow stays zero
    if dt_max > 0:
        # the largest displacement searched is a quarter of the image width
        v_max = width / 4 / dt_max
        for r in range(rows):
            for c in range(cols):
                sel = np.flatnonzero((row == r) & (col == c))
                if len(sel) < MIN_PATCH_EVENTS:
                    continue
                sel = sel[:: -(-len(sel) // MAX_SEARCH_EVENTS)]
                flow[r, c] = _search(xy[sel], dt[sel], v_max, dt_max, width, height, blur_px)
                found[r, c] = True
    if found.any():
        flow[~found] = np.median(flow[found], axis=0)

    v = _flow_at(xy, flow, width, height)
    image = _iwe(xy, dt, v[None], width, height, blur_px)[0]
    nonzero = image[image > 0]
    scale = float(np.percentile(nonzero, 99)) if len(nonzero) else 0.0
    if not scale > 0:
        return np.zeros((height, width), np.float32), flow
    # the 99th percentile, not the maximum: a few hot pixels must not dim every edge
    return np.clip(image / scale, 0.0, 1.0).astype(np.float32), flow


def variance_gain(
    xy: np.ndarray,
    t_us: np.ndarray,
    t_ref_us: int,
    width: int,
    height: int,
    flow: np.ndarray,
    *,
    blur_px: float = 1.0,
) -> float:
    """The IWE's variance with ``flow`` [rows, cols, 2] over that with zero flow (> 1: sharper);
    1 where there is nothing to compare."""
    xy, dt = _prepare(xy, t_us, t_ref_us)
    if len(dt) == 0:
        return 1.0
    v = _flow_at(xy, np.asarray(flow, np.float64), width, height)
    images = _iwe(xy, dt, np.stack([v, np.zeros_like(v)]), width, height, blur_px)
    var = images.reshape(2, -1).var(axis=1)
    return float(var[0] / var[1]) if var[1] > 0 else 1.0


def _prepare(xy: np.ndarray, t_us: np.ndarray, t_ref_us: int) -> tuple[np.ndarray, np.ndarray]:
    """Sane positions [E, 2], dithered, and their times in seconds from t_ref [E]."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    t = np.asarray(t_us, np.int64).reshape(-1)
    if len(t) != len(xy):
        raise ValueError(f"{len(xy)} event positions but {len(t)} timestamps")
    dt = (t - np.int64(t_ref_us)).astype(np.float64) * 1e-6
    keep = (np.abs(xy) < 1e9).all(axis=1)  # finite, and far from overflowing int64 pixels
    xy, dt = xy[keep], dt[keep]
    # events on whole pixels (a sensor's) that share a coordinate stay on the pixel lattice
    # while that velocity component is zero, where bilinear votes make the variance peak: a
    # fixed sub-pixel dither (a 0.3 px jitter, small beside the blur) frees the estimate of it
    i = np.arange(len(xy))[:, None]
    return xy + (i * [0.6180339887, 0.7548776662]) % 1.0 - 0.5, dt


def _search(
    xy: np.ndarray, dt: np.ndarray, v_max: float, dt_max: float, w: int, h: int, blur: float
) -> np.ndarray:
    """The velocity (px/s) whose IWE of these events has the largest variance."""
    best = np.zeros(2)
    step, n = v_max / COARSE_STEPS, COARSE_STEPS
    for _ in range(1 + REFINE_ROUNDS):
        offsets = np.arange(-n, n + 1) * step
        grid = np.stack(np.meshgrid(offsets, offsets), axis=-1).reshape(-1, 2) + best
        # a sharp peak can fall between the points of a coarse grid: blur as much as its
        # spacing smears an edge, so that the nearest point still stands out
        sigma = max(blur, 0.5 * step * dt_max)
        # the canvas holds every warped, blurred vote, beyond the image too (votes dropped at
        # its border would bias the velocity), so the variance ranks as the sum of squares; its
        # pixels are `cell` image pixels, as the coarse rounds need no finer ones than their blur
        cell = max(1, int(sigma))
        reach = np.abs(grid).max(axis=0) * dt_max + 3 * sigma + 2 * cell
        lo = np.floor(xy.min(axis=0) - reach)
        cw, ch = (int(v) for v in np.ceil((xy.max(axis=0) + reach - lo) / cell) + 1)
        per = max(1, CHUNK_PIXELS // (cw * ch))
        scores = []
        for i in range(0, len(grid), per):
            v = grid[i : i + per, None] / cell
            image = _iwe((xy - lo) / cell, dt, v, cw, ch, sigma / cell)
            scores.append((image.reshape(len(image), -1) ** 2).sum(axis=1))
        best = grid[int(np.argmax(np.concatenate(scores)))]
        step, n = step / REFINE_STEPS, REFINE_STEPS
    return best


def _flow_at(xy: np.ndarray, flow: np.ndarray, w: int, h: int) -> np.ndarray:
    """[E, 2] the patch flow interpolated bilinearly between patch centres (held at the borders)."""
    rows, cols = flow.shape[:2]
    u = np.clip((xy[:, 0] + 0.5) * cols / w - 0.5, 0, cols - 1)
    r = np.clip((xy[:, 1] + 0.5) * rows / h - 0.5, 0, rows - 1)
    c0, r0 = np.floor(u).astype(np.int64), np.floor(r).astype(np.int64)
    c1, r1 = np.minimum(c0 + 1, cols - 1), np.minimum(r0 + 1, rows - 1)
    fu, fr = (u - c0)[:, None], (r - r0)[:, None]
    top = flow[r0, c0] * (1 - fu) + flow[r0, c1] * fu
    bottom = flow[r1, c0] * (1 - fu) + flow[r1, c1] * fu
    return top * (1 - fr) + bottom * fr


def _iwe(
    xy: np.ndarray, dt: np.ndarray, velocity: np.ndarray, w: int, h: int, sigma: float
) -> np.ndarray:
    """[N, h, w] images of warped events, one per velocity: ``velocity`` [N, 1 or E, 2].
    Bilinear votes of event counts (either polarity); votes off the w x h image are dropped."""
    pos = xy[None] - dt[None, :, None] * velocity
    n = pos.shape[0]
    x0, y0 = np.floor(pos[..., 0]), np.floor(pos[..., 1])
    fx, fy = pos[..., 0] - x0, pos[..., 1] - y0
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    base = np.arange(n)[:, None] * (w * h)
    image = np.zeros(n * w * h)
    for ox, oy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        weight = (fx if ox else 1 - fx) * (fy if oy else 1 - fy)
        xi, yi = x0 + ox, y0 + oy
        ok = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
        image += np.bincount((base + yi * w + xi)[ok], weight[ok], minlength=n * w * h)
    return _blur(image.reshape(n, h, w), sigma)


def _blur(images: np.ndarray, sigma: float) -> np.ndarray:
    """[N, h, w] Gaussian blur (separable, zero outside the image)."""
    if sigma <= 0:
        return images
    r = max(1, math.ceil(3 * sigma))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k = torch.from_numpy(k / k.sum())
    out = F.conv2d(torch.from_numpy(images)[:, None], k.view(1, 1, 1, -1), padding=(0, r))
    out = F.conv2d(out, k.view(1, 1, -1, 1), padding=(r, 0))
    return out[:, 0].numpy()
