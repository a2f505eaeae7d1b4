"""The compiled CPU rasterizer: the layout of the GPU rasterizers (3DGS, gsplat), in numba.

1. Projection: each Gaussian's centre, depth, 2D conic (EWA, exactly as
   ``_raster_torch.project``: the clamped Jacobian, 0.3 px added to the 2D covariance) and its
   normal in the camera frame (``rasterize.camera_normals``).
2. Tile intersection: each Gaussian's box where its alpha can reach 1/255 (the torch backend's
   box), the TILE_W x TILE_H tiles it covers; the Gaussians sorted once by depth and bucketed
   by tile with a counting sort, which keeps them in depth order within each tile.
3. Compositing, tiles in parallel: a tile's Gaussians copied side by side and listed per pixel
   row; along a row, each Gaussian only over the columns its ellipse reaches, its exp(-sigma)
   walked from column to column by products; each pixel front to back until its
   transmittance would fall to 1e-4, saving its final transmittance and last contributor.
4. The backward pass walks each pixel's list back to front from those two, recovering each
   transmittance by division. Each (tile, Gaussian) intersection has its own row of gradients
   (a tile's rows are contiguous and only its thread writes them); a second pass sums each
   Gaussian's rows in tile order. No atomics, and the same sums whatever the number of
   threads: a run repeats bit for bit.

Unlike on a GPU, work is cheaper per pixel than per (Gaussian, row): wide, short tiles
(64 x 8 measured 25 % faster than 16 x 16 at 173 x 130, and no slower at 800 x 800) give
fewer and longer runs along the rows.

The kernels compute in float64 whatever the inputs' dtype (exact gradient checks in tests, and
no precision lost in the transmittance's division); results come back in the inputs' dtype and
device. They run on as many threads as torch is set to use. Gradients reach every input but
the intrinsics ``K`` (as in gsplat).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numba
import numpy as np
import torch

from evcap.recon._threads import follow_torch_threads
from evcap.recon.raster.rasterize import Camera, Render

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
EPS2D = 0.3  # added to the 2D covariance (a pixel's footprint), as gsplat and 3DGS do
TILE_W, TILE_H = 64, 8  # a tile's width and height in pixels
CHUNKS = 64  # the Gaussians go to the threads in this many runs (projection, intersection)
# per intersection: d/d(mean x, mean y, conic a, b, c, opacity), then d/d(each value channel)
SPLAT = 6
# values travel padded with zeros to a multiple of this many channels: the compiler's vector
# loops over them then have no scalar remainder (8 % faster at 7 channels, measured)
LANES = 8
# 10 % faster compositing; no flag that assumes finite values, so the checks for them stay
FASTMATH = {"contract", "arcp", "nsz", "afn", "reassoc"}


# -- projection ------------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _rotmat(qw, qx, qy, qz):
    """Row-major rotation matrix of a unit quaternion, as a flat tuple."""
    return (
        1 - 2 * (qy * qy + qz * qz),
        2 * (qx * qy - qw * qz),
        2 * (qx * qz + qw * qy),
        2 * (qx * qy + qw * qz),
        1 - 2 * (qx * qx + qz * qz),
        2 * (qy * qz - qw * qx),
        2 * (qx * qz - qw * qy),
        2 * (qy * qz + qw * qx),
        1 - 2 * (qx * qx + qy * qy),
    )


@numba.njit(cache=True, inline="always")
def _unit_quat(quats, i):
    n = math.sqrt(quats[i, 0] ** 2 + quats[i, 1] ** 2 + quats[i, 2] ** 2 + quats[i, 3] ** 2)
    n = max(n, 1e-12)
    return quats[i, 0] / n, quats[i, 1] / n, quats[i, 2] / n, quats[i, 3] / n, n


@numba.njit(cache=True, inline="always")
def _flattest(scales, i):
    """The axis of the smallest scale (the first of equal ones, as torch's argmin)."""
    k = 0
    for j in (1, 2):
        if scales[i, j] < scales[i, k]:
            k = j
    return k


@numba.njit(cache=True, inline="always")
def _covariances(quats, scales, R, i, Sigma, cov, RM):
    """Rg = R(q); into Sigma the world covariance M M^T with M = Rg diag(s), into RM = R M,
    into cov the camera's R Sigma R^T = RM RM^T."""
    qw, qx, qy, qz, _ = _unit_quat(quats, i)
    Rg = _rotmat(qw, qx, qy, qz)
    s0, s1, s2 = scales[i, 0], scales[i, 1], scales[i, 2]
    for r in range(3):
        for c in range(3):
            RM[r, c] = (R[r, 0] * Rg[c] + R[r, 1] * Rg[3 + c] + R[r, 2] * Rg[6 + c]) * (
                s0 if c == 0 else s1 if c == 1 else s2
            )
    for r in range(3):
        for c in range(r, 3):
            m = Rg[3 * r] * Rg[3 * c] * s0 * s0 + Rg[3 * r + 1] * Rg[3 * c + 1] * s1 * s1
            Sigma[r, c] = Sigma[c, r] = m + Rg[3 * r + 2] * Rg[3 * c + 2] * s2 * s2
            v = RM[r, 0] * RM[c, 0] + RM[r, 1] * RM[c, 1] + RM[r, 2] * RM[c, 2]
            cov[r, c] = cov[c, r] = v
    return Rg


@numba.njit(cache=True, inline="always")
def _limits(f, c, size):
    """The range of x / z (or y / z) the Jacobian is taken in: the view and 30 % around it."""
    margin = 0.3 * 0.5 * size / f
    return -(c + 0.5) / f - margin, (size - 0.5 - c) / f + margin


@numba.njit(cache=True, inline="always")
def _in_camera(R, t, means, i):
    x = R[0, 0] * means[i, 0] + R[0, 1] * means[i, 1] + R[0, 2] * means[i, 2] + t[0]
    y = R[1, 0] * means[i, 0] + R[1, 1] * means[i, 1] + R[1, 2] * means[i, 2] + t[1]
    z = R[2, 0] * means[i, 0] + R[2, 1] * means[i, 1] + R[2, 2] * means[i, 2] + t[2]
    return x, y, z


@numba.njit(cache=True, inline="always")
def _normal_sign(R, Rg, k, x, y, z):
    """-1 where the camera-frame normal (column k of Rg, rotated) points away from the camera."""
    facing = 0.0
    for r in range(3):
        n = R[r, 0] * Rg[k] + R[r, 1] * Rg[3 + k] + R[r, 2] * Rg[6 + k]
        facing += n * (x if r == 0 else y if r == 1 else z)
    return -1.0 if facing > 0 else 1.0


@numba.njit(cache=True, parallel=True)
def _project_fwd(means, quats, scales, view):
    """(means2d, conics, cov2d, depths, camera-frame normals, valid)."""
    R, t, fx, fy, cx, cy, width, height, near = view
    n = means.shape[0]
    means2d, conics, cov2d = np.empty((n, 2)), np.empty((n, 3)), np.empty((n, 3))
    depths, normals, valid = np.empty(n), np.empty((n, 3)), np.empty(n, np.bool_)
    lim_x, lim_y = _limits(fx, cx, width), _limits(fy, cy, height)
    for chunk in numba.prange(CHUNKS):
        Sigma, cov, RM = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
        for i in range(chunk * n // CHUNKS, (chunk + 1) * n // CHUNKS):
            Rg = _covariances(quats, scales, R, i, Sigma, cov, RM)
            x, y, z = _in_camera(R, t, means, i)
            ok = z > near
            zs = z if ok else 1.0
            tx = zs * min(max(x / zs, lim_x[0]), lim_x[1])
            ty = zs * min(max(y / zs, lim_y[0]), lim_y[1])
            j00, j02 = fx / zs, -fx * tx / (zs * zs)
            j11, j12 = fy / zs, -fy * ty / (zs * zs)
            cxx = j00 * j00 * cov[0, 0] + 2 * j00 * j02 * cov[0, 2] + j02 * j02 * cov[2, 2] + EPS2D
            cxy = j00 * j11 * cov[0, 1] + j00 * j12 * cov[0, 2] + j02 * j11 * cov[1, 2]
            cxy += j02 * j12 * cov[2, 2]
            cyy = j11 * j11 * cov[1, 1] + 2 * j11 * j12 * cov[1, 2] + j12 * j12 * cov[2, 2] + EPS2D
            det = cxx * cyy - cxy * cxy
            ok = ok and det > 0 and math.isfinite(det)
            if not ok:
                det = 1.0
            conics[i, 0], conics[i, 1], conics[i, 2] = cyy / det, -cxy / det, cxx / det
            cov2d[i, 0], cov2d[i, 1], cov2d[i, 2] = cxx, cxy, cyy
            means2d[i, 0] = fx * x / zs + cx
            means2d[i, 1] = fy * y / zs + cy
            depths[i] = z
            valid[i] = ok
            k = _flattest(scales, i)
            sign = _normal_sign(R, Rg, k, x, y, z)
            for r in range(3):
                normals[i, r] = sign * (R[r, 0] * Rg[k] + R[r, 1] * Rg[3 + k] + R[r, 2] * Rg[6 + k])
    return means2d, conics, cov2d, depths, normals, valid


@numba.njit(cache=True, parallel=True)
def _project_bwd(
    means, quats, scales, view, conics, valid, v_means2d, v_conics, v_depths, v_normals
):
    """Gradients of the projection: (means, quats, scales, and each Gaussian's d/d(R, t)
    [N, 12], for the caller to sum)."""
    R, t, fx, fy, cx, cy, width, height, near = view
    n = means.shape[0]
    v_means, v_quats, v_scales = np.zeros((n, 3)), np.zeros((n, 4)), np.zeros((n, 3))
    v_view = np.zeros((n, 12))
    lim_x, lim_y = _limits(fx, cx, width), _limits(fy, cy, height)
    for chunk in numba.prange(CHUNKS):
        Sigma, cov, RM = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
        v_cov, v_Sigma, A = np.zeros((3, 3)), np.empty((3, 3)), np.empty((3, 3))
        vRg = np.empty(9)
        for i in range(chunk * n // CHUNKS, (chunk + 1) * n // CHUNKS):
            vu, vv, vd = v_means2d[i, 0], v_means2d[i, 1], v_depths[i]
            va, vb, vc = v_conics[i, 0], v_conics[i, 1] * 0.5, v_conics[i, 2]
            vn = (v_normals[i, 0], v_normals[i, 1], v_normals[i, 2])
            reach = abs(vu) + abs(vv) + abs(vd) + abs(va) + abs(vb) + abs(vc)
            if reach + abs(vn[0]) + abs(vn[1]) + abs(vn[2]) == 0:
                continue  # out of view or hidden: nothing reaches it
            Rg = _covariances(quats, scales, R, i, Sigma, cov, RM)
            x, y, z = _in_camera(R, t, means, i)
            vRg[:] = 0.0
            if not valid[i]:
                # the centre and depth only, with z held at 1 (as the forward pass did)
                vp = (fx * vu, fy * vv, vd)
            else:
                ux, uy = x / z, y / z
                tx = z * min(max(ux, lim_x[0]), lim_x[1])
                ty = z * min(max(uy, lim_y[0]), lim_y[1])
                z2 = z * z
                j00, j02, j11, j12 = fx / z, -fx * tx / z2, fy / z, -fy * ty / z2
                # conic = inverse of the 2D covariance: dL/dcov2d = G = -C V C
                a, b, c = conics[i, 0], conics[i, 1], conics[i, 2]
                m00, m01 = a * va + b * vb, a * vb + b * vc
                m10, m11 = b * va + c * vb, b * vb + c * vc
                g00, g01, g11 = -(m00 * a + m01 * b), -(m00 * b + m01 * c), -(m10 * b + m11 * c)
                # 2D covariance = J cov J^T, J = [[j00, 0, j02], [0, j11, j12]]:
                # v_cov = J^T G J, v_J = 2 G J cov
                v_cov[0, 0] = g00 * j00 * j00
                v_cov[0, 1] = v_cov[1, 0] = g01 * j00 * j11
                v_cov[0, 2] = v_cov[2, 0] = (g00 * j02 + g01 * j12) * j00
                v_cov[1, 1] = g11 * j11 * j11
                v_cov[1, 2] = v_cov[2, 1] = (g01 * j02 + g11 * j12) * j11
                v_cov[2, 2] = g00 * j02 * j02 + 2 * g01 * j02 * j12 + g11 * j12 * j12
                gj0 = (g00 * j00, g01 * j11, g00 * j02 + g01 * j12)  # rows of G J
                gj1 = (g01 * j00, g11 * j11, g01 * j02 + g11 * j12)
                vj00 = 2 * (gj0[0] * cov[0, 0] + gj0[1] * cov[1, 0] + gj0[2] * cov[2, 0])
                vj02 = 2 * (gj0[0] * cov[0, 2] + gj0[1] * cov[1, 2] + gj0[2] * cov[2, 2])
                vj11 = 2 * (gj1[0] * cov[0, 1] + gj1[1] * cov[1, 1] + gj1[2] * cov[2, 1])
                vj12 = 2 * (gj1[0] * cov[0, 2] + gj1[1] * cov[1, 2] + gj1[2] * cov[2, 2])
                v_z = -fx / z2 * vj00 - fy / z2 * vj11
                v_z += 2 * fx * tx / (z2 * z) * vj02 + 2 * fy * ty / (z2 * z) * vj12
                v_tx, v_ty = -fx / z2 * vj02, -fy / z2 * vj12
                v_x, v_y = fx / z * vu, fy / z * vv
                v_z += -fx * x / z2 * vu - fy * y / z2 * vv
                # tx = z clamp(x / z): x's where it is not clamped, z's where it is
                if lim_x[0] <= ux <= lim_x[1]:
                    v_x += v_tx
                else:
                    v_z += min(max(ux, lim_x[0]), lim_x[1]) * v_tx
                if lim_y[0] <= uy <= lim_y[1]:
                    v_y += v_ty
                else:
                    v_z += min(max(uy, lim_y[0]), lim_y[1]) * v_ty
                vp = (v_x, v_y, v_z + vd)
                # cov = R Sigma R^T: v_Sigma = R^T v_cov R (A = v_cov R), and d/dR = 2 A Sigma
                for r in range(3):
                    for q in range(3):
                        A[r, q] = (
                            v_cov[r, 0] * R[0, q] + v_cov[r, 1] * R[1, q] + v_cov[r, 2] * R[2, q]
                        )
                for r in range(3):
                    for q in range(3):
                        v_Sigma[r, q] = R[0, r] * A[0, q] + R[1, r] * A[1, q] + R[2, r] * A[2, q]
                        w = A[r, 0] * Sigma[0, q] + A[r, 1] * Sigma[1, q] + A[r, 2] * Sigma[2, q]
                        v_view[i, 3 * r + q] = 2 * w
                # Sigma = M M^T: v_M = 2 v_Sigma M; M = Rg diag(s)
                for k in range(3):
                    sk = scales[i, k]
                    for r in range(3):
                        vM = (
                            2
                            * sk
                            * (
                                v_Sigma[r, 0] * Rg[k]
                                + v_Sigma[r, 1] * Rg[3 + k]
                                + v_Sigma[r, 2] * Rg[6 + k]
                            )
                        )
                        v_scales[i, k] += vM * Rg[3 * r + k]
                        vRg[3 * r + k] = vM * sk
            # the normal: sign * R Rg[:, k]
            k = _flattest(scales, i)
            sign = _normal_sign(R, Rg, k, x, y, z)
            for r in range(3):
                for m in range(3):
                    vRg[3 * m + k] += sign * R[r, m] * vn[r]
            # p = R m + t
            for r in range(3):
                v_means[i, r] = R[0, r] * vp[0] + R[1, r] * vp[1] + R[2, r] * vp[2]
                for q in range(3):
                    v_view[i, 3 * r + q] += vp[r] * means[i, q] + sign * vn[r] * Rg[3 * q + k]
                v_view[i, 9 + r] = vp[r]
            # Rg of the unit quaternion, then the normalisation
            qw, qx, qy, qz, qn = _unit_quat(quats, i)
            v = vRg
            gw = 2 * (-qz * v[1] + qy * v[2] + qz * v[3] - qx * v[5] - qy * v[6] + qx * v[7])
            gx = 2 * (qy * v[1] + qz * v[2] + qy * v[3] - 2 * qx * v[4] - qw * v[5] + qz * v[6])
            gx += 2 * (qw * v[7] - 2 * qx * v[8])
            gy = 2 * (-2 * qy * v[0] + qx * v[1] + qw * v[2] + qx * v[3] + qz * v[5] - qw * v[6])
            gy += 2 * (qz * v[7] - 2 * qy * v[8])
            gz = 2 * (-2 * qz * v[0] - qw * v[1] + qx * v[2] + qw * v[3] - 2 * qz * v[4])
            gz += 2 * (qy * v[5] + qx * v[6] + qy * v[7])
            # q / |q| (|q| clamped at 1e-12, below which it is a plain scaling)
            dot = gw * qw + gx * qx + gy * qy + gz * qz if qn > 1e-12 else 0.0
            v_quats[i, 0] = (gw - qw * dot) / qn
            v_quats[i, 1] = (gx - qx * dot) / qn
            v_quats[i, 2] = (gy - qy * dot) / qn
            v_quats[i, 3] = (gz - qz * dot) / qn
    return v_means, v_quats, v_scales, v_view


# -- tile intersection -----------------------------------------------------------------------


@numba.njit(cache=True, parallel=True)
def _boxes(means2d, cov2d, valid, opacities, width, height, box):
    """Each Gaussian's pixels where its alpha can reach 1/255 (the torch backend's box):
    box [N, 4] = first and last column, first and last row; empty when last < first."""
    for i in numba.prange(means2d.shape[0]):
        box[i, 0], box[i, 1], box[i, 2], box[i, 3] = 0, -1, 0, -1
        o = min(opacities[i], 1.0)
        if not valid[i] or not o > ALPHA_MIN:
            continue
        k2 = 2 * math.log(max(o / ALPHA_MIN, 1.0))
        hx = math.sqrt(k2 * max(cov2d[i, 0], 0.0))
        hy = math.sqrt(k2 * max(cov2d[i, 2], 0.0))
        mx, my = means2d[i, 0], means2d[i, 1]
        if not (
            math.isfinite(mx) and math.isfinite(my) and math.isfinite(hx) and math.isfinite(hy)
        ):
            continue
        box[i, 0] = min(max(math.ceil(mx - hx), 0), width)
        box[i, 1] = min(max(math.floor(mx + hx), -1), width - 1)
        box[i, 2] = min(max(math.ceil(my - hy), 0), height)
        box[i, 3] = min(max(math.floor(my + hy), -1), height - 1)


@numba.njit(cache=True, parallel=True)
def _bucket(box, order, width, height, tile_w, tile_h):
    """(tile_start [tiles + 1], the Gaussian of each intersection [M] (by tile, in ``order``
    within each), gaussian_start [N + 1], the intersections of each Gaussian [M]). A counting
    sort in CHUNKS runs of ``order``, each with its own count per tile and its own place in
    each tile's list, so that the runs fill in parallel and the result is the serial one."""
    n = box.shape[0]
    tiles_x = (width + tile_w - 1) // tile_w
    tiles = tiles_x * ((height + tile_h - 1) // tile_h)
    rect = np.zeros((n, 4), np.int64)  # first and last tile column, first and last tile row
    count = np.zeros(n, np.int64)
    for i in numba.prange(n):
        if box[i, 1] >= box[i, 0] and box[i, 3] >= box[i, 2]:
            for c in range(4):
                rect[i, c] = box[i, c] // (tile_w if c < 2 else tile_h)
            count[i] = (rect[i, 1] - rect[i, 0] + 1) * (rect[i, 3] - rect[i, 2] + 1)
    gaussian_start = np.zeros(n + 1, np.int64)
    gaussian_start[1:] = np.cumsum(count)
    per_run = np.zeros((CHUNKS, tiles), np.int64)
    for run in numba.prange(CHUNKS):
        for q in range(run * n // CHUNKS, (run + 1) * n // CHUNKS):
            i = order[q]
            for ty in range(rect[i, 2], rect[i, 3] + 1 if count[i] else rect[i, 2]):
                for tx in range(rect[i, 0], rect[i, 1] + 1):
                    per_run[run, ty * tiles_x + tx] += 1
    tile_start = np.zeros(tiles + 1, np.int64)
    cursors = np.empty((CHUNKS, tiles), np.int64)
    for t in range(tiles):
        at = tile_start[t]
        for run in range(CHUNKS):
            cursors[run, t] = at
            at += per_run[run, t]
        tile_start[t + 1] = at
    owner = np.empty(gaussian_start[n], np.int64)
    slots = np.empty(gaussian_start[n], np.int64)
    for run in numba.prange(CHUNKS):
        cursor = cursors[run]
        for q in range(run * n // CHUNKS, (run + 1) * n // CHUNKS):
            i = order[q]
            j = gaussian_start[i]
            for ty in range(rect[i, 2], rect[i, 3] + 1 if count[i] else rect[i, 2]):
                for tx in range(rect[i, 0], rect[i, 1] + 1):
                    t = ty * tiles_x + tx
                    owner[cursor[t]] = i
                    slots[j] = cursor[t]
                    cursor[t] += 1
                    j += 1
    return tile_start, owner, gaussian_start, slots


# -- compositing -----------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _tile_area(layout, t):
    """(first column, first row, columns, rows) of tile t."""
    _, _, _, width, height, tile_w, tile_h, _ = layout
    tiles_x = (width + tile_w - 1) // tile_w
    x0, y0 = (t % tiles_x) * tile_w, (t // tiles_x) * tile_h
    return x0, y0, min(tile_w, width - x0), min(tile_h, height - y0)


@numba.njit(cache=True)
def _share(layout, worker):
    """The tiles one of the threads takes: by estimated cost (Gaussians times pixels), dealt
    out in turn, so that the threads finish together (a small image has few tiles)."""
    tile_start, workers = layout[0], layout[-1]
    n = len(tile_start) - 1
    cost = np.empty(n)
    for t in range(n):
        _, _, cols, rows = _tile_area(layout, t)
        cost[t] = (tile_start[t + 1] - tile_start[t] + 1) * rows * cols
    return np.argsort(-cost, kind="mergesort")[worker::workers]


# a tile's copy of its Gaussians: the splat (centre, conic, opacity), the sigma beyond which
# alpha is under 1/255 (with a margin: the exact test on alpha follows), what the columns a
# row's ellipse covers need (b / a, (b^2 - a c) / a^2, 2 cut / a), exp(-a), the box's columns
(
    MEAN_X,
    MEAN_Y,
    CONIC_A,
    CONIC_B,
    CONIC_C,
    OPACITY,
    CUT,
    B_OVER_A,
    SPAN_DY2,
    SPAN_1,
    EXP_A,
    BOX_X0,
    BOX_X1,
) = range(13)


@numba.njit(cache=True, parallel=True)
def _splat_terms(splats):
    """[N, 11]: each splat's columns MEAN_X..EXP_A (the divisions, log and exp done once)."""
    terms = np.empty((splats.shape[0], 11))
    for g in numba.prange(splats.shape[0]):
        a, b, c, o = splats[g, 2], splats[g, 3], splats[g, 4], splats[g, 5]
        cut = math.log(max(o, 1e-300) / ALPHA_MIN) + 1e-6
        for col in range(SPLAT):
            terms[g, col] = splats[g, col]
        terms[g, CUT] = cut
        terms[g, B_OVER_A], terms[g, SPAN_DY2], terms[g, SPAN_1] = (
            b / a,
            (b * b - a * c) / (a * a),
            2 * cut / a,
        )
        terms[g, EXP_A] = math.exp(-a)
    return terms


@numba.njit(cache=True, inline="always")
def _gather(layout, t, terms, values, local, vals, rows, row_len):
    """Tile t's Gaussians side by side: local [k] (the columns MEAN_X..BOX_X1), vals [k]
    their values; rows [r, :row_len[r]] = those (k) whose box covers the tile's row r, front
    to back."""
    tile_start, owner, box = layout[0], layout[1], layout[2]
    y0, tile_h = _tile_area(layout, t)[1], layout[6]
    row_len[:] = 0
    for k in range(tile_start[t + 1] - tile_start[t]):
        g = owner[tile_start[t] + k]
        for c in range(BOX_X0):
            local[k, c] = terms[g, c]
        local[k, BOX_X0], local[k, BOX_X1] = box[g, 0], box[g, 1]
        for c in range(values.shape[1]):
            vals[k, c] = values[g, c]
        for r in range(max(box[g, 2] - y0, 0), min(box[g, 3] - y0, tile_h - 1) + 1):
            rows[r, row_len[r]] = k
            row_len[r] += 1


@numba.njit(cache=True, inline="always", fastmath=FASTMATH)
def _span(local, k, py, x_first, x_last):
    """The columns of row ``py`` in [x_first, x_last] where Gaussian k's sigma can be under
    its cut-off: between the roots of 0.5 a dx^2 + b dy dx + 0.5 c dy^2 = cut, widened a
    little."""
    dy = py - local[k, MEAN_Y]
    half2 = local[k, SPAN_DY2] * dy * dy + local[k, SPAN_1]
    if not half2 >= 0:
        return 0, -1
    half = math.sqrt(half2) + 1e-3
    mid = local[k, MEAN_X] - local[k, B_OVER_A] * dy
    lo = max(x_first, local[k, BOX_X0], math.ceil(mid - half))
    hi = min(x_last, local[k, BOX_X1], math.floor(mid + half))
    return int(lo), int(hi)


@numba.njit(cache=True, inline="always", fastmath=FASTMATH)
def _row_terms(local, k, py):
    """What Gaussian k's sigma along row ``py`` needs: sigma(px) = (ha dx + bdy) dx + hcdy2
    with dx = px - mean x."""
    dy = py - local[k, MEAN_Y]
    return (
        local[k, MEAN_X],
        0.5 * local[k, CONIC_A],
        local[k, CONIC_B] * dy,
        0.5 * local[k, CONIC_C] * dy * dy,
    )


@numba.njit(cache=True, inline="always", fastmath=FASTMATH)
def _exp_walk(local, k, mx, ha, bdy, hcdy2, lo, hi):
    """exp(-sigma) along a row from column lo, by two products a column: (whether to walk,
    exp(-sigma(lo)), its ratio to the next column's, the ratio's own ratio). Walked where
    the Gaussian is at least a pixel wide across the row (ha <= 0.5: the ratios stay near 1)
    and the row long enough to gain from it; elsewhere an exp a pixel."""
    if ha > 0.5 or hi - lo < 2:
        return False, 1.0, 1.0, 1.0
    dx = lo - mx
    g = math.exp(-((ha * dx + bdy) * dx + hcdy2))
    return True, g, math.exp(-(ha * (2 * dx + 1) + bdy)), local[k, EXP_A]


@numba.njit(cache=True, inline="always")
def _tile_buffers(layout, t, channels, columns):
    """A tile's copies of its splats (``columns`` each) and values, its rows' lists."""
    tile_start, tile_h = layout[0], layout[6]
    n = tile_start[t + 1] - tile_start[t]
    return (
        np.empty((n, columns)),
        np.empty((n, channels)),
        np.empty((tile_h, n), np.int64),
        np.empty(tile_h, np.int64),
    )


@numba.njit(cache=True, parallel=True, fastmath=FASTMATH)
def _composite_fwd(layout, terms, values, out, final_t, last, peak):
    """Per pixel: out = the sum of w values, final_t = its transmittance, last = how many
    entries of its row's list it went through; per intersection: peak = its largest w (a
    tile is one thread's: no two write one entry). A tile's row at a time, Gaussian by
    Gaussian over the columns each covers, front to back."""
    tile_start, width, workers = layout[0], layout[3], layout[-1]
    channels = values.shape[1]
    for worker in numba.prange(workers):
        for t in _share(layout, worker):
            s = tile_start[t]
            peak[s : tile_start[t + 1]] = 0.0
            local, vals, rows, row_len = _tile_buffers(layout, t, channels, BOX_X1 + 1)
            _gather(layout, t, terms, values, local, vals, rows, row_len)
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
                    lo, hi = _span(local, k, py, x0, x0 + cols - 1)
                    mx, ha, bdy, hcdy2 = _row_terms(local, k, py)
                    o, cut = local[k, OPACITY], local[k, CUT]
                    walking, walk, ratio, ratio_step = _exp_walk(
                        local, k, mx, ha, bdy, hcdy2, lo, hi
                    )
                    top = 0.0
                    for px in range(lo, hi + 1):
                        g = walk
                        walk *= ratio
                        ratio *= ratio_step
                        i = np.uint64(px - x0)
                        if done[i]:
                            continue
                        dx = px - mx
                        sigma = (ha * dx + bdy) * dx + hcdy2
                        if sigma < 0 or sigma > cut:
                            continue
                        if not walking:
                            g = math.exp(-sigma)
                        alpha = min(ALPHA_MAX, o * g)
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
def _composite_bwd(layout, terms, values, final_t, last, v_out, v_alpha, grads):
    """Each intersection's gradients into its row of ``grads`` [M, SPLAT + channels]; each
    pixel's list walked back to front from its final transmittance and last entry."""
    tile_start, width, workers = layout[0], layout[3], layout[-1]
    channels = values.shape[1]
    for worker in numba.prange(workers):
        for t in _share(layout, worker):
            s = tile_start[t]
            grads[s : tile_start[t + 1]] = 0.0
            local, vals, rows, row_len = _tile_buffers(layout, t, channels, BOX_X1 + 1)
            _gather(layout, t, terms, values, local, vals, rows, row_len)
            x0, y0, cols, tile_rows = _tile_area(layout, t)
            T, n, v_end = np.empty(cols), np.empty(cols, np.int64), np.empty(cols)
            v_row = np.empty((cols, channels))
            # the gradient of a pixel against what the Gaussians behind the current one put
            # in it: their colors only ever meet the gradient in this dot product
            behind = np.empty(cols)
            v_vals = np.empty(channels)
            for r in range(tile_rows):
                p0 = (y0 + r) * width + x0
                behind[:] = 0.0
                for i in range(cols):
                    T[i], n[i] = final_t[p0 + i], last[p0 + i]
                    # d alpha_pixel / d alpha_k = T_final / (1 - alpha_k)
                    v_end[i] = v_alpha[p0 + i] * final_t[p0 + i]
                    v_row[i] = v_out[p0 + i]
                for j in range(n.max() - 1, -1, -1):
                    k = np.uint64(rows[r, j])  # unsigned: no checks for negative indices
                    lo, hi = _span(local, k, y0 + r, x0, x0 + cols - 1)
                    mx, ha, bdy, hcdy2 = _row_terms(local, k, y0 + r)
                    o, cut = local[k, OPACITY], local[k, CUT]
                    a, b, c = local[k, CONIC_A], local[k, CONIC_B], local[k, CONIC_C]
                    dy = y0 + r - local[k, MEAN_Y]
                    v_mx = v_my = v_a = v_b = v_c = v_o = 0.0
                    v_vals[:] = 0.0
                    walking, walk, ratio, ratio_step = _exp_walk(
                        local, k, mx, ha, bdy, hcdy2, lo, hi
                    )
                    for px in range(lo, hi + 1):
                        g = walk
                        walk *= ratio
                        ratio *= ratio_step
                        i = np.uint64(px - x0)
                        if j >= n[i]:
                            continue
                        dx = px - mx
                        sigma = (ha * dx + bdy) * dx + hcdy2
                        if sigma < 0 or sigma > cut:
                            continue
                        if not walking:
                            g = math.exp(-sigma)
                        alpha = min(ALPHA_MAX, o * g)
                        if alpha < ALPHA_MIN:
                            continue
                        keep = 1 / (1 - alpha)
                        T[i] *= keep
                        w = alpha * T[i]
                        seen = 0.0  # the pixel's gradient against this Gaussian's color
                        for ch in range(channels):
                            v_vals[ch] += w * v_row[i, ch]
                            seen += v_row[i, ch] * vals[k, ch]
                        v_alpha_k = (v_end[i] - behind[i]) * keep + seen * T[i]
                        behind[i] += seen * w
                        if o * g <= ALPHA_MAX:  # else alpha is clamped: no gradient through it
                            v_o += v_alpha_k * g
                            v_sigma = -v_alpha_k * alpha
                            v_mx -= v_sigma * (a * dx + b * dy)
                            v_my -= v_sigma * (b * dx + c * dy)
                            v_a += 0.5 * v_sigma * dx * dx
                            v_b += v_sigma * dx * dy
                            v_c += 0.5 * v_sigma * dy * dy
                    row = grads[s + k]
                    row[0] += v_mx
                    row[1] += v_my
                    row[2] += v_a
                    row[3] += v_b
                    row[4] += v_c
                    row[5] += v_o
                    for ch in range(channels):
                        row[SPLAT + ch] += v_vals[ch]


@numba.njit(cache=True, parallel=True)
def _max_rows(gaussian_start, slots, peak, out):
    """out[g] = the largest of Gaussian g's intersections' ``peak`` (0 for none)."""
    for g in numba.prange(len(gaussian_start) - 1):
        top = 0.0
        for j in range(gaussian_start[g], gaussian_start[g + 1]):
            top = max(top, peak[slots[j]])
        out[g] = top


@numba.njit(cache=True, parallel=True)
def _sum_rows(gaussian_start, slots, grads, out):
    """out[g] = the sum of Gaussian g's intersection rows, in tile order."""
    for g in numba.prange(len(gaussian_start) - 1):
        for c in range(grads.shape[1]):
            out[g, c] = 0.0
        for j in range(gaussian_start[g], gaussian_start[g + 1]):
            for c in range(grads.shape[1]):
                out[g, c] += grads[slots[j], c]


# -- the stages, on arrays ---------------------------------------------------------------------


def _np(x: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().cpu().numpy(), dtype=np.float64)


def camera_arrays(camera: Camera, near: float) -> tuple:
    """What the projection kernels take of a camera."""
    view = _np(camera.viewmat)
    K = _np(camera.K)
    return (
        view[:3, :3].copy(),
        view[:3, 3].copy(),
        K[0, 0],
        K[1, 1],
        K[0, 2],
        K[1, 2],
        camera.width,
        camera.height,
        near,
    )


@dataclass
class Projection:
    """Each Gaussian in the image: float64 arrays."""

    means2d: np.ndarray  # [N, 2] pixels
    conics: np.ndarray  # [N, 3] inverse 2D covariance (a, b, c)
    cov2d: np.ndarray  # [N, 3] (xx, xy, yy)
    depths: np.ndarray  # [N] camera z
    normals: np.ndarray  # [N, 3] camera frame, facing the camera
    valid: np.ndarray  # [N] bool: in front of the camera with a proper footprint


def project(means: np.ndarray, quats: np.ndarray, scales: np.ndarray, view: tuple) -> Projection:
    return Projection(*_project_fwd(means, quats, scales, view))


def project_backward(
    means: np.ndarray,
    quats: np.ndarray,
    scales: np.ndarray,
    view: tuple,
    projection: Projection,
    v_means2d: np.ndarray,
    v_conics: np.ndarray,
    v_depths: np.ndarray,
    v_normals: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """d/d(means, quats, scales) and each Gaussian's part of d/d(viewmat) [N, 12] (summed by
    view_gradient) from d/d(the projection's outputs)."""
    v_means, v_quats, v_scales, per = _project_bwd(
        means,
        quats,
        scales,
        view,
        projection.conics,
        projection.valid,
        v_means2d,
        v_conics,
        v_depths,
        v_normals,
    )
    return v_means, v_quats, v_scales, per


def view_gradient(per_gaussian: np.ndarray) -> np.ndarray:
    """[4, 4] d/d(viewmat) from project_backward's [N, 12] per Gaussian."""
    total = per_gaussian.sum(0)
    v_view = np.zeros((4, 4))
    v_view[:3, :3] = total[:9].reshape(3, 3)
    v_view[:3, 3] = total[9:]
    return v_view


@dataclass
class Tiles:
    """Which Gaussians each tile holds, front to back, and where each Gaussian's are."""

    width: int
    height: int
    box: np.ndarray  # [N, 4] each Gaussian's pixels: first and last column, first and last row
    tile_start: np.ndarray  # [tiles + 1] each tile's first intersection
    owner: np.ndarray  # [M] the Gaussian of each intersection
    gaussian_start: np.ndarray  # [N + 1] each Gaussian's first entry in ``slots``
    slots: np.ndarray  # [M] the intersections of each Gaussian

    @property
    def visible(self) -> np.ndarray:
        """[N] bool: the Gaussians whose alpha >= 1/255 box reaches into the image."""
        return np.diff(self.gaussian_start) > 0

    def layout(self) -> tuple:
        """What the compositing kernels take of it, and the threads they run on."""
        return (
            self.tile_start,
            self.owner,
            self.box,
            self.width,
            self.height,
            TILE_W,
            TILE_H,
            numba.get_num_threads(),
        )


def intersect(projection: Projection, opacities: np.ndarray, width: int, height: int) -> Tiles:
    p = projection
    box = np.empty((len(p.means2d), 4), np.int64)
    _boxes(p.means2d, p.cov2d, p.valid, opacities, width, height, box)
    order = np.argsort(p.depths)  # the one depth sort
    return Tiles(width, height, box, *_bucket(box, order, width, height, TILE_W, TILE_H))


@dataclass
class Composited:
    """A compositing's result, and what its backward pass takes."""

    out: np.ndarray  # [H * W, C] the sum of w values; C padded to a multiple of LANES
    final_t: np.ndarray  # [H * W] transmittance left
    last: np.ndarray  # [H * W] how many entries of its row's list each pixel went through
    terms: np.ndarray  # [N, 11] the splats' terms (_splat_terms)
    values: np.ndarray  # [N, C]
    peak: np.ndarray  # [N] each Gaussian's largest blending weight w over the pixels


def lanes(channels: int) -> int:
    """Channels rounded up to a multiple of LANES: the width values are composited at."""
    return channels + -channels % LANES


def _to_lanes(x: np.ndarray) -> np.ndarray:
    """x [R, C] with zero channels after its own up to lanes(C) (x itself when C is that)."""
    rows, channels = x.shape
    if channels == lanes(channels):
        return x
    out = np.zeros((rows, lanes(channels)))
    out[:, :channels] = x
    return out


_scratch = threading.local()


def _reused(shape: tuple[int, int]) -> np.ndarray:
    """An uninitialised float64 array of ``shape``, in memory this thread keeps between calls:
    fresh pages cost their first touch (the intersections' gradient rows are tens of MB: 4 of
    a backward pass's 41 ms, measured at 15k Gaussians and 341 x 257)."""
    size = shape[0] * shape[1]
    held = getattr(_scratch, "grads", None)
    if held is None or held.size < size:
        held = _scratch.grads = np.empty(max(size, 1))
    return held[:size].reshape(shape)


def composite(
    tiles: Tiles,
    means2d: np.ndarray,
    conics: np.ndarray,
    opacities: np.ndarray,
    values: np.ndarray,
) -> Composited:
    """Alpha-composite ``values`` [N, C] front to back (not copied when C is a multiple of
    LANES)."""
    values = _to_lanes(values)
    splats = np.concatenate([means2d, conics, opacities[:, None]], 1)
    terms = _splat_terms(splats)
    pixels = tiles.width * tiles.height
    out = np.empty((pixels, values.shape[1]))
    final_t, last = np.empty(pixels), np.empty(pixels, np.int64)
    at_intersections, peak = np.empty(len(tiles.owner)), np.empty(len(terms))
    _composite_fwd(tiles.layout(), terms, values, out, final_t, last, at_intersections)
    _max_rows(tiles.gaussian_start, tiles.slots, at_intersections, peak)
    return Composited(out, final_t, last, terms, values, peak)


def composite_backward(
    tiles: Tiles, result: Composited, v_out: np.ndarray, v_alpha: np.ndarray
) -> np.ndarray:
    """[N, 6 + C]: d/d(means2d, conics, opacity, values) from d/d(out [H * W, C], alpha)."""
    channels = v_out.shape[1]
    v_out = _to_lanes(v_out)
    grads = _reused((len(tiles.owner), SPLAT + v_out.shape[1]))
    _composite_bwd(
        tiles.layout(),
        result.terms,
        result.values,
        result.final_t,
        result.last,
        v_out,
        v_alpha,
        grads,
    )
    per = np.empty((len(result.terms), grads.shape[1]))
    _sum_rows(tiles.gaussian_start, tiles.slots, grads, per)
    return per[:, : SPLAT + channels]


# -- autograd --------------------------------------------------------------------------------

DEPTH_ALPHA_MIN = 1e-10  # expected depth = sum w z / max(alpha, this)


class _Rasterize(torch.autograd.Function):
    """(means, quats, scales, opacities, features, viewmat, means2d) -> (color [H * W, D],
    expected depth, alpha [H * W], normal [H * W, 3], each Gaussian's largest blending weight
    [N] (no gradient)). ``means2d`` holds the projected centres
    and takes no part in the forward pass: its gradient is the screen-space one that
    densification reads."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, features, viewmat, means2d, state):
        view, arrays, projection, tiles = state
        p = projection
        D = features.shape[1]
        # the features, depth and normal side by side, at the compositing's width
        values = np.zeros((len(p.depths), lanes(D + 4)))
        values[:, :D] = features.detach().numpy()
        values[:, D] = p.depths
        values[:, D + 1 : D + 4] = p.normals
        result = composite(tiles, p.means2d, p.conics, arrays[3], values)
        ctx.state = (view, arrays[:3], projection, tiles, result, D)
        ctx.like = (means, quats, scales, opacities, features, viewmat, means2d)
        pixels, dtype = len(result.final_t), features.dtype
        color, normal = torch.empty(pixels, D, dtype=dtype), torch.empty(pixels, 3, dtype=dtype)
        depth, alpha = torch.empty(pixels, dtype=dtype), torch.empty(pixels, dtype=dtype)
        outputs = (color, depth, alpha, normal)
        _outputs(result.out, result.final_t, D, *(x.numpy() for x in outputs))
        peak = torch.from_numpy(result.peak).to(features.device, dtype)
        ctx.mark_non_differentiable(peak)
        return *(x.to(features.device) for x in outputs), peak

    @staticmethod
    def backward(ctx, v_color, v_depth, v_alpha, v_normal, _v_peak):
        view, (means, quats, scales), projection, tiles, result, D = ctx.state
        pixels = len(result.final_t)
        v_out, v_alpha_all = np.empty((pixels, result.values.shape[1])), np.empty(pixels)
        grads = [_pixels(v, pixels) for v in (v_color, v_depth, v_alpha, v_normal)]
        _pixel_gradients(*grads, result.final_t, result.out, D, v_out, v_alpha_all)
        per = composite_backward(tiles, result, v_out, v_alpha_all)
        v_means, v_quats, v_scales, v_view = project_backward(
            means,
            quats,
            scales,
            view,
            projection,
            per[:, 0:2],
            per[:, 2:5],
            per[:, SPLAT + D],
            per[:, SPLAT + D + 1 : SPLAT + D + 4],
        )
        like = ctx.like
        return (
            _back(v_means, like[0]),
            _back(v_quats, like[1]),
            _back(v_scales, like[2]),
            _back(per[:, 5], like[3]),
            _back(per[:, SPLAT : SPLAT + D], like[4]),
            _back(view_gradient(v_view), like[5]) if ctx.needs_input_grad[5] else None,
            _back(per[:, 0:2], like[6]),
            None,
        )


def _back(x: np.ndarray, like: torch.Tensor) -> torch.Tensor:
    """x as a tensor of ``like``'s dtype and device (one copy)."""
    dtype = np.float32 if like.dtype == torch.float32 else np.float64
    return torch.from_numpy(np.ascontiguousarray(x, dtype=dtype)).to(like.device, like.dtype)


def _pixels(v: torch.Tensor | None, pixels: int) -> np.ndarray:
    """An output's gradient as [H * W, channels] (no copy on the CPU); [0, 0] for none."""
    if v is None:
        return np.zeros((0, 0), np.float32)
    return v.detach().reshape(pixels, -1).cpu().numpy()


@numba.njit(cache=True, parallel=True)
def _outputs(out, final_t, D, color, depth, alpha, normal):
    """color [H * W, D], expected depth, alpha and normal [H * W, 3], in their arrays' dtype,
    from the composited values [H * W, lanes] (the features, sum w z, the normal) and the
    transmittance left: one pass, no intermediate arrays."""
    for p in numba.prange(len(final_t)):
        a = 1 - final_t[p]
        for c in range(D):
            color[p, c] = out[p, c]
        depth[p] = out[p, D] / max(a, DEPTH_ALPHA_MIN)
        alpha[p] = a
        for c in range(3):
            normal[p, c] = out[p, D + 1 + c]


@numba.njit(cache=True, parallel=True)
def _pixel_gradients(v_color, v_depth, v_alpha, v_normal, final_t, out, D, v_out, v_alpha_all):
    """d/d(each pixel's composited values [H * W, lanes]) and d/d(its alpha, 1 - final_t)
    from the gradients of color, expected depth (sum w z / alpha), alpha and normal ([0, 0]
    for an output that has none)."""
    for p in numba.prange(len(final_t)):
        for c in range(v_out.shape[1]):
            v_out[p, c] = 0.0
        for c in range(v_color.shape[1]):
            v_out[p, c] = v_color[p, c]
        for c in range(v_normal.shape[1]):
            v_out[p, D + 1 + c] = v_normal[p, c]
        v_a = v_alpha[p, 0] if v_alpha.shape[0] else 0.0
        if v_depth.shape[0]:
            alpha = 1 - final_t[p]
            a = max(alpha, DEPTH_ALPHA_MIN)
            v_out[p, D] = v_depth[p, 0] / a
            if alpha >= DEPTH_ALPHA_MIN:
                v_a -= v_depth[p, 0] * out[p, D] / (a * a)
        v_alpha_all[p] = v_a


def rasterize_cpu(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    camera: Camera,
    near: float,
) -> Render:
    follow_torch_threads()
    W, H, D = camera.width, camera.height, features.shape[1]
    view = camera_arrays(camera, near)
    arrays = [_np(x) for x in (means, quats, scales, opacities)]
    projection = project(*arrays[:3], view)
    tiles = intersect(projection, arrays[3], W, H)
    # a leaf of its own: the gradient of the projected centres (densification reads it)
    means2d = _back(projection.means2d, means).requires_grad_(means.requires_grad)
    color, depth, alpha, normal, peak = _Rasterize.apply(
        means,
        quats,
        scales,
        opacities,
        features,
        camera.viewmat,
        means2d,
        (view, arrays, projection, tiles),
    )
    return Render(
        color.reshape(H, W, D),
        depth.reshape(H, W),
        alpha.reshape(H, W),
        normal.reshape(H, W, 3),
        means2d,
        torch.from_numpy(tiles.visible).to(means.device),
        peak,
    )
