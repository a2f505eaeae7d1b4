"""The gsplat backend: gsplat's CUDA rasterization (gsplat >= 1.5), for CUDA devices.

gsplat puts pixel centres at +0.5 (the corner of pixel 0 is 0), OpenCV at 0: the principal
point is shifted by half a pixel on the way in. Normals travel as extra color channels.
"""

from __future__ import annotations

import functools

import torch

from evcap.recon.raster.rasterize import Camera, Render, camera_normals


@functools.cache
def available() -> bool:
    """True when gsplat imports and its CUDA kernels run here (first use builds them)."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat

        dev = torch.device("cuda")
        one = torch.ones(1, 3, device=dev)
        gsplat.rasterization(
            torch.tensor([[0.0, 0.0, 2.0]], device=dev),
            torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=dev),
            one * 0.1,
            torch.ones(1, device=dev) * 0.5,
            one,
            torch.eye(4, device=dev)[None],
            torch.tensor([[[10.0, 0, 8], [0, 10.0, 8], [0, 0, 1]]], device=dev),
            16,
            16,
        )
        return True
    except Exception:  # noqa: BLE001  any failure to import or build means: not here
        return False


def rasterize_gsplat(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    camera: Camera,
    near: float,
) -> Render:
    normals = camera_normals(quats, scales, means, camera)
    import gsplat

    K = camera.K.clone()
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    D = features.shape[1]
    colors, alphas, meta = gsplat.rasterization(
        means,
        quats,
        scales,
        opacities,
        torch.cat([features, normals], dim=1),
        camera.viewmat[None],
        K[None],
        camera.width,
        camera.height,
        near_plane=near,
        render_mode="RGB+ED",
        packed=False,
    )
    means2d = meta["means2d"]
    if means2d.requires_grad:
        means2d.retain_grad()
    radii = meta["radii"][0]
    visible = (radii > 0).all(-1) if radii.ndim == 2 else radii > 0
    alpha = alphas[0, ..., 0]
    depth = torch.where(alpha > 0, colors[0, ..., D + 3], torch.zeros_like(alpha))
    return Render(colors[0, ..., :D], depth, alpha, colors[0, ..., D : D + 3], means2d, visible)
