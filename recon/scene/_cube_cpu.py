"""cube_map.cube_lookup on the CPU, compiled, for directions that take no gradient (a render's
pixels, the shading's fixed directions): each direction's face, its four texels and their
bilinear weights found in one pass, and the faces' gradient summed in another (a channel per
thread, in the directions' order: the same sums every run). cube_map.cube_lookup's gathers in
PyTorch are the reference, and what runs on a GPU or when the directions need a gradient (pose
refinement).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from evcap.recon._threads import follow_torch_threads


@numba.njit(cache=True, inline="always")
def _taps(x, y, z, size):
    """(face, row and column of the top-left texel, the column and row fractions) of the
    bilinear read in direction (x, y, z), as grid_sample with align_corners=False and border
    padding on the face the direction lands on."""
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax >= ay and ax >= az:  # the first of equal axes, as argmax
        major, u, v, axis = x, y, z, 0
    elif ay >= az:
        major, u, v, axis = y, x, z, 1
    else:
        major, u, v, axis = z, x, y, 2
    face = 2 * axis + (1 if major < 0 else 0)
    m = max(abs(major), 1e-12)
    u, v = u / m, v / m
    s = float(size)
    px = min(max(((u + 1) * s - 1) / 2, 0.0), s - 1)
    py = min(max(((v + 1) * s - 1) / 2, 0.0), s - 1)
    cx = min(math.floor(px), max(s - 2, 0.0))
    cy = min(math.floor(py), max(s - 2, 0.0))
    return face, int(cy), int(cx), px - cx, py - cy


@numba.njit(cache=True, parallel=True)
def _lookup(faces, dirs, out, taps, fractions):
    """out [N, C]: the reads; taps [N, 3] (face, row, column of the top-left texel) and
    fractions [N, 2] (column, row) kept for the backward pass."""
    size = faces.shape[-1]
    step = 1 if size > 1 else 0
    for i in numba.prange(dirs.shape[0]):
        f, r, c, fx, fy = _taps(dirs[i, 0], dirs[i, 1], dirs[i, 2], size)
        taps[i, 0], taps[i, 1], taps[i, 2] = f, r, c
        fractions[i, 0], fractions[i, 1] = fx, fy
        for ch in range(faces.shape[1]):
            upper = faces[f, ch, r, c] * (1 - fx) + faces[f, ch, r, c + step] * fx
            lower = faces[f, ch, r + step, c] * (1 - fx) + faces[f, ch, r + step, c + step] * fx
            out[i, ch] = upper * (1 - fy) + lower * fy


@numba.njit(cache=True, parallel=True)
def _lookup_backward(taps, fractions, grad, v_faces):
    """The faces' gradient, a channel per thread, each summed in the directions' order."""
    step = 1 if v_faces.shape[-1] > 1 else 0
    for ch in numba.prange(grad.shape[1]):
        for i in range(taps.shape[0]):
            f, r, c = taps[i, 0], taps[i, 1], taps[i, 2]
            fx, fy = fractions[i, 0], fractions[i, 1]
            g = grad[i, ch]
            v_faces[f, ch, r, c] += g * (1 - fx) * (1 - fy)
            v_faces[f, ch, r, c + step] += g * fx * (1 - fy)
            v_faces[f, ch, r + step, c] += g * (1 - fx) * fy
            v_faces[f, ch, r + step, c + step] += g * fx * fy


class _CubeLookup(torch.autograd.Function):
    @staticmethod
    def forward(ctx, faces, dirs):
        # read and written in their own dtype, computed in float64 (float32 to float64 is
        # exact, and the store rounds as a cast would): no copies
        d = dirs.detach().reshape(-1, 3).numpy()
        out = torch.empty(len(d), faces.shape[1], dtype=faces.dtype)
        taps, fractions = np.empty((len(d), 3), np.int64), np.empty((len(d), 2))
        _lookup(faces.detach().numpy(), d, out.numpy(), taps, fractions)
        ctx.state = (taps, fractions, faces.shape, faces.dtype)
        return out.reshape(*dirs.shape[:-1], faces.shape[1])

    @staticmethod
    def backward(ctx, grad):
        taps, fractions, shape, dtype = ctx.state
        g = grad.detach().reshape(len(taps), -1).numpy()
        v_faces = np.zeros(tuple(shape))
        _lookup_backward(taps, fractions, g, v_faces)
        return torch.from_numpy(v_faces).to(dtype), None


def cube_lookup_cpu(faces: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """cube_lookup's values [..., C] of ``faces`` [6, C, S, S] in directions [..., 3] (no
    gradient reaches the directions)."""
    follow_torch_threads()
    return _CubeLookup.apply(faces, dirs)
