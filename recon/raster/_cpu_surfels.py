"""The compiled CPU rasterizer's surfels (recon/raster/surfels.py says what they are): the
Gaussians' tiles, threads and backward layout (recon/raster/_cpu.py), with each pair's alpha and
depth from the ray-splat intersection.

The discs' matrices M and projected centres are made in torch (surfels.py), which also carries
their gradients back to the means, rotations, scales and camera; the kernels here composite and
return d/d(M, centre, opacity, values) per disc. A pair's depth is its own (where its ray meets
the disc), so the depth channel of ``values`` is filled per pair, and its gradient goes to M.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from evcap.recon._threads import follow_torch_threads
from evcap.recon.raster import _cpu
from evcap.recon.raster._cpu import (
    ALPHA_MAX,
    ALPHA_MIN,
    FASTMATH,
    T_MIN,
    _back,
    _max_rows,
    _pixels,
    _reused,
    _share,
    _sum_rows,
    _tile_area,
    _tile_buffers,
    _to_lanes,
)
from evcap.recon.raster.rasterize import Camera, Render
from evcap.recon.raster.surfels import (
    FILTER_INV_SQUARE,
    surfel_boxes,
    surfel_matrices,
    surfel_normals,
)

# per disc: d/d(M's 9 entries, centre x, centre y, opacity), then d/d(each value channel)
SURFEL = 12
# a tile's copy of its discs: M, centre, opacity, the exponent beyond which alpha is under
# 1/255, the box's columns
CENTRE_X, CENTRE_Y, OPACITY, CUT, BOX_X0, BOX_X1 = range(9, 15)


@numba.njit(cache=True, inline="always")
def _gather(layout, t, splats, values, local, vals, rows, row_len):
    """Tile t's discs side by side (local [k]: M, centre, opacity, cut-off, box columns; vals
    [k] their values) and rows [r, :row_len[r]] those whose box covers row r, front to back."""
    tile_start, owner, box = layout[0], layout[1], layout[2]
    y0, tile_h = _tile_area(layout, t)[1], layout[6]
    row_len[:] = 0
    for k in range(tile_start[t + 1] - tile_start[t]):
        g = owner[tile_start[t] + k]
        for c in range(CUT):
            local[k, c] = splats[g, c]
        local[k, CUT] = math.log(max(splats[g, OPACITY], 1e-300) / ALPHA_MIN) + 1e-6
        local[k, BOX_X0], local[k, BOX_X1] = box[g, 0], box[g, 1]
        for c in range(values.shape[1]):
            vals[k, c] = values[g, c]
        for r in range(max(box[g, 2] - y0, 0), min(box[g, 3] - y0, tile_h - 1) + 1):
            rows[r, row_len[r]] = k
            row_len[r] += 1


@numba.njit(cache=True, inline="always", fastmath=FASTMATH)
def _intersect(local, k, px, py):
    """Pixel (px, py) against disc k: (exponent rho / 2, depth, on the disc (not the filter),
    u, v, c2) with c = h_x x h_y."""
    hx0 = px * local[k, 6] - local[k, 0]
    hx1 = px * local[k, 7] - local[k, 1]
    hx2 = px * local[k, 8] - local[k, 2]
    hy0 = py * local[k, 6] - local[k, 3]
    hy1 = py * local[k, 7] - local[k, 4]
    hy2 = py * local[k, 8] - local[k, 5]
    c2 = hx0 * hy1 - hx1 * hy0
    dx, dy = px - local[k, CENTRE_X], py - local[k, CENTRE_Y]
    rho2d = FILTER_INV_SQUARE * (dx * dx + dy * dy)
    if c2 != 0:
        u = (hx1 * hy2 - hx2 * hy1) / c2
        v = (hx2 * hy0 - hx0 * hy2) / c2
        rho3d = u * u + v * v
        if rho3d <= rho2d:
            return 0.5 * rho3d, local[k, 6] * u + local[k, 7] * v + local[k, 8], True, u, v, c2
    return 0.5 * rho2d, local[k, 8], False, 0.0, 0.0, c2


@numba.njit(cache=True, parallel=True, fastmath=FASTMATH)
def _composite_fwd(layout, splats, values, channels_z, near, out, final_t, last, peak):
    """As _cpu._composite_fwd, each pair's alpha and depth from its ray and disc; of each
    pair's values, the channel channels_z[0] is its own depth and channels_z[1] (unless
    negative) its square."""
    depth_channel, square_channel = channels_z
    tile_start, width, workers = layout[0], layout[3], layout[-1]
    channels = values.shape[1]
    for worker in numba.prange(workers):
        for t in _share(layout, worker):
            s = tile_start[t]
            peak[s : tile_start[t + 1]] = 0.0
            local, vals, rows, row_len = _tile_buffers(layout, t, channels, BOX_X1 + 1)
            _gather(layout, t, splats, values, local, vals, rows, row_len)
            x0, y0, cols, tile_rows = _tile_area(layout, t)
            acc, T = np.empty((cols, channels)), np.empty(cols)
            n, done = np.empty(cols, np.int64), np.empty(cols, np.bool_)
            for r in range(tile_rows):
                py = y0 + r
                acc[:] = 0.0
                T[:] = 1.0
                n[:] = 0
                done[:] = False
                finished = 0
                for j in range(row_len[r]):
                    k = np.uint64(rows[r, j])  # unsigned: no checks for negative indices
                    lo = int(max(x0, local[k, BOX_X0]))
                    hi = int(min(x0 + cols - 1, local[k, BOX_X1]))
                    o, cut = local[k, OPACITY], local[k, CUT]
                    top = 0.0
                    for px in range(lo, hi + 1):
                        i = np.uint64(px - x0)
                        if done[i]:
                            continue
                        power, z = _intersect(local, k, px, py)[:2]
                        if power > cut or not z > near:
                            continue
                        alpha = min(ALPHA_MAX, o * math.exp(-power))
                        if alpha < ALPHA_MIN:
                            continue
                        next_t = T[i] * (1 - alpha)
                        if next_t <= T_MIN:
                            done[i] = True
                            finished += 1
                            continue
                        w = alpha * T[i]
                        top = max(top, w)
                        for c in range(channels):
                            acc[i, c] += w * vals[k, c]
                        acc[i, depth_channel] += w * (z - vals[k, depth_channel])
                        if square_channel >= 0:
                            acc[i, square_channel] += w * (z * z - vals[k, square_channel])
                        T[i] = next_t
                        n[i] = j + 1
                    peak[s + k] = max(peak[s + k], top)
                    if finished == cols:
                        break
                for i in range(cols):
                    pix = py * width + x0 + i
                    out[pix] = acc[i]
                    final_t[pix] = T[i]
                    last[pix] = n[i]


@numba.njit(cache=True, parallel=True, fastmath=FASTMATH)
def _composite_bwd(layout, splats, values, channels_z, near, final_t, last, v_out, v_alpha, grads):
    """Each intersection's gradients into its row of ``grads`` [M, SURFEL + channels], as
    _cpu._composite_bwd; a pair's depth's gradient (and its square's) goes to M (their
    channels' own columns stay 0)."""
    depth_channel, square_channel = channels_z
    tile_start, width, workers = layout[0], layout[3], layout[-1]
    channels = values.shape[1]
    for worker in numba.prange(workers):
        for t in _share(layout, worker):
            s = tile_start[t]
            grads[s : tile_start[t + 1]] = 0.0
            local, vals, rows, row_len = _tile_buffers(layout, t, channels, BOX_X1 + 1)
            _gather(layout, t, splats, values, local, vals, rows, row_len)
            x0, y0, cols, tile_rows = _tile_area(layout, t)
            T, n, v_end = np.empty(cols), np.empty(cols, np.int64), np.empty(cols)
            v_row = np.empty((cols, channels))
            behind = np.empty(cols)
            v_vals, v_M = np.empty(channels), np.empty(9)
            for r in range(tile_rows):
                py = y0 + r
                p0 = py * width + x0
                behind[:] = 0.0
                for i in range(cols):
                    T[i], n[i] = final_t[p0 + i], last[p0 + i]
                    v_end[i] = v_alpha[p0 + i] * final_t[p0 + i]
                    v_row[i] = v_out[p0 + i]
                for j in range(n.max() - 1, -1, -1):
                    k = np.uint64(rows[r, j])
                    lo = int(max(x0, local[k, BOX_X0]))
                    hi = int(min(x0 + cols - 1, local[k, BOX_X1]))
                    o, cut = local[k, OPACITY], local[k, CUT]
                    v_cx = v_cy = v_o = 0.0
                    v_vals[:] = 0.0
                    v_M[:] = 0.0
                    for px in range(lo, hi + 1):
                        i = np.uint64(px - x0)
                        if j >= n[i]:
                            continue
                        power, z, on_disc, u, v, c2 = _intersect(local, k, px, py)
                        if power > cut or not z > near:
                            continue
                        g = math.exp(-power)
                        alpha = min(ALPHA_MAX, o * g)
                        if alpha < ALPHA_MIN:
                            continue
                        keep = 1 / (1 - alpha)
                        T[i] *= keep
                        w = alpha * T[i]
                        seen = 0.0
                        for ch in range(channels):
                            v_vals[ch] += w * v_row[i, ch]
                            seen += v_row[i, ch] * vals[k, ch]
                        seen += v_row[i, depth_channel] * (z - vals[k, depth_channel])
                        v_z = w * v_row[i, depth_channel]
                        if square_channel >= 0:
                            sq = z * z - vals[k, square_channel]
                            seen += v_row[i, square_channel] * sq
                            v_z += 2 * z * w * v_row[i, square_channel]
                        v_alpha_k = (v_end[i] - behind[i]) * keep + seen * T[i]
                        behind[i] += seen * w
                        v_power = 0.0
                        if o * g <= ALPHA_MAX:  # else alpha is clamped: no gradient through it
                            v_o += v_alpha_k * g
                            v_power = -v_alpha_k * alpha
                        if on_disc:
                            # power = (u^2 + v^2) / 2, depth = M20 u + M21 v + M22, with
                            # (u, v) = (c0, c1) / c2 and c = h_x x h_y
                            m20, m21 = local[k, 6], local[k, 7]
                            v_u = v_power * u + v_z * m20
                            v_v = v_power * v + v_z * m21
                            v_c0, v_c1 = v_u / c2, v_v / c2
                            v_c2 = -(v_u * u + v_v * v) / c2
                            hx0 = px * local[k, 6] - local[k, 0]
                            hx1 = px * local[k, 7] - local[k, 1]
                            hx2 = px * local[k, 8] - local[k, 2]
                            hy0 = py * local[k, 6] - local[k, 3]
                            hy1 = py * local[k, 7] - local[k, 4]
                            hy2 = py * local[k, 8] - local[k, 5]
                            # d/dh_x = h_y x v_c, d/dh_y = v_c x h_x
                            vhx0 = hy1 * v_c2 - hy2 * v_c1
                            vhx1 = hy2 * v_c0 - hy0 * v_c2
                            vhx2 = hy0 * v_c1 - hy1 * v_c0
                            vhy0 = v_c1 * hx2 - v_c2 * hx1
                            vhy1 = v_c2 * hx0 - v_c0 * hx2
                            vhy2 = v_c0 * hx1 - v_c1 * hx0
                            # h_x = px M[2] - M[0], h_y = py M[2] - M[1]
                            v_M[0] -= vhx0
                            v_M[1] -= vhx1
                            v_M[2] -= vhx2
                            v_M[3] -= vhy0
                            v_M[4] -= vhy1
                            v_M[5] -= vhy2
                            v_M[6] += px * vhx0 + py * vhy0 + v_z * u
                            v_M[7] += px * vhx1 + py * vhy1 + v_z * v
                            v_M[8] += px * vhx2 + py * vhy2 + v_z
                        else:  # the screen-space filter about the centre, the centre's depth
                            v_rho2d = 0.5 * v_power * FILTER_INV_SQUARE
                            v_cx -= 2 * v_rho2d * (px - local[k, CENTRE_X])
                            v_cy -= 2 * v_rho2d * (py - local[k, CENTRE_Y])
                            v_M[8] += v_z
                    row = grads[s + k]
                    for c in range(9):
                        row[c] += v_M[c]
                    row[CENTRE_X] += v_cx
                    row[CENTRE_Y] += v_cy
                    row[OPACITY] += v_o
                    for ch in range(channels):
                        row[SURFEL + ch] += v_vals[ch]
                    row[SURFEL + depth_channel] = 0.0
                    if square_channel >= 0:
                        row[SURFEL + square_channel] = 0.0


class _Composite(torch.autograd.Function):
    """(M [N, 9], centres [N, 2], opacities [N], values [N, C], means2d) -> (the sum of w
    values [H * W, C] with each pair's own depth (and its square) in the channels
    ``channels_z``, alpha [H * W],
    the largest blending weight [N]). ``means2d`` takes no part in the forward pass: its
    gradient is the screen-space one (surfels.screen_shifted's), for densification."""

    @staticmethod
    def forward(ctx, M, centres, opacities, values, means2d, state):
        tiles, channels_z, near = state
        splats = np.concatenate([_cpu._np(M), _cpu._np(centres), _cpu._np(opacities)[:, None]], 1)
        wide = _to_lanes(_cpu._np(values))
        pixels = tiles.width * tiles.height
        out, final_t = np.empty((pixels, wide.shape[1])), np.empty(pixels)
        last = np.empty(pixels, np.int64)
        at_intersections, peak = np.empty(len(tiles.owner)), np.empty(len(splats))
        _composite_fwd(
            tiles.layout(), splats, wide, channels_z, near, out, final_t, last, at_intersections
        )
        _max_rows(tiles.gaussian_start, tiles.slots, at_intersections, peak)
        ctx.state = (tiles, channels_z, near, splats, wide, out, final_t, last)
        ctx.like = (M, centres, opacities, values, means2d)
        C, dtype = values.shape[1], values.dtype
        summed = torch.from_numpy(np.ascontiguousarray(out[:, :C])).to(values.device, dtype)
        alpha = torch.from_numpy(1 - final_t).to(values.device, dtype)
        peak = torch.from_numpy(peak).to(values.device, dtype)
        ctx.mark_non_differentiable(peak)
        return summed, alpha, peak

    @staticmethod
    def backward(ctx, v_summed, v_alpha, _v_peak):
        tiles, channels_z, near, splats, wide, out, final_t, last = ctx.state
        pixels = len(final_t)
        v_out = np.zeros((pixels, wide.shape[1]))
        if v_summed is not None:
            v_out[:, : v_summed.shape[1]] = _pixels(v_summed, pixels)
        v_a = np.zeros(pixels) if v_alpha is None else _pixels(v_alpha, pixels)[:, 0]
        v_a = np.ascontiguousarray(v_a, np.float64)
        grads = _reused((len(tiles.owner), SURFEL + wide.shape[1]))
        _composite_bwd(
            tiles.layout(), splats, wide, channels_z, near, final_t, last, v_out, v_a, grads
        )
        per = np.empty((len(splats), grads.shape[1]))
        _sum_rows(tiles.gaussian_start, tiles.slots, grads, per)
        M, centres, opacities, values, means2d = ctx.like
        v_M = per[:, :9]
        # a shift of the disc across the image by (dx, dy) adds (dx, dy) M[2] to M's first
        # two rows and moves its centre by as much
        screen = np.stack(
            [
                (v_M[:, 0:3] * splats[:, 6:9]).sum(1) + per[:, CENTRE_X],
                (v_M[:, 3:6] * splats[:, 6:9]).sum(1) + per[:, CENTRE_Y],
            ],
            1,
        )
        C = values.shape[1]
        return (
            _back(v_M, M),
            _back(per[:, CENTRE_X : CENTRE_Y + 1], centres),
            _back(per[:, OPACITY], opacities),
            _back(per[:, SURFEL : SURFEL + C], values),
            _back(screen, means2d),
            None,
        )


def rasterize_surfels_cpu(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    camera: Camera,
    near: float,
    depth_squared: bool = False,
) -> Render:
    """``depth_squared``: the features' last channel is each pair's depth squared (what the
    depth-spread loss composites), whatever the features hold there."""
    follow_torch_threads()
    W, H, D = camera.width, camera.height, features.shape[1]
    boxes = surfel_boxes(means, quats, scales, camera, near)
    projection = _cpu.Projection(
        _cpu._np(boxes.means2d),
        _cpu._np(boxes.conics),
        _cpu._np(boxes.cov2d),
        _cpu._np(boxes.depths),
        np.zeros((len(means), 3)),
        boxes.valid.cpu().numpy(),
    )
    tiles = _cpu.intersect(projection, _cpu._np(opacities), W, H)
    means2d = _back(projection.means2d, means).requires_grad_(means.requires_grad)
    M = surfel_matrices(means, quats, scales, camera)
    centres = M[:, :2, 2] / M[:, 2:, 2]
    normals = surfel_normals(quats, means, camera)
    zeros = features.new_zeros(len(means), 1)
    values = torch.cat([features, zeros, normals], 1)
    summed, alpha, peak = _Composite.apply(
        M.reshape(-1, 9),
        centres,
        opacities,
        values,
        means2d,
        (tiles, (D, D - 1 if depth_squared else -1), near),
    )
    depth = summed[:, D] / alpha.clamp(min=_cpu.DEPTH_ALPHA_MIN)
    return Render(
        summed[:, :D].reshape(H, W, D),
        depth.reshape(H, W),
        alpha.reshape(H, W),
        summed[:, D + 1 :].reshape(H, W, 3),
        means2d,
        torch.from_numpy(tiles.visible).to(means.device),
        peak,
    )
