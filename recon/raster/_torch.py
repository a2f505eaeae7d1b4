"""The pure-PyTorch rasterizer: EWA projection, then front-to-back compositing over the
(Gaussian, pixel) pairs that matter, in vectorised tensor operations.

Rather than a dense alpha matrix per tile (most of whose entries are zero: measured 5 times more
work here), the pairs are listed exactly: each Gaussian's pixels inside the ellipse where its
alpha reaches 1/255 (3DGS's cut-off), sorted by pixel with the Gaussians in depth order.
Transmittance is a cumulative sum of log(1 - alpha) within each pixel's run (in float64, so that
the running sum over the whole image keeps its precision); a pixel stops at transmittance 1e-4
as in 3DGS. Autograd does the backward pass. When the pairs would exceed ``PAIR_BUDGET``, the
image is done in bands of rows (tiles as wide as the image), one after the other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from evcap.recon.raster.rasterize import Camera, Render, camera_normals, quat_to_rotmat

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
EPS2D = 0.3  # added to the 2D covariance (a pixel's footprint), as gsplat and 3DGS do
PAIR_BUDGET = 4_000_000  # candidate pairs per band: bounds the memory of one band


@dataclass
class Projected:
    means2d: torch.Tensor  # [N, 2] pixels
    conics: torch.Tensor  # [N, 3] inverse 2D covariance (a, b, c): a dx^2 + 2 b dx dy + c dy^2
    cov2d: torch.Tensor  # [N, 3] (xx, xy, yy)
    depths: torch.Tensor  # [N] camera z
    valid: torch.Tensor  # [N] bool: in front of the camera with a proper footprint


def project(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    camera: Camera,
    near: float,
) -> Projected:
    """EWA splatting: each Gaussian's centre and 2D covariance in the image."""
    R, t = camera.viewmat[:3, :3], camera.viewmat[:3, 3]
    p = means @ R.T + t
    x, y, z = p.unbind(1)
    M = quat_to_rotmat(quats) * scales[:, None, :]
    cov = R @ (M @ M.transpose(1, 2)) @ R.T
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    W, H = camera.width, camera.height
    valid = z > near
    zs = torch.where(valid, z, torch.ones_like(z))
    # the Jacobian is taken at a point clamped near the view (3DGS), so that splats far off
    # screen do not blow up
    tan_x, tan_y = 0.5 * W / fx, 0.5 * H / fy
    tx = zs * torch.clamp(x / zs, -(cx + 0.5) / fx - 0.3 * tan_x, (W - 0.5 - cx) / fx + 0.3 * tan_x)
    ty = zs * torch.clamp(y / zs, -(cy + 0.5) / fy - 0.3 * tan_y, (H - 0.5 - cy) / fy + 0.3 * tan_y)
    zero = torch.zeros_like(zs)
    J = torch.stack(
        [fx / zs, zero, -fx * tx / zs**2, zero, fy / zs, -fy * ty / zs**2], dim=1
    ).reshape(-1, 2, 3)
    c2 = J @ cov @ J.transpose(1, 2)
    cxx, cxy, cyy = c2[:, 0, 0] + EPS2D, c2[:, 0, 1], c2[:, 1, 1] + EPS2D
    det = cxx * cyy - cxy * cxy
    valid = valid & (det > 0) & torch.isfinite(det)
    det = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([cyy / det, -cxy / det, cxx / det], dim=1)
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=1)
    return Projected(means2d, conics, torch.stack([cxx, cxy, cyy], 1), z, valid)


