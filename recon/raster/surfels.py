"""Surfels (2DGS, Huang et al. 2024): flat Gaussian discs, each pixel's alpha and depth taken
where its ray meets the disc's plane, not from a projected 2D Gaussian.

A surfel is a Gaussian whose first two axes (the columns 0 and 1 of its rotation, scaled by
scales 0 and 1) span its disc; its third axis is its normal and its third scale is not used.
Its point (u, v) in the disc's own units lies at mean + u s0 axis0 + v s1 axis1; in the
camera's homogeneous pixel coordinates (x w, y w, w) = M (u, v, 1) with
M = K [R axis0 s0 | R axis1 s1 | R mean + t]. A pixel (x, y) sees the disc where the planes
x w - x w' = 0 and y w - y w' = 0 meet it: (u, v, 1) is proportional to the cross product
of h_x = x M[2] - M[0] and h_y = y M[2] - M[1] (M's rows). There the Gaussian's exponent is
(u^2 + v^2) / 2 and the depth is w = M[2] . (u, v, 1). A disc seen edge-on would vanish
between pixels: as 2DGS, each pixel takes the larger of that Gaussian and a screen-space one
of sigma 1 / sqrt(FILTER_INV_SQUARE) pixels about the projected centre, which then gives the
centre's depth.

Every backend renders them the same way: torch here (autograd), the compiled CPU compositing
in recon/raster/_cpu_surfels.py, checked against it and the per-pixel reference.
"""

from __future__ import annotations

import torch

from evcap.recon.raster import _torch
from evcap.recon.raster.rasterize import Camera, Render, quat_to_rotmat

FILTER_INV_SQUARE = 2.0  # 2DGS's screen-space filter: sigma 1 / sqrt(2) pixel
# the boxes' 2D covariance: EWA's of the disc (its third scale 0) with the filter's own added,
# so that the box holds the filter wherever the disc is thinner than it
BOX_EPS2D = 1.0 / FILTER_INV_SQUARE


def surfel_matrices(
    means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, camera: Camera
) -> torch.Tensor:
    """[N, 3, 3] M: (u, v, 1) in each disc to (x w, y w, w) in the camera's pixels."""
    R, t = camera.viewmat[:3, :3], camera.viewmat[:3, 3]
    Rg = quat_to_rotmat(quats)
    axes = R @ (Rg[:, :, :2] * scales[:, None, :2])  # [N, 3, 2] the disc's axes, camera frame
    centre = means @ R.T + t
    return camera.K.to(means.dtype) @ torch.cat([axes, centre[:, :, None]], 2)


def surfel_boxes(
    means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, camera: Camera, near: float
) -> _torch.Projected:
    """The projection the tile boxes are taken from (no gradient): EWA's of each disc, its
    2D covariance widened to hold the screen-space filter."""
    with torch.no_grad():
        flat = scales * scales.new_tensor([1.0, 1.0, 0.0])
        p = _torch.project(means, quats, flat, camera, near)
        extra = BOX_EPS2D - _torch.EPS2D
        cov2d = p.cov2d + p.cov2d.new_tensor([extra, 0.0, extra])
    return _torch.Projected(p.means2d, p.conics, cov2d, p.depths, p.valid)


