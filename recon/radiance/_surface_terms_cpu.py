"""Stage I's surface terms of one render on the CPU, compiled: the normal consistency, the depth
spread and the normal smoothness (losses.normal_loss, depth_spread_loss,
normal_smoothness_loss, the reference they are tested against and what runs on a GPU) in one
pass over the render's maps, and their gradients in two more, where PyTorch takes some sixty
operations over whole images each way.

Everything is computed in float64; the results come back in the maps' dtype. The passes go row
by row in parallel, each pixel writing only its own gradients (what a pixel's depth gets from
its neighbours' depth normals is gathered, not scattered), so a run repeats bit for bit.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from evcap.recon._threads import follow_torch_threads

NORMAL, SPREAD, SMOOTH = range(3)  # the terms, in the order they come back
EPS = 1e-12  # normalising (as F.normalize's eps)
FLOOR = 1e-6  # the depth and alpha floors of depth_spread_loss, the depth's of the smoothness
# a pixel's smoothness pairs: with the pixel after it in its row and column (it is the first),
# and with the one before (it is the second)
NEXT_ROW, NEXT_COL = (0, 1, 0, -1), (1, 0, -1, 0)


@numba.njit(cache=True, inline="always")
def _unit(x, y, z):
    norm = math.sqrt(x * x + y * y + z * z)
    d = max(norm, EPS)
    return x / d, y / d, z / d, d


@numba.njit(cache=True, inline="always")
def _unit_backward(x, y, z, d, gx, gy, gz):
    """The gradient at (x, y, z) of (x, y, z) / max(|.|, EPS), ``d`` that denominator."""
    if d <= EPS:
        return gx / d, gy / d, gz / d
    ux, uy, uz = x / d, y / d, z / d
    dot = ux * gx + uy * gy + uz * gz
    return (gx - ux * dot) / d, (gy - uy * dot) / d, (gz - uz * dot) / d


@numba.njit(cache=True, inline="always")
def _sign(x):
    return 1.0 if x > 0 else -1.0 if x < 0 else 0.0


@numba.njit(cache=True, inline="always")
def _point(depth, K, i, j):
    d = depth[i, j]
    return (j - K[2]) / K[0] * d, (i - K[3]) / K[1] * d, d


@numba.njit(cache=True, inline="always")
def _depth_normal(depth, K, i, j):
    """(defined, the unit normal of the depth's local gradients facing the camera (3), the
    cross product it normalises (3), its denominator, its sign, dx (3), dy (3))."""
    H, W = depth.shape
    ok = 0 < i < H - 1 and 0 < j < W - 1
    if ok:
        ok = (
            depth[i, j] > 0
            and depth[i, j + 1] > 0
            and depth[i, j - 1] > 0
            and depth[i + 1, j] > 0
            and depth[i - 1, j] > 0
        )
    if not ok:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    px, py, pz = _point(depth, K, i, j)
    ax, ay, az = _point(depth, K, i, j + 1)
    bx, by, bz = _point(depth, K, i, j - 1)
    dx0, dx1, dx2 = ax - bx, ay - by, az - bz
    ax, ay, az = _point(depth, K, i + 1, j)
    bx, by, bz = _point(depth, K, i - 1, j)
    dy0, dy1, dy2 = ax - bx, ay - by, az - bz
    c0 = dx1 * dy2 - dx2 * dy1
    c1 = dx2 * dy0 - dx0 * dy2
    c2 = dx0 * dy1 - dx1 * dy0
    n0, n1, n2, d = _unit(c0, c1, c2)
    s = -1.0 if n0 * px + n1 * py + n2 * pz > 0 else 1.0
    return True, s * n0, s * n1, s * n2, c0, c1, c2, d, s, dx0, dx1, dx2, dy0, dy1, dy2


@numba.njit(cache=True, inline="always")
def _pair_weight(depth, alpha, i, j, u, v, step):
    """The smoothness weight of pixels (i, j) and (u, v), the one after it (row or column)."""
    if not (alpha[i, j] > 0.5 and alpha[u, v] > 0.5):
        return 0.0
    return math.exp(-abs(depth[u, v] - depth[i, j]) / (step * max(depth[u, v], FLOOR)))


@numba.njit(cache=True, parallel=True)
def _prepare(normal, depth, alpha, step, unit, length, weights):
    """Each pixel's unit normal [H, W, 3] and its length before normalising (at least EPS),
    and the smoothness weights [H, W, 2] of its pairs with the pixel after it in its row and
    in its column (0 where there is none)."""
    H, W = depth.shape
    for row in numba.prange(H):
        i = np.int64(row)  # prange's index is unsigned: mixed with signed ints it turns float
        for j in range(W):
            x = _unit(normal[i, j, 0], normal[i, j, 1], normal[i, j, 2])
            unit[i, j, 0], unit[i, j, 1], unit[i, j, 2], length[i, j] = x
            weights[i, j, 0] = (
                _pair_weight(depth, alpha, i, j, i, j + 1, step) if j + 1 < W else 0.0
            )
            weights[i, j, 1] = (
                _pair_weight(depth, alpha, i, j, i + 1, j, step) if i + 1 < H else 0.0
            )


@numba.njit(cache=True, parallel=True)
def _forward(unit, depth, alpha, moment, weights, K, which, sums):
    """sums [H, 6] per row: the normal term's error and pixels, the spread's and its pixels,
    the smoothness's weighted differences and weights."""
    H, W = depth.shape
    for row in numba.prange(H):
        i = np.int64(row)
        for j in range(W):
            n0, n1, n2 = unit[i, j, 0], unit[i, j, 1], unit[i, j, 2]
            opaque = alpha[i, j] > 0.5
            if which[NORMAL] and opaque:
                ok, m0, m1, m2 = _depth_normal(depth, K, i, j)[:4]
                if ok:
                    sums[i, 0] += abs(n0 - m0) + abs(n1 - m1) + abs(n2 - m2)
                    sums[i, 1] += 1.0
            if which[SPREAD] and opaque:
                a = max(alpha[i, j], FLOOR)
                mean_sq = max(depth[i, j], FLOOR) ** 2
                relative = max(moment[i, j] / a - mean_sq, 0.0) / mean_sq
                sums[i, 2] += relative / (1 + relative)
                sums[i, 3] += 1.0
            if which[SMOOTH]:
                for side in range(2):
                    w = weights[i, j, side]
                    if w > 0:
                        u, v = i + side, j + 1 - side
                        diff = abs(unit[u, v, 0] - n0) + abs(unit[u, v, 1] - n1)
                        sums[i, 4] += (diff + abs(unit[u, v, 2] - n2)) * w
                        sums[i, 5] += w


