"""The voxel grid: the input of the E2VID-style networks (Rebecq et al., TPAMI 2019).

A window of events becomes ``bins`` images. The window's timestamps are scaled to [0, bins - 1]
(its first event on bin 0, its last on bin bins - 1), and each event's polarity (+1 ON, -1 OFF)
is split linearly between the two bins nearest its time: an event at 1.25 puts 0.75 of its
polarity into bin 1 and 0.25 into bin 2. The networks then see only the non-zero voxels
normalised to mean 0 and standard deviation 1 (``normalize_voxels``).

``voxel_grid`` (NumPy, float64 sums) is the reference; ``voxel_grid_torch`` builds the same grid
on any torch device.
"""

from __future__ import annotations

import numpy as np
import torch

from evcap.errors import InputError


def voxel_grid(
    x: np.ndarray,  # [E] integer pixel columns
    y: np.ndarray,  # [E] integer pixel rows
    t: np.ndarray,  # [E] int64 microseconds
    p: np.ndarray,  # [E] polarity: 1 (or > 0) ON, 0 (or <= 0) OFF
    width: int,
    height: int,
    bins: int = 5,
) -> np.ndarray:
    """The voxel grid [bins, height, width] float32 of one window of events."""
    x, y, tn, pol = _prepare(x, y, t, p, width, height, bins)
    grid = np.zeros(bins * height * width)
    if len(tn):
        left = np.floor(tn).astype(np.int64)
        frac = tn - left
        pixel = y * width + x
        # the last event sits exactly on bin bins - 1: its right share (zero) has no bin
        right = left + 1 < bins
        plane = height * width
        index = np.concatenate([left * plane + pixel, (left[right] + 1) * plane + pixel[right]])
        weight = np.concatenate([pol * (1.0 - frac), pol[right] * frac[right]])
        grid = np.bincount(index, weights=weight, minlength=grid.size)
    return grid.reshape(bins, height, width).astype(np.float32)


def voxel_grid_torch(
    x: np.ndarray | torch.Tensor,
    y: np.ndarray | torch.Tensor,
    t: np.ndarray | torch.Tensor,
    p: np.ndarray | torch.Tensor,
    width: int,
    height: int,
    bins: int = 5,
    device: str | torch.device = "cpu",
) -> torch.Tensor:
    """``voxel_grid`` built with torch on ``device``: [bins, height, width] float32."""
    xs, ys, ts, ps = (_int64(a, device) for a in (x, y, t, p))
    _check(len(xs), len(ys), len(ts), len(ps), width, height, bins)
    grid = torch.zeros(bins * height * width, dtype=torch.float32, device=device)
    if len(ts):
        if int(xs.min()) < 0 or int(xs.max()) >= width:
            raise InputError(f"voxel grid: x outside 0..{width - 1}")
        if int(ys.min()) < 0 or int(ys.max()) >= height:
            raise InputError(f"voxel grid: y outside 0..{height - 1}")
        # times relative to the first in int64, then float64: float32 would lose microseconds
        rel = ts - ts.min()
        span = int(rel.max())
        tn = rel.double() * (bins - 1) / span if span > 0 else rel.double()
        pol = torch.where(ps > 0, 1.0, -1.0).double()
        left = tn.floor().long()
        frac = tn - left
        pixel = ys * width + xs
        grid.index_add_(0, left * height * width + pixel, (pol * (1.0 - frac)).float())
        right = left + 1 < bins
        index = (left[right] + 1) * height * width + pixel[right]
        grid.index_add_(0, index, (pol[right] * frac[right]).float())
    return grid.view(bins, height, width)


def normalize_voxels(v: np.ndarray) -> np.ndarray:
    """``v`` with its non-zero voxels shifted and scaled to mean 0 and standard deviation 1;
    zero voxels stay zero (no events there), and so does a grid with no events."""
    v = np.asarray(v, np.float32)
    nonzero = v != 0
    n = int(nonzero.sum())
    if n == 0:
        return v.copy()
    values = v[nonzero].astype(np.float64)
    mean = values.mean()
    std = values.std()
    # one value everywhere (a single event, say) has no spread: shifting it is all there is
    scale = 1.0 / std if std > 0 else 1.0
    out = np.zeros_like(v)
    out[nonzero] = ((values - mean) * scale).astype(np.float32)
    return out


def _int64(a: np.ndarray | torch.Tensor, device: str | torch.device) -> torch.Tensor:
    if torch.is_tensor(a):
        return a.to(device=device, dtype=torch.int64).reshape(-1)
    return torch.from_numpy(np.asarray(a).reshape(-1).astype(np.int64)).to(device)


def _check(nx: int, ny: int, nt: int, np_: int, width: int, height: int, bins: int) -> None:
    if not nx == ny == nt == np_:
        raise InputError(f"voxel grid: {nx} x, {ny} y, {nt} t and {np_} p (need one each)")
    if width < 1 or height < 1:
        raise InputError(f"voxel grid: image size {width}x{height} must be at least 1x1")
    if bins < 1:
        raise InputError(f"voxel grid: bins={bins} must be at least 1")


def _prepare(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray, width: int, height: int, bins: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Validated pixel columns and rows (int64), times scaled to [0, bins - 1] and signed
    polarities (float64)."""
    x = np.asarray(x).reshape(-1).astype(np.int64)
    y = np.asarray(y).reshape(-1).astype(np.int64)
    t = np.asarray(t).reshape(-1).astype(np.int64)
    p = np.asarray(p).reshape(-1)
    _check(len(x), len(y), len(t), len(p), width, height, bins)
    if len(t) == 0:
        return x, y, np.zeros(0), np.zeros(0)
    if x.min() < 0 or x.max() >= width:
        raise InputError(f"voxel grid: x outside 0..{width - 1}")
    if y.min() < 0 or y.max() >= height:
        raise InputError(f"voxel grid: y outside 0..{height - 1}")
    rel = t - t.min()
    span = int(rel.max())
    # a window whose events share one time stamp puts them all in bin 0
    tn = rel * (bins - 1) / span if span > 0 else rel.astype(np.float64)
    return x, y, tn, np.where(p > 0, 1.0, -1.0)
