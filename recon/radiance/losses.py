"""The terms of stage I's loss beside the event loss (recon/events/loss.py): the brightness
anchor, normal consistency and the surface terms (method.md; terms.py weights them)."""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch
import torch.nn.functional as F

from evcap.errors import NumericalError


def checked_loss(
    stage: str, step: int, total: torch.Tensor | None, parameters: Iterable[torch.Tensor]
) -> float:
    """The loss ``total`` as a float (NaN when None), after checking that it and every
    parameter are finite: NumericalError, naming the step, when one is not. One wait for the
    device, so the trainers check every few steps rather than at each."""
    checks = [torch.isfinite(p.detach()).all() for p in parameters]
    if total is not None:
        checks.append(torch.isfinite(total.detach()))
    if checks and not bool(torch.stack(checks).all()):
        if total is not None and not torch.isfinite(total.detach()):
            raise NumericalError(f"{stage}: the loss became {float(total)} by step {step}")
        raise NumericalError(
            f"{stage}: a parameter became NaN or infinite by step {step}: the optimisation "
            "diverged; lower its learning rates"
        )
    return float(total.detach()) if total is not None else math.nan


def quiet_variation_loss(log_image: torch.Tensor, loud: torch.Tensor) -> torch.Tensor:
    """Mean |log L_p - log L_q| (all channels) between neighbouring sensor pixels [H, W, C]
    where no event fired within a pixel of either (``loud`` [H, W]: pixels with events). What
    no edge ever crosses, the events leave free: only the contrast at a patch's outline is
    measured, and the inside relaxes toward anything (a box lit dark at its outline and grey
    inside). Total variation carries the outline's level inward, and leaves the edges to the
    events."""
    near = F.max_pool2d(loud[None, None].to(log_image.dtype), 3, 1, 1)[0, 0] > 0
    quiet = ~near
    total, count = log_image.new_zeros(()), log_image.new_zeros(())
    for dim in (0, 1):
        size = log_image.shape[dim] - 1
        m = (quiet.narrow(dim, 0, size) & quiet.narrow(dim, 1, size)).to(log_image.dtype)
        total = total + (log_image.diff(dim=dim).abs().sum(-1) * m).sum()
        count = count + m.sum()
    return total / count.clamp(min=1)


def anchor_loss(radiance: torch.Tensor, level: float) -> torch.Tensor:
    """(mean of the rendered pixels' (R + G + B) / 3 - g)^2: fixes the overall brightness."""
    return (radiance.mean() - level) ** 2