@numba.njit(cache=True, parallel=True)
def _backward(
    normal,
    unit,
    length,
    depth,
    alpha,
    moment,
    weights,
    K,
    coeff,
    v_normal,
    v_depth,
    v_alpha,
    v_moment,
    v_dx,
    v_dy,
):
    """The gradients of coeff . (the three terms' sums) at each pixel's own maps, and of the
    normal term at the two differences [H, W, 3] each that made the pixel's depth normal (which
    _gather_depth turns into the depth's)."""
    H, W = depth.shape
    for row in numba.prange(H):
        i = np.int64(row)
        for j in range(W):
            n0, n1, n2 = unit[i, j, 0], unit[i, j, 1], unit[i, j, 2]
            g0 = g1 = g2 = 0.0  # d / d(the unit normal)
            opaque = alpha[i, j] > 0.5
            if coeff[NORMAL] != 0 and opaque:
                ok, m0, m1, m2, c0, c1, c2, d, s, a0, a1, a2, b0, b1, b2 = _depth_normal(
                    depth, K, i, j
                )
                if ok:
                    c = coeff[NORMAL]
                    e0, e1, e2 = c * _sign(n0 - m0), c * _sign(n1 - m1), c * _sign(n2 - m2)
                    g0, g1, g2 = g0 + e0, g1 + e1, g2 + e2
                    # the depth normal's side: d / d(the cross product it normalises), then
                    # with c = dx x dy, d/d(dx) = dy x h and d/d(dy) = h x dx
                    h0, h1, h2 = _unit_backward(c0, c1, c2, d, -s * e0, -s * e1, -s * e2)
                    v_dx[i, j, 0] = b1 * h2 - b2 * h1
                    v_dx[i, j, 1] = b2 * h0 - b0 * h2
                    v_dx[i, j, 2] = b0 * h1 - b1 * h0
                    v_dy[i, j, 0] = h1 * a2 - h2 * a1
                    v_dy[i, j, 1] = h2 * a0 - h0 * a2
                    v_dy[i, j, 2] = h0 * a1 - h1 * a0
            if coeff[SMOOTH] != 0:
                # as the first of a pair (with the pixel after it) and as the second
                for side in range(4):
                    u, v = i + NEXT_ROW[side], j + NEXT_COL[side]
                    if side < 2:
                        w = weights[i, j, side]
                    elif u >= 0 and v >= 0:
                        w = weights[u, v, side - 2]
                    else:
                        w = 0.0
                    if w > 0:
                        c = coeff[SMOOTH] * w
                        g0 += c * _sign(n0 - unit[u, v, 0])
                        g1 += c * _sign(n1 - unit[u, v, 1])
                        g2 += c * _sign(n2 - unit[u, v, 2])
            x0, x1, x2 = normal[i, j, 0], normal[i, j, 1], normal[i, j, 2]
            v0, v1, v2 = _unit_backward(x0, x1, x2, length[i, j], g0, g1, g2)
            v_normal[i, j, 0], v_normal[i, j, 1], v_normal[i, j, 2] = v0, v1, v2
            if coeff[SPREAD] != 0 and opaque:
                a = max(alpha[i, j], FLOOR)
                z = max(depth[i, j], FLOOR)
                mean_sq = z * z
                excess = moment[i, j] / a - mean_sq
                if excess >= 0:
                    relative = excess / mean_sq
                    g = coeff[SPREAD] / (1 + relative) ** 2  # d / d(relative)
                    v_moment[i, j] = g / (a * mean_sq)
                    if alpha[i, j] >= FLOOR:
                        v_alpha[i, j] = -g * moment[i, j] / (a * a * mean_sq)
                    if depth[i, j] >= FLOOR:
                        v_depth[i, j] = -g * moment[i, j] / (a * mean_sq * mean_sq) * 2 * z


