"""Depth maps fused into a truncated signed distance volume, and the surface through its zero
level (marching cubes, scikit-image), cleaned of floaters and simplified: the mesh a
reconstruction's depth describes.

Each voxel holds the mean over the views that see it of its signed distance to the surface
along the view's axis (the depth seen less the voxel's; positive in front, clipped to the
truncation distance, in units of it). A
ray that meets nothing (depth 0: the pixel sees through to the background) says its voxels
are empty: a floater that some views show and others see through is carved away.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from evcap.errors import InputError
from evcap.recon._threads import follow_torch_threads

MAX_VOXELS = 320**3  # float32 value and weight: 260 MB; beyond it, ask for a coarser grid


@dataclass(frozen=True)
class Grid:
    """The voxels: voxel (i, j, k)'s centre lies at origin + voxel * (i, j, k)."""

    origin: np.ndarray  # [3] world
    voxel: float
    shape: tuple[int, int, int]

    @classmethod
    def around(cls, lo: np.ndarray, hi: np.ndarray, voxel: float) -> Grid:
        """The grid covering the box lo..hi; InputError when it would be too large."""
        shape = tuple(int(math.ceil(x)) + 1 for x in (np.asarray(hi) - lo) / voxel)
        if math.prod(shape) > MAX_VOXELS:
            fits = voxel * (math.prod(shape) / MAX_VOXELS) ** (1 / 3) * 1.01
            raise InputError(
                f"a voxel of {voxel:.4g} makes {shape[0]} x {shape[1]} x {shape[2]} voxels "
                f"({math.prod(shape) / 1e6:.0f} M, at most {MAX_VOXELS / 1e6:.0f} M): give a "
                f"larger voxel (--resolution {fits:.3g} or more) or a smaller --bounds box"
            )
        return cls(np.asarray(lo, np.float64), float(voxel), shape)  # type: ignore[arg-type]


class Tsdf:
    """The volume being fused."""

    def __init__(self, grid: Grid, truncation_voxels: float = 4.0) -> None:
        self.grid = grid
        self.truncation = truncation_voxels * grid.voxel
        self.value = np.ones(math.prod(grid.shape), np.float32)
        self.weight = np.zeros(math.prod(grid.shape), np.float32)

    def integrate(self, depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> None:
        """One pinhole view: ``depth`` [H, W] the camera z of the surface each pixel sees (0:
        nothing there; NaN: not known), ``K`` its intrinsics, ``T_world_cam`` its pose."""
        R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
        # voxel (i, j, k) in the camera: base + i * step_i + j * step_j + k * step_k
        base = (self.grid.origin - t) @ R
        steps = self.grid.voxel * R  # rows: the world's axes in the camera
        follow_torch_threads()
        _integrate(
            self.value,
            self.weight,
            np.asarray(self.grid.shape, np.int64),
            base,
            np.ascontiguousarray(steps),
            np.asarray(K, np.float64),
            np.ascontiguousarray(depth, np.float64),
            self.truncation,
        )

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices [V, 3] world, faces [F, 3]) of the zero level, within the voxels some view
        observed; triangles wound so that their normals face the empty side."""
        from scipy.ndimage import binary_erosion
        from skimage.measure import marching_cubes

        value = self.value.reshape(self.grid.shape)
        observed = self.weight.reshape(self.grid.shape) > 0
        # a cube is meshed only where all its corners were observed: the unobserved voxels'
        # initial value would make a surface of its own at the edge of what was seen
        mask = binary_erosion(observed, np.ones((3, 3, 3), bool), border_value=0)
        if not (value[mask] < 0).any() or not (value[mask] > 0).any():
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        verts, faces, _, _ = marching_cubes(
            value, 0.0, spacing=(self.grid.voxel,) * 3, mask=mask, gradient_direction="descent"
        )
        return verts + self.grid.origin, faces.astype(np.int64)


@numba.njit(parallel=True, cache=True)
def _integrate(value, weight, shape, base, steps, K, depth, truncation):  # pragma: no cover
    H, W = depth.shape
    nx, ny, nz = shape[0], shape[1], shape[2]
    for i in numba.prange(nx):
        for j in range(ny):
            for k in range(nz):
                x = base[0] + i * steps[0, 0] + j * steps[1, 0] + k * steps[2, 0]
                y = base[1] + i * steps[0, 1] + j * steps[1, 1] + k * steps[2, 1]
                z = base[2] + i * steps[0, 2] + j * steps[1, 2] + k * steps[2, 2]
                if z <= 1e-6:
                    continue
                u = int(np.floor(K[0, 0] * x / z + K[0, 2] + 0.5))
                v = int(np.floor(K[1, 1] * y / z + K[1, 2] + 0.5))
                if u < 0 or u >= W or v < 0 or v >= H:
                    continue
                d = depth[v, u]
                if np.isnan(d):  # the pixel says nothing
                    continue
                if d > 0:
                    sdf = d - z
                    if sdf <= -truncation:  # hidden behind the surface: nothing known
                        continue
                    obs = min(1.0, sdf / truncation)
                else:  # the ray meets nothing: empty
                    obs = 1.0
                n = (i * ny + j) * nz + k
                w = weight[n]
                value[n] = (value[n] * w + obs) / (w + 1)
                weight[n] = w + 1


def largest_parts(
    vertices: np.ndarray, faces: np.ndarray, keep_share: float
) -> tuple[np.ndarray, np.ndarray]:
    """The mesh without its small disconnected pieces (floaters): the connected parts with at
    least ``keep_share`` of the largest part's area."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=True)
    parts = mesh.split(only_watertight=False)
    if len(parts) <= 1:
        return np.asarray(mesh.vertices), np.asarray(mesh.faces)
    areas = np.array([p.area for p in parts])
    kept = trimesh.util.concatenate(
        [p for p, a in zip(parts, areas, strict=True) if a >= keep_share * areas.max()]
    )
    return np.asarray(kept.vertices), np.asarray(kept.faces)


def simplified(
    vertices: np.ndarray, faces: np.ndarray, max_triangles: int
) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with at most about ``max_triangles`` (quadric edge collapse, fast_simplification):
    marching cubes gives two triangles per voxel of surface, far more than the views resolve
    where the voxels are fine, and the texture atlas takes time with every triangle."""
    if len(faces) <= max_triangles:
        return vertices, faces
    import fast_simplification

    v, f = fast_simplification.simplify(
        vertices.astype(np.float64), faces.astype(np.int64), 1 - max_triangles / len(faces)
    )
    return np.asarray(v), np.asarray(f, np.int64)
