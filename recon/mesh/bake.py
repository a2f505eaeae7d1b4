"""Textures for a mesh: a UV atlas (xatlas) and maps baked into it from rendered views.

Each texel covered by a triangle is a point of the surface; its value is the mean of the views'
pixels where that point is what the view sees (its depth within a tolerance of the view's
depth), weighted by how squarely the view looks at it. Texels no view sees, and those between
the charts, take their nearest seen texel's value (no dark seams where a viewer filters
across a chart's edge).

Texture coordinates here are (u, v) with v down the image (row = v * size), as glTF has them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from evcap.errors import InputError


@dataclass
class Atlas:
    """The mesh cut into charts laid out in the unit square: its vertices split where charts
    meet."""

    vertices: np.ndarray  # [V, 3]
    faces: np.ndarray  # [F, 3]
    uv: np.ndarray  # [V, 2] in [0, 1], v down
    source_vertex: np.ndarray  # [V] the input vertex each came from


def atlas(vertices: np.ndarray, faces: np.ndarray, size: int) -> Atlas:
    """The UV atlas of the mesh, its charts padded for a ``size`` x ``size`` texture."""
    import xatlas

    pack_options = xatlas.PackOptions()
    pack_options.resolution = size
    pack_options.padding = 2
    pack_options.bilinear = True
    charts = xatlas.Atlas()
    charts.add_mesh(vertices.astype(np.float32), faces.astype(np.uint32))
    charts.generate(xatlas.ChartOptions(), pack_options)
    if charts.atlas_count != 1:  # the charts did not fit one texture of that size
        raise InputError(
            f"the mesh's charts need {charts.atlas_count} textures of {size} px: "
            "give a larger --texture-size"
        )
    source, new_faces, uv = charts[0]
    return Atlas(vertices[source], new_faces.astype(np.int64), uv.astype(np.float64), source)


@dataclass
class Texels:
    """The texels the triangles cover and the surface point each stands for."""

    size: int
    index: np.ndarray  # [M] flat index into the size x size texture
    position: np.ndarray  # [M, 3]
    normal: np.ndarray  # [M, 3] unit (the face's)


def texels(a: Atlas, size: int) -> Texels:
    """Rasterize the atlas: for each texel centre inside a triangle, its point on the mesh."""
    face = np.full(size * size, -1, np.int64)
    bary = np.zeros((size * size, 2))
    _rasterize(a.uv * size, a.faces, size, face, bary)
    index = np.flatnonzero(face >= 0)
    f = a.faces[face[index]]
    b1, b2 = bary[index, 0], bary[index, 1]
    p0, p1, p2 = (a.vertices[f[:, k]] for k in range(3))
    position = p0 * (1 - b1 - b2)[:, None] + p1 * b1[:, None] + p2 * b2[:, None]
    n = np.cross(p1 - p0, p2 - p0)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return Texels(size, index, position, n)


@numba.njit(cache=True)
def _rasterize(uv, faces, size, face_out, bary_out):  # pragma: no cover - compiled
    for f in range(len(faces)):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        ax, ay = uv[a, 0], uv[a, 1]
        e1x, e1y = uv[b, 0] - ax, uv[b, 1] - ay
        e2x, e2y = uv[c, 0] - ax, uv[c, 1] - ay
        det = e1x * e2y - e2x * e1y
        if abs(det) < 1e-12:
            continue
        x0 = max(int(np.floor(min(ax, ax + e1x, ax + e2x) - 0.5)), 0)
        x1 = min(int(np.ceil(max(ax, ax + e1x, ax + e2x) + 0.5)), size - 1)
        y0 = max(int(np.floor(min(ay, ay + e1y, ay + e2y) - 0.5)), 0)
        y1 = min(int(np.ceil(max(ay, ay + e1y, ay + e2y) + 0.5)), size - 1)
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                px, py = x + 0.5 - ax, y + 0.5 - ay
                s = (px * e2y - e2x * py) / det
                t = (e1x * py - px * e1y) / det
                if s >= -1e-6 and t >= -1e-6 and s + t <= 1 + 1e-6:
                    face_out[y * size + x] = f
                    bary_out[y * size + x, 0] = s
                    bary_out[y * size + x, 1] = t


@dataclass
class View:
    """A pinhole view rendered for baking: its depth, opacity and maps."""

    T_world_cam: np.ndarray  # [4, 4]
    K: np.ndarray  # [3, 3]
    depth: np.ndarray  # [H, W] camera z, 0 where nothing is
    alpha: np.ndarray  # [H, W]
    maps: np.ndarray  # [H, W, C]


def bake(
    t: Texels, views: list[View], tolerance: float, min_alpha: float
) -> tuple[np.ndarray, np.ndarray]:
    """(values [M, C], seen [M]): each texel's weighted mean over the views that see its point
    (depth within ``tolerance``, opacity at least ``min_alpha``, facing the camera)."""
    channels = views[0].maps.shape[-1]
    total = np.zeros((len(t.index), channels))
    weight = np.zeros(len(t.index))
    for view in views:
        H, W = view.depth.shape
        R, c = view.T_world_cam[:3, :3], view.T_world_cam[:3, 3]
        cam = (t.position - c) @ R
        z = cam[:, 2]
        facing = -((t.position - c) * t.normal).sum(1) / np.maximum(
            np.linalg.norm(t.position - c, axis=1), 1e-12
        )
        zs = np.where(z > 1e-6, z, 1.0)
        u = np.floor(view.K[0, 0] * cam[:, 0] / zs + view.K[0, 2] + 0.5).astype(np.int64)
        v = np.floor(view.K[1, 1] * cam[:, 1] / zs + view.K[1, 2] + 0.5).astype(np.int64)
        ok = (z > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H) & (facing > 0.1)
        idx = np.flatnonzero(ok)
        uu, vv = u[idx], v[idx]
        ok = (np.abs(view.depth[vv, uu] - z[idx]) < tolerance) & (view.alpha[vv, uu] >= min_alpha)
        idx, uu, vv = idx[ok], uu[ok], vv[ok]
        w = facing[idx] ** 2 * view.alpha[vv, uu]
        total[idx] += w[:, None] * view.maps[vv, uu]
        weight[idx] += w
    seen = weight > 0
    values = total / np.maximum(weight, 1e-12)[:, None]
    return values, seen


def texture(t: Texels, values: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """The texture [size, size, C]: the seen texels' values, every other texel its nearest seen
    one's (all zeros when none was seen)."""
    from scipy.ndimage import distance_transform_edt

    size, channels = t.size, values.shape[1]
    image = np.zeros((size * size, channels))
    known = np.zeros(size * size, bool)
    image[t.index[seen]] = values[seen]
    known[t.index[seen]] = True
    if not known.any():
        return image.reshape(size, size, channels)
    _, (iy, ix) = distance_transform_edt(~known.reshape(size, size), return_indices=True)
    return image.reshape(size, size, channels)[iy, ix]


def sample(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples [N, C] of a texture [S, S, C] at texture coordinates [N, 2] (v down)."""
    size = image.shape[0]
    x = np.clip(uv[:, 0] * size - 0.5, 0, size - 1)
    y = np.clip(uv[:, 1] * size - 0.5, 0, size - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, size - 1), np.minimum(y0 + 1, size - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy
