"""The ground truth's light integrals, by Monte Carlo over fixed stratified sample sets.

Diffuse: the irradiance E = int L(l) V(l) (n.l) dl over the hemisphere, with cosine-weighted
directions: the hemisphere cut into rings x sectors cells of equal cosine-weighted measure, a
ray through each cell's centre, E ~ pi / C * sum L V. The rays are cast once per vertex (the
bake); which of them reach the sky is kept, and the specular integral reads it.

Specular: int L(l) V(l) f(l, v) (n.l) dl for Cook-Torrance GGX (Schlick's Fresnel, F0 = 0.04,
Smith's separable masking), half vectors drawn from GGX's distribution of visible normals
(Heitz 2018) on a stratified grid, each sample weighted L V F G1(l); compiled, per pixel, the
light read from a latitude-longitude table of the environment fine enough that its bilinear
reads are exact to well under the sensor's noise.

The sets are fixed: a pixel's value is a smooth function of the view (noise that changed from
frame to frame would fire events). Their sizes keep the estimate within a fraction of the
sensor's noise of the converged integral (tests/sim/test_integrals.py).
"""

from __future__ import annotations

import numba
import numpy as np

from evcap.sim.lighting import F0, tangents
from evcap.sim.scene import SPECULAR_SIDE


def frames(normals: np.ndarray) -> np.ndarray:
    """[N, 3, 3] rows: two tangents and the normal (world -> local: frames @ d)."""
    t1, t2 = tangents(normals)
    return np.stack([t1, t2, normals], 1)


