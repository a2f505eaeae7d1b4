"""Visibility of the environment from each Gaussian, baked once from the frozen stage-I
geometry as spherical harmonics (degree 3), used by stage II when the scene has occluders.

The Gaussians' opacity is splatted into an occupancy grid over the opaque part of the scene;
from each Gaussian, rays in fixed directions march through it and keep the light that gets
through (transmittance). A ray starts off the Gaussian's own surface: lifted along its normal
(to the side the ray leaves by) and two cells out along the ray. Lifted along the ray alone, a
ray that grazes a plane (a floor, a table) marched through the plane's own cells and the plane
shadowed itself from its whole horizon.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from evcap.recon.gaussians import Gaussians
from evcap.recon.sh import sh_basis
from evcap.recon.shading import fibonacci_directions

SH_DEGREE = 3
BAKE_DIRECTIONS = 128
GRID = 64  # cells along the longest side of the occupied box
OPAQUE = 0.05  # Gaussians fainter than this neither block light nor get a bake
LIFT = 2.5  # cells a ray starts off its Gaussian's surface: past the surface's own occupancy


@torch.no_grad()
def bake_visibility(gaussians: Gaussians, normals: torch.Tensor, chunk: int = 512) -> torch.Tensor:
    """[N, 16] SH coefficients of each Gaussian's visibility (1: open sky, 0: blocked), the rays
    starting off the surface through it whose unit normals [N, 3] are given (either side)."""
    means, opacity = gaussians.means.detach(), gaussians.opacities.detach()
    n = len(means)
    coeffs = torch.zeros(n, (SH_DEGREE + 1) ** 2, device=means.device)
    coeffs[:, 0] = 1 / sh_basis(0, torch.zeros(1, 3))[0, 0]  # V = 1 everywhere
    solid = opacity > OPAQUE
    if solid.sum() < 2:
        return coeffs
    pts = means[solid]
    lo = torch.quantile(pts, 0.005, dim=0)
    hi = torch.quantile(pts, 0.995, dim=0)
    cell = float((hi - lo).max()) / GRID
    if not cell > 0:
        return coeffs
    lo = lo - 2 * cell
    dims = (((hi + 2 * cell) - lo) / cell).ceil().long().clamp(min=1)
    occupancy = _splat(pts, opacity[solid], lo, cell, dims)
    dirs = fibonacci_directions(BAKE_DIRECTIONS).to(means.device)
    basis = sh_basis(SH_DEGREE, dirs)  # [K, 16]
    project = torch.linalg.pinv(basis)  # least squares from K directions to 16 coefficients
    steps = int(math.ceil(float(dims.float().norm())))
    t = (torch.arange(steps, device=means.device, dtype=torch.float32) + 2) * cell
    normals = normals.to(means.device)
    for i in torch.nonzero(solid).squeeze(1).split(chunk):
        # each ray lifted off the surface on the side it leaves by: [B, K, 3]
        side = torch.sign(normals[i] @ dirs.T)[..., None]
        start = means[i, None] + LIFT * cell * side * normals[i, None]
        # [B, K, S, 3] points along every ray, in the grid's [-1, 1] coordinates
        p = start[:, :, None] + dirs[None, :, None] * t[None, None, :, None]
        g = (p - lo) / (dims.float() * cell) * 2 - 1
        occ = F.grid_sample(
            occupancy[None, None],
            g.reshape(1, -1, 1, 1, 3),
            align_corners=False,
            padding_mode="zeros",
        ).reshape(len(i), len(dirs), steps)
        transmittance = torch.exp(torch.log1p(-occ.clamp(0, 0.999)).sum(-1))  # [B, K]
        coeffs[i] = transmittance @ project.T
    return coeffs


def _splat(points, opacity, lo, cell: float, dims: torch.Tensor) -> torch.Tensor:
    """Occupancy [X, Y, Z] -> stored [Z, Y, X] for grid_sample: the largest opacity of the
    Gaussians whose centre falls in each cell, spread one cell around (surfaces of sparse
    Gaussians must not leak light between them)."""
    idx = ((points - lo) / cell).floor().long()
    idx = torch.minimum(idx.clamp(min=0), dims - 1)
    flat = (idx[:, 2] * dims[1] + idx[:, 1]) * dims[0] + idx[:, 0]
    grid = torch.zeros(int(dims.prod()), device=points.device)
    grid.scatter_reduce_(0, flat, opacity, reduce="amax")
    grid = grid.reshape(int(dims[2]), int(dims[1]), int(dims[0]))
    return F.max_pool3d(grid[None, None], 3, stride=1, padding=1)[0, 0]


def visibility_at(coeffs: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """[N, K] visibility in [0, 1] at unit directions [K, 3]."""
    return (coeffs @ sh_basis(SH_DEGREE, directions).T).clamp(0, 1)