def surfel_normals(quats: torch.Tensor, means: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Each disc's normal (its third axis) in the camera frame, turned to face the camera."""
    R = camera.viewmat[:3, :3]
    n = quat_to_rotmat(quats)[:, :, 2] @ R.T
    p = means @ R.T + camera.viewmat[:3, 3]
    return torch.where((n * p).sum(1, keepdim=True) > 0, -n, n)


def screen_shifted(M: torch.Tensor, means2d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(M, projected centres [N, 2]) with ``means2d`` (a leaf holding the centres) entering as
    a shift of each disc across the image: its gradient is then the screen-space one that
    densification reads, as a 3D Gaussian's projected centre's."""
    shift = means2d - means2d.detach()
    rows = torch.stack([M[:, 0] + shift[:, :1] * M[:, 2], M[:, 1] + shift[:, 1:] * M[:, 2]], 1)
    M = torch.cat([rows, M[:, 2:]], 1)
    return M, M[:, :2, 2] / M[:, 2:, 2]


def ray_splat(
    M: torch.Tensor,
    centre: torch.Tensor,
    opacity: torch.Tensor,
    px: torch.Tensor,
    py: torch.Tensor,
    near: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(alpha, depth) of pairs: pixel (px, py) against the disc of M [P, 3, 3] with projected
    centre [P, 2] and opacity [P]; alpha 0 where the disc is met at or before ``near``."""
    x, y = px.to(M.dtype), py.to(M.dtype)
    hx = x[:, None] * M[:, 2] - M[:, 0]
    hy = y[:, None] * M[:, 2] - M[:, 1]
    c = torch.linalg.cross(hx, hy, dim=1)
    met = c[:, 2] != 0
    c2 = torch.where(met, c[:, 2], torch.ones_like(c[:, 2]))
    u, v = c[:, 0] / c2, c[:, 1] / c2
    rho3d = torch.where(met, u * u + v * v, torch.full_like(u, torch.inf))
    dx, dy = x - centre[:, 0], y - centre[:, 1]
    rho2d = FILTER_INV_SQUARE * (dx * dx + dy * dy)
    on_disc = rho3d <= rho2d
    rho = torch.where(on_disc, rho3d, rho2d)
    depth = torch.where(on_disc, M[:, 2, 0] * u + M[:, 2, 1] * v + M[:, 2, 2], M[:, 2, 2])
    alpha = torch.clamp(opacity * torch.exp(-0.5 * rho), max=_torch.ALPHA_MAX)
    return torch.where(depth > near, alpha, 0), depth


def rasterize_surfels_torch(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    camera: Camera,
    near: float,
    depth_squared: bool = False,
) -> Render:
    """The torch backend's surfels: the pairs listed as for Gaussians (their boxes from
    surfel_boxes), composited front to back by the discs' centres' depths.
    ``depth_squared``: the features' last channel is each pair's depth squared."""
    W, H, D = camera.width, camera.height, features.shape[1]
    boxes = surfel_boxes(means, quats, scales, camera, near)
    means2d = boxes.means2d.detach().clone().requires_grad_(means.requires_grad)
    M, centre = screen_shifted(surfel_matrices(means, quats, scales, camera), means2d)
    normals = surfel_normals(quats, means, camera)
    params = torch.cat([M.reshape(-1, 9), centre, opacities[:, None], features, normals], 1)
    with torch.no_grad():
        visible = _torch._boxes(boxes, opacities, W, 0, H)[4] > 0
    out, acc = None, None
    peak = torch.zeros(len(means), dtype=opacities.dtype, device=means.device)
    for y0, y1 in _torch._bands(boxes, opacities, W, H):
        with torch.no_grad():
            gid, px, py = _torch._pairs(boxes, opacities, W, y0, y1)
            p = params.detach().index_select(0, gid)
            alpha = ray_splat(p[:, :9].reshape(-1, 3, 3), p[:, 9:11], p[:, 11], px, py, near)[0]
            hit = torch.nonzero(alpha >= _torch.ALPHA_MIN).squeeze(1)
            pix, order = torch.sort((py * W + px).index_select(0, hit), stable=True)
            gid = gid.index_select(0, hit).index_select(0, order)
        pp = params.index_select(0, gid)
        alpha, depth = ray_splat(
            pp[:, :9].reshape(-1, 3, 3), pp[:, 9:11], pp[:, 11], pix % W, pix // W, near
        )
        own = pp[:, 12 : 12 + D]
        if depth_squared:
            own = torch.cat([own[:, :-1], (depth * depth)[:, None]], 1)
        values = torch.cat([own, depth[:, None], pp[:, 12 + D :]], 1)
        o, a, w = _torch._composite(alpha, pix, values, H * W)
        out, acc = (o, a) if out is None else (out + o, acc + a)
        peak.scatter_reduce_(0, gid, w.detach(), "amax")
    return _torch.composited_render(out, acc, camera, D, means2d, visible, peak)