def depth_normals(depth: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Normals [H, W, 3] (camera frame, facing the camera) from a depth map's local gradients,
    and where they are defined (interior pixels with positive depth around them)."""
    H, W = depth.shape
    ys, xs = torch.meshgrid(
        torch.arange(H, dtype=depth.dtype, device=depth.device),
        torch.arange(W, dtype=depth.dtype, device=depth.device),
        indexing="ij",
    )
    x = (xs - K[0, 2]) / K[0, 0] * depth
    y = (ys - K[1, 2]) / K[1, 1] * depth
    p = torch.stack([x, y, depth], -1)
    dx = p[1:-1, 2:] - p[1:-1, :-2]
    dy = p[2:, 1:-1] - p[:-2, 1:-1]
    n = torch.cross(dx, dy, dim=-1)
    n = F.normalize(n, dim=-1, eps=1e-12)
    n = torch.where((n * p[1:-1, 1:-1]).sum(-1, keepdim=True) > 0, -n, n)
    valid = torch.zeros(H, W, dtype=torch.bool, device=depth.device)
    d = depth > 0
    valid[1:-1, 1:-1] = d[1:-1, 1:-1] & d[1:-1, 2:] & d[1:-1, :-2] & d[2:, 1:-1] & d[:-2, 1:-1]
    out = torch.zeros(H, W, 3, dtype=depth.dtype, device=depth.device)
    out[1:-1, 1:-1] = n
    return out, valid


def normal_loss(
    rendered: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor, K: torch.Tensor
) -> torch.Tensor:
    """Mean |n - n_d|_1 between the rendered normals and the depth's, where the render is
    mostly opaque."""
    n_d, valid = depth_normals(depth, K)
    mask = valid & (alpha.detach() > 0.5)
    n = F.normalize(rendered, dim=-1, eps=1e-12)
    err = (n - n_d).abs().sum(-1)
    m = mask.to(err.dtype)
    return (err * m).sum() / m.sum().clamp(min=1)


def surface_terms(
    normal: torch.Tensor,
    depth: torch.Tensor,
    alpha: torch.Tensor,
    second_moment: torch.Tensor | None,
    K: torch.Tensor,
    smooth_step: float,
    which: tuple[bool, bool, bool],
) -> torch.Tensor:
    """[3]: normal_loss, depth_spread_loss and normal_smoothness_loss of one render (0 for a
    term ``which`` leaves out); on the CPU one compiled pass (recon/radiance/_surface_terms_cpu.py),
    elsewhere these functions."""
    if normal.device.type == "cpu":
        from evcap.recon.radiance._surface_terms_cpu import surface_terms_cpu

        return surface_terms_cpu(normal, depth, alpha, second_moment, K, smooth_step, which)
    zero = depth.new_zeros(())
    return torch.stack(
        [
            normal_loss(normal, depth, alpha, K) if which[0] else zero,
            depth_spread_loss(second_moment, depth, alpha) if which[1] else zero,
            normal_smoothness_loss(normal, depth, alpha, smooth_step) if which[2] else zero,
        ]
    )


def depth_spread_loss(
    second_moment: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor
) -> torch.Tensor:
    """Mean relative variance of the depths along each ray, r = Var(z) / E[z]^2 with the
    compositing weights (as r / (1 + r)), where the render is mostly opaque: 0 for a thin
    surface, large for fog spread in depth (a cheaper relative of the distortion loss of
    Mip-NeRF 360 and 2DGS).
    ``second_moment``: sum w z^2; ``depth``: sum w z / sum w."""
    a = alpha.clamp(min=1e-6)
    mean_sq = depth.clamp(min=1e-6) ** 2
    relative = (second_moment / a - mean_sq).clamp(min=0) / mean_sq
    # bounded, r / (1 + r): a ray through a floater near the camera and the surface far
    # behind has a relative variance near 1 or more, and its unbounded gradient once turned
    # such a floater into an opaque wall in front of the cameras
    robust = relative / (1 + relative)
    m = (alpha.detach() > 0.5).to(relative.dtype)
    return (robust * m).sum() / m.sum().clamp(min=1)


def normal_smoothness_loss(
    normal: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor, step: float
) -> torch.Tensor:
    """Mean |n_p - n_q|_1 between neighbouring pixels' rendered normals [H, W, 3], where both
    are mostly opaque, weighted by exp(-|z_p - z_q| / (step z_p)): smooth across a texture's
    edges on one surface, free across an outline (a jump in depth). A surface's normals are
    told nothing by the events inside a patch of one color; this makes them continue."""
    n = F.normalize(normal, dim=-1, eps=1e-12)
    z = depth.detach()
    opaque = alpha.detach() > 0.5
    total, weight = n.new_zeros(()), n.new_zeros(())
    for dim in (0, 1):  # rows, then columns: each pixel and the one after it
        size = z.shape[dim] - 1
        near = z.narrow(dim, 1, size)
        w = torch.exp(-z.diff(dim=dim).abs() / (step * near.clamp(min=1e-6)))
        w = w * (opaque.narrow(dim, 0, size) & opaque.narrow(dim, 1, size)).to(w.dtype)
        total = total + (n.diff(dim=dim).abs().sum(-1) * w).sum()
        weight = weight + w.sum()
    return total / weight.clamp(min=1)


def depth_curvature_loss(depth: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Mean |z_(p-1) - 2 z_p + z_(p+1)| / z_p along rows and columns, where all three pixels
    are mostly opaque: 0 on any plane, small on a smooth surface, large where one patch of a
    surface sits in front of or behind its neighbours. The events say where a texture's edges
    are, not where the inside of a patch of one color is: a robust (L1) prior that surfaces
    continue across such edges."""
    opaque = alpha.detach() > 0.5
    total, count = depth.new_zeros(()), depth.new_zeros(())
    for dim in (0, 1):
        size = depth.shape[dim] - 2
        m = opaque.narrow(dim, 0, size) & opaque.narrow(dim, 1, size) & opaque.narrow(dim, 2, size)
        m = m.to(depth.dtype)
        middle = depth.narrow(dim, 1, size).detach().clamp(min=1e-6)
        total = total + (depth.diff(n=2, dim=dim).abs() / middle * m).sum()
        count = count + m.sum()
    return total / count.clamp(min=1)


def structure_block_loss(
    depth: torch.Tensor,
    alpha: torch.Tensor,
    points: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    tolerance: float,
    opaque: float = 1.0,
) -> torch.Tensor:
    """Each stereo point blocks its ray: at the render's pixel [H, W] nearest each point [N, 3]
    (world) in front of the camera ``viewmat`` [4, 4], mean of ``opaque`` * (1 - alpha) +
    max(0, depth / z - 1 - ``tolerance``), z the point's depth. One-sided: a surface in front
    of the point (an occluder) passes. What the events saw a surface at is not seen through:
    a pale object on a pale floor makes few events inside its outline, and without this its
    Gaussians fade while the floor behind, held opaque, shows through it."""
    H, W = depth.shape
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    uv = cam @ K.T
    u = torch.round(uv[:, 0] / z.clamp(min=1e-6)).long()
    v = torch.round(uv[:, 1] / z.clamp(min=1e-6)).long()
    seen = (z > 1e-3) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    if not bool(seen.any()):
        return depth.new_zeros(())
    index = v[seen] * W + u[seen]
    a, d = alpha.reshape(-1)[index], depth.reshape(-1)[index]
    behind = (d / z[seen] - 1 - tolerance).clamp(min=0)
    return (opaque * (1 - a) + behind).mean()