@numba.njit(cache=True, parallel=True)
def _gather_depth(K, v_dx, v_dy, v_depth):
    """Each pixel's depth: its point enters its left and right neighbours' dx and the ones
    above and below's dy (p = ray * depth)."""
    H, W = v_depth.shape
    for row in numba.prange(H):
        i = np.int64(row)  # prange's index is unsigned: mixed with signed ints it turns float
        for j in range(W):
            g0 = g1 = g2 = 0.0
            if j > 0:
                g0 += v_dx[i, j - 1, 0]
                g1 += v_dx[i, j - 1, 1]
                g2 += v_dx[i, j - 1, 2]
            if j < W - 1:
                g0 -= v_dx[i, j + 1, 0]
                g1 -= v_dx[i, j + 1, 1]
                g2 -= v_dx[i, j + 1, 2]
            if i > 0:
                g0 += v_dy[i - 1, j, 0]
                g1 += v_dy[i - 1, j, 1]
                g2 += v_dy[i - 1, j, 2]
            if i < H - 1:
                g0 -= v_dy[i + 1, j, 0]
                g1 -= v_dy[i + 1, j, 1]
                g2 -= v_dy[i + 1, j, 2]
            v_depth[i, j] += (j - K[2]) / K[0] * g0 + (i - K[3]) / K[1] * g1 + g2


def _np(x: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().numpy(), dtype=np.float64)


class SurfaceTerms(torch.autograd.Function):
    """(normal [H, W, 3], depth [H, W], alpha [H, W], second moment [H, W], K [3, 3], the
    smoothness's step, which terms) -> [3]: normal consistency, depth spread, normal
    smoothness (0 where not asked for)."""

    @staticmethod
    def forward(ctx, normal, depth, alpha, moment, K, step, which):
        dtype = normal.dtype
        normal, depth, alpha, moment = (_np(x) for x in (normal, depth, alpha, moment))
        H, W = depth.shape
        k = np.array([float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])])
        flags = np.array(which, np.bool_)
        unit, length, weights = np.empty((H, W, 3)), np.empty((H, W)), np.empty((H, W, 2))
        _prepare(normal, depth, alpha, float(step), unit, length, weights)
        sums = np.zeros((H, 6))
        _forward(unit, depth, alpha, moment, weights, k, flags, sums)
        total = sums.sum(0)
        counts = np.maximum(total[1::2], 1.0)
        # d(term)/d(its sum): 1 / its pixels (or weights), 0 for a term not asked for
        scale = np.where(flags, 1 / counts, 0.0)
        ctx.state = (normal, unit, length, depth, alpha, moment, weights, k, scale, dtype)
        return torch.tensor(total[0::2] / counts, dtype=dtype)

    @staticmethod
    def backward(ctx, grad):
        normal, unit, length, depth, alpha, moment, weights, k, scale, dtype = ctx.state
        coeff = grad.detach().double().numpy() * scale
        H, W = depth.shape
        v_normal = np.empty((H, W, 3))
        v_depth, v_alpha, v_moment = np.zeros((H, W)), np.zeros((H, W)), np.zeros((H, W))
        v_dx, v_dy = np.zeros((H, W, 3)), np.zeros((H, W, 3))
        _backward(
            normal,
            unit,
            length,
            depth,
            alpha,
            moment,
            weights,
            k,
            coeff,
            v_normal,
            v_depth,
            v_alpha,
            v_moment,
            v_dx,
            v_dy,
        )
        if coeff[NORMAL] != 0:
            _gather_depth(k, v_dx, v_dy, v_depth)
        out = [torch.from_numpy(v).to(dtype) for v in (v_normal, v_depth, v_alpha, v_moment)]
        return (*out, None, None, None)


def surface_terms_cpu(
    normal: torch.Tensor,
    depth: torch.Tensor,
    alpha: torch.Tensor,
    moment: torch.Tensor | None,
    K: torch.Tensor,
    step: float,
    which: tuple[bool, bool, bool],
) -> torch.Tensor:
    follow_torch_threads()
    if moment is None:
        moment = torch.zeros_like(depth)
    return SurfaceTerms.apply(normal, depth, alpha, moment, K, step, which)
