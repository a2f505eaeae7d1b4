"""A per-pixel reference rasterizer: the 3DGS compositing rule written as the plain loop it is.
Slow; only for tests of the fast backends (tiny images, a few Gaussians)."""

from __future__ import annotations

import torch

from evcap.recon.raster._torch import ALPHA_MAX, ALPHA_MIN, T_MIN, project
from evcap.recon.raster.rasterize import Camera, Render


def composite_reference(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    values: torch.Tensor,
    order: list[int],
    width: int,
    height: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Each pixel's sum of w values [H, W, C] and alpha [H, W], the Gaussians taken front to
    back in ``order``."""
    rows, alphas = [], []
    for y in range(height):
        for x in range(width):
            T = torch.ones((), dtype=values.dtype)
            acc = torch.zeros(values.shape[1], dtype=values.dtype)
            for i in order:
                dx, dy = x - means2d[i, 0], y - means2d[i, 1]
                a, b, c = conics[i]
                sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                if sigma < 0:  # only from rounding: the conic is positive definite
                    continue
                alpha = torch.clamp(opacities[i] * torch.exp(-sigma), max=ALPHA_MAX)
                if alpha < ALPHA_MIN:
                    continue
                if T * (1 - alpha) <= T_MIN:
                    break
                acc = acc + T * alpha * values[i]
                T = T * (1 - alpha)
            rows.append(acc)
            alphas.append(1 - T)
    out = torch.stack(rows).reshape(height, width, -1)
    return out, torch.stack(alphas).reshape(height, width)


def rasterize_reference(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    normals: torch.Tensor,
    camera: Camera,
    near: float,
) -> Render:
    proj = project(means, quats, scales, camera, near)
    order = [int(i) for i in torch.argsort(proj.depths) if proj.valid[i]]
    values = torch.cat([features, proj.depths[:, None], normals], dim=1)
    out, alpha = composite_reference(
        proj.means2d, proj.conics, opacities, values, order, camera.width, camera.height
    )
    D = features.shape[1]
    depth = out[..., D] / alpha.clamp(min=1e-10)
    visible = torch.zeros(len(means), dtype=torch.bool)
    return Render(out[..., :D], depth, alpha, out[..., D + 1 :], proj.means2d, visible)


def rasterize_surfels_reference(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    camera: Camera,
    near: float,
) -> Render:
    """Surfels (recon/raster/surfels.py) pixel by pixel, every disc tried at every pixel (no
    boxes), front to back by their centres' depths."""
    from evcap.recon.raster.surfels import ray_splat, surfel_matrices, surfel_normals

    M = surfel_matrices(means, quats, scales, camera)
    centre = M[:, :2, 2] / M[:, 2:, 2]
    normals = surfel_normals(quats, means, camera)
    order = [int(i) for i in torch.argsort(M[:, 2, 2].detach()) if M[i, 2, 2] > near]
    D = features.shape[1]
    rows, alphas = [], []
    for y in range(camera.height):
        for x in range(camera.width):
            T = torch.ones((), dtype=features.dtype)
            acc = torch.zeros(D + 4, dtype=features.dtype)
            for i in order:
                px, py = torch.tensor([x]), torch.tensor([y])
                alpha, z = ray_splat(
                    M[i : i + 1], centre[i : i + 1], opacities[i : i + 1], px, py, near
                )
                alpha, z = alpha[0], z[0]
                if alpha < ALPHA_MIN:
                    continue
                if T * (1 - alpha) <= T_MIN:
                    break
                acc = acc + T * alpha * torch.cat([features[i], z[None], normals[i]])
                T = T * (1 - alpha)
            rows.append(acc)
            alphas.append(1 - T)
    out = torch.stack(rows).reshape(camera.height, camera.width, -1)
    alpha = torch.stack(alphas).reshape(camera.height, camera.width)
    depth = out[..., D] / alpha.clamp(min=1e-10)
    visible = torch.zeros(len(means), dtype=torch.bool)
    return Render(out[..., :D], depth, alpha, out[..., D + 1 :], centre, visible)