def cell_grid(count: int) -> tuple[int, int]:
    """(rings, sectors) of the cosine-weighted cells: about ``count`` cells, twice as many
    sectors as rings."""
    rings = max(1, int(round(np.sqrt(count / 2))))
    return rings, max(1, count // rings)


def cosine_cells(rings: int, sectors: int) -> np.ndarray:
    """[rings * sectors, 3] local directions (z: the normal) through the cells' centres."""
    u, phi = np.meshgrid(
        (np.arange(rings) + 0.5) / rings,  # sin^2 of the polar angle: equal cosine measure
        (np.arange(sectors) + 0.5) / sectors * 2 * np.pi,
        indexing="ij",
    )
    s = np.sqrt(u)
    return np.stack([s * np.cos(phi), s * np.sin(phi), np.sqrt(1 - u)], -1).reshape(-1, 3)


@numba.njit(cache=True)
def cell_of(x: float, y: float, z: float, rings: int, sectors: int) -> int:
    """Index of the cosine cell that holds the local direction (x, y, z) (z > 0: above the
    surface)."""
    ring = min(int(max(1 - z * z, 0.0) * rings), rings - 1)
    turn = np.arctan2(y, x) % (2 * np.pi)
    return ring * sectors + min(int(turn / (2 * np.pi) * sectors), sectors - 1)


def specular_environment(
    table: np.ndarray,
    normals: np.ndarray,
    view: np.ndarray,
    roughness: np.ndarray,
    side: int = SPECULAR_SIDE,
    sky_open: tuple | None = None,
) -> np.ndarray:
    """The environment's specular light [N, 3] at points with unit normals and directions to
    the viewer [N, 3]: GGX's visible normals sampled on a side x side grid, the light read from
    ``table`` (Environment.table: world directions, bilinear). ``sky_open``: (triangles [N, 3],
    barycentric weights [N, 3], each vertex's frame [V, 3, 3] and open cells [V, C], rings,
    sectors): a sample's visibility is that of the cell holding it at each of the triangle's
    vertices, blended (below a vertex's surface: blocked); None: nothing blocks the sky."""
    n = len(normals)
    out = np.zeros((n, 3))
    if n == 0:
        return out
    f = frames(normals)
    alpha = np.maximum(roughness, 0.02) ** 2
    if sky_open is None:
        tri, w = np.zeros((n, 3), np.int64), np.zeros((n, 3))
        vframes, vopen, rings, sectors = np.zeros((1, 3, 3)), np.ones((1, 1), np.bool_), 1, 1
        shadows = False
    else:
        tri, w, vframes, vopen, rings, sectors = sky_open
        shadows = True
    # the grid's points on the unit disc, the same for every pixel (concentric rings of equal area)
    rad = np.sqrt((np.arange(side) + 0.5) / side)[:, None]
    phi = 2 * np.pi * (np.arange(side) + 0.5) / side
    disc = np.stack([rad * np.cos(phi), rad * np.sin(phi)], -1).reshape(-1, 2)
    _specular(
        np.ascontiguousarray(table, np.float32),  # half the memory its reads wait on
        np.ascontiguousarray(f, np.float64),
        np.ascontiguousarray(view, np.float64),
        np.ascontiguousarray(alpha, np.float64),
        disc,
        shadows,
        np.ascontiguousarray(tri, np.int64),
        np.ascontiguousarray(w, np.float64),
        np.ascontiguousarray(vframes, np.float64),
        np.ascontiguousarray(vopen),
        rings,
        sectors,
        F0,
        out,
    )
    return out


@numba.njit(cache=True, parallel=True)
def _specular(
    table, f, view, alpha, disc, shadows, tri, w, vframes, vopen, rings, sectors, f0, out
):  # pragma: no cover - compiled
    h, width = table.shape[0], table.shape[1]
    for p in numba.prange(len(f)):
        nx, ny, nz = f[p, 2, 0], f[p, 2, 1], f[p, 2, 2]
        vx, vy, vz = view[p, 0], view[p, 1], view[p, 2]
        ndv = min(max(nx * vx + ny * vy + nz * vz, 1e-4), 1.0)
        a = alpha[p]
        k = a * a  # Smith's G1 for GGX: 2c / (c + sqrt(a^2 + (1 - a^2) c^2))
        # the view in the local frame, stretched to the hemisphere configuration (Heitz 2018)
        ex = a * (vx * f[p, 0, 0] + vy * f[p, 0, 1] + vz * f[p, 0, 2])
        ey = a * (vx * f[p, 1, 0] + vy * f[p, 1, 1] + vz * f[p, 1, 2])
        ez = ndv
        norm = np.sqrt(ex * ex + ey * ey + ez * ez)
        ex, ey, ez = ex / norm, ey / norm, ez / norm
        lensq = ex * ex + ey * ey
        if lensq > 0:
            ax, ay = -ey / np.sqrt(lensq), ex / np.sqrt(lensq)
        else:
            ax, ay = 1.0, 0.0
        bx, by, bz = -ez * ay, ez * ax, ex * ay - ey * ax  # (e x a), a = (ax, ay, 0)
        s_mix = 0.5 * (1 + ez)
        r, g, b = 0.0, 0.0, 0.0
        for i in range(len(disc)):
            t1 = disc[i, 0]
            t2 = (1 - s_mix) * np.sqrt(max(1 - t1 * t1, 0.0)) + s_mix * disc[i, 1]
            t3 = np.sqrt(max(1 - t1 * t1 - t2 * t2, 0.0))
            # a visible normal of the hemisphere, stretched back: the half vector (local)
            lx = a * (t1 * ax + t2 * bx + t3 * ex)
            ly = a * (t1 * ay + t2 * by + t3 * ey)
            lz = max(t2 * bz + t3 * ez, 0.0)
            norm = np.sqrt(lx * lx + ly * ly + lz * lz)
            if norm == 0:
                continue
            lx, ly, lz = lx / norm, ly / norm, lz / norm
            hx = lx * f[p, 0, 0] + ly * f[p, 1, 0] + lz * f[p, 2, 0]
            hy = lx * f[p, 0, 1] + ly * f[p, 1, 1] + lz * f[p, 2, 1]
            hz = lx * f[p, 0, 2] + ly * f[p, 1, 2] + lz * f[p, 2, 2]
            vdh = vx * hx + vy * hy + vz * hz
            if vdh <= 0:
                continue
            dx, dy, dz = 2 * vdh * hx - vx, 2 * vdh * hy - vy, 2 * vdh * hz - vz
            ndl = nx * dx + ny * dy + nz * dz
            if ndl <= 0:
                continue
            ndl = min(ndl, 1.0)
            # drawn in proportion to D G1(v) (v.h) / (n.v): what is left of f (n.l) / pdf
            gl = 2 * ndl / (ndl + np.sqrt(k + (1 - k) * ndl * ndl))
            m = 1 - min(vdh, 1.0)
            m2 = m * m
            fresnel = f0 + (1 - f0) * (m2 * m2 * m)
            weight = fresnel * gl
            if shadows:
                seen = 0.0
                for c in range(3):
                    vert = tri[p, c]
                    qx = vframes[vert, 0, 0] * dx + vframes[vert, 0, 1] * dy
                    qx += vframes[vert, 0, 2] * dz
                    qy = vframes[vert, 1, 0] * dx + vframes[vert, 1, 1] * dy
                    qy += vframes[vert, 1, 2] * dz
                    qz = vframes[vert, 2, 0] * dx + vframes[vert, 2, 1] * dy
                    qz += vframes[vert, 2, 2] * dz
                    if qz > 0 and vopen[vert, cell_of(qx, qy, qz, rings, sectors)]:
                        seen += w[p, c]
                weight *= seen
                if weight == 0:
                    continue
            # the light in direction d: bilinear in the latitude-longitude table
            x = (np.arctan2(dy, dx) / (2 * np.pi) + 0.5) * width - 0.5
            y = (0.5 - np.arcsin(min(max(dz, -1.0), 1.0)) / np.pi) * h - 0.5
            y = min(max(y, 0.0), h - 1.0)
            x0, y0 = int(np.floor(x)), int(np.floor(y))
            fx, fy = x - x0, y - y0
            y1 = min(y0 + 1, h - 1)
            x1 = (x0 + 1) % width
            x0 = x0 % width
            w00, w01 = weight * (1 - fx) * (1 - fy), weight * fx * (1 - fy)
            w10, w11 = weight * (1 - fx) * fy, weight * fx * fy
            r += w00 * table[y0, x0, 0] + w01 * table[y0, x1, 0]
            r += w10 * table[y1, x0, 0] + w11 * table[y1, x1, 0]
            g += w00 * table[y0, x0, 1] + w01 * table[y0, x1, 1]
            g += w10 * table[y1, x0, 1] + w11 * table[y1, x1, 1]
            b += w00 * table[y0, x0, 2] + w01 * table[y0, x1, 2]
            b += w10 * table[y1, x0, 2] + w11 * table[y1, x1, 2]
        out[p, 0], out[p, 1], out[p, 2] = r / len(disc), g / len(disc), b / len(disc)