def _extents(proj: Projected, opacities: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Centre and half-sizes of each Gaussian's alpha >= 1/255 ellipse's bounding box, and
    whether it can show at all."""
    o = opacities.detach().clamp(max=1.0)
    k2 = 2 * torch.log((o / ALPHA_MIN).clamp(min=1.0))
    hx = torch.sqrt(k2 * proj.cov2d[:, 0].detach().clamp(min=0))
    hy = torch.sqrt(k2 * proj.cov2d[:, 2].detach().clamp(min=0))
    mx, my = proj.means2d[:, 0].detach(), proj.means2d[:, 1].detach()
    live = proj.valid & (o > ALPHA_MIN)
    live &= torch.isfinite(mx) & torch.isfinite(my) & torch.isfinite(hx) & torch.isfinite(hy)
    zero = torch.zeros_like(mx)
    return tuple(torch.where(live, v, zero) for v in (mx, my, hx, hy)) + (live,)


def _boxes(
    proj: Projected, opacities: torch.Tensor, width: int, y0: int, y1: int
) -> tuple[torch.Tensor, ...]:
    """First column and row, width and height of each Gaussian's ellipse box within rows
    [y0, y1), and its number of pixels there."""
    mx, my, hx, hy, live = _extents(proj, opacities)
    xa = torch.ceil(mx - hx).clamp(min=0, max=width).long()
    xb = torch.floor(mx + hx).clamp(min=-1, max=width - 1).long()
    ya = torch.ceil(my - hy).clamp(min=y0, max=y1).long()
    yb = torch.floor(my + hy).clamp(min=y0 - 1, max=y1 - 1).long()
    bw, bh = (xb - xa + 1).clamp(min=0), (yb - ya + 1).clamp(min=0)
    return xa, ya, bw, bh, torch.where(live, bw * bh, 0)


def _pairs(
    proj: Projected, opacities: torch.Tensor, width: int, y0: int, y1: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(gaussian, x, y) of every pixel in rows [y0, y1) inside a Gaussian's ellipse box,
    Gaussians in depth order."""
    xa, ya, bw, _, counts = _boxes(proj, opacities, width, y0, y1)
    order = torch.argsort(torch.where(counts > 0, proj.depths.detach(), math.inf))
    order = order[counts[order] > 0]
    counts = counts[order]
    gid = torch.repeat_interleave(order, counts)
    start = torch.cumsum(counts, 0) - counts
    local = torch.arange(len(gid), device=gid.device) - torch.repeat_interleave(start, counts)
    w = bw[gid]
    return gid, xa[gid] + local % w, ya[gid] + local // w


def _alphas(pp: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """Alpha of each pair from its Gaussian's (mean x, mean y, conic a, b, c, opacity)."""
    mx, my, a, b, c, o = pp[:, :6].unbind(1)
    dx, dy = px.to(pp.dtype) - mx, py.to(pp.dtype) - my
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = torch.where(sigma >= 0, o * torch.exp(-sigma.clamp(min=0)), 0)
    return torch.clamp(alpha, max=ALPHA_MAX)


def _composite(
    alpha: torch.Tensor, pix: torch.Tensor, values: torch.Tensor, n_pixels: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Front-to-back compositing of per-pair ``values`` [P, D]; pairs sorted by pixel, in depth
    order within each pixel. Returns (sum w values [n_pixels, D], sum w [n_pixels], w [P])."""
    log_t = torch.log1p(-alpha).double()
    running = torch.cumsum(log_t, 0) - log_t  # exclusive, over all pairs
    first = torch.ones_like(pix, dtype=torch.bool)
    first[1:] = pix[1:] != pix[:-1]
    index = torch.arange(len(pix), device=pix.device)
    run_start = torch.cummax(torch.where(first, index, 0), 0).values
    T = torch.exp(running - running[run_start]).to(alpha.dtype)
    with torch.no_grad():
        keep = T * (1 - alpha) > T_MIN
    w = torch.where(keep, T * alpha, 0)
    out = values.new_zeros(n_pixels, values.shape[1]).index_add(0, pix, w[:, None] * values)
    return out, alpha.new_zeros(n_pixels).index_add(0, pix, w), w


def rasterize_torch(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    camera: Camera,
    near: float,
) -> Render:
    normals = camera_normals(quats, scales, means, camera)
    W, H, D = camera.width, camera.height, features.shape[1]
    proj = project(means, quats, scales, camera, near)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    # everything a pair needs from its Gaussian, gathered in one go (one scatter back)
    params = torch.cat(
        [means2d, proj.conics, opacities[:, None], features, proj.depths[:, None], normals], 1
    )
    with torch.no_grad():  # as 3DGS's radii > 0: in view, whether or not occluded
        visible = _boxes(proj, opacities, W, 0, H)[4] > 0
    out, acc = None, None
    peak = torch.zeros(len(means), dtype=opacities.dtype, device=means.device)
    for y0, y1 in _bands(proj, opacities, W, H):
        with torch.no_grad():
            gid, px, py = _pairs(proj, opacities, W, y0, y1)
            hit = _alphas(params.detach().index_select(0, gid), px, py) >= ALPHA_MIN
            hit = torch.nonzero(hit).squeeze(1)
            pix, order = torch.sort((py * W + px).index_select(0, hit), stable=True)
            gid = gid.index_select(0, hit).index_select(0, order)
        pp = params.index_select(0, gid)
        o, a, w = _composite(_alphas(pp, pix % W, pix // W), pix, pp[:, 6:], H * W)
        out, acc = (o, a) if out is None else (out + o, acc + a)
        peak.scatter_reduce_(0, gid, w.detach(), "amax")
    return composited_render(out, acc, camera, D, means2d, visible, peak)


def composited_render(
    out: torch.Tensor,
    acc: torch.Tensor,
    camera: Camera,
    D: int,
    means2d: torch.Tensor,
    visible: torch.Tensor,
    peak: torch.Tensor,
) -> Render:
    """The maps from each pixel's sum of w (features [D], z, normal [3]) ``out`` and its alpha
    ``acc``."""
    H, W = camera.height, camera.width
    depth = out[:, D] / acc.clamp(min=1e-10)
    return Render(
        out[:, :D].reshape(H, W, D),
        depth.reshape(H, W),
        acc.reshape(H, W),
        out[:, D + 1 :].reshape(H, W, 3),
        means2d,
        visible,
        peak,
    )


def _bands(proj: Projected, opacities: torch.Tensor, width: int, height: int) -> list:
    """Row ranges that keep each band's candidate pairs under PAIR_BUDGET."""
    with torch.no_grad():
        _, _, hx, hy, live = _extents(proj, opacities)
        per = torch.clamp(2 * hx + 1, max=width) * torch.clamp(2 * hy + 1, max=height)
        total = float(torch.where(live, per, 0).sum())
    n = max(1, min(height, math.ceil(total / PAIR_BUDGET)))
    edges = [round(i * height / n) for i in range(n + 1)]
    return list(zip(edges[:-1], edges[1:], strict=True))
