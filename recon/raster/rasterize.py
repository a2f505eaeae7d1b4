"""Differentiable rendering of 3D Gaussians: one interface, three backends.

``cpu``: compiled kernels with a hand-written backward pass (recon/raster/_cpu.py), the
default on the CPU. ``torch``: pure PyTorch, autograd for the backward pass
(recon/raster/_torch.py): the readable reference, runs everywhere. ``gsplat``: gsplat's CUDA
kernels (recon/raster/_gsplat.py), used on a CUDA device when gsplat is installed. All take the
same Gaussians and camera and return the same maps; the cpu and torch backends are tested
against each other and against a per-pixel reference (recon/raster/_reference.py), gsplat
against torch where a GPU is present.

Conventions: the camera is OpenCV's (x right, y down, z forward), ``viewmat`` maps world to
camera, ``K`` has the pixel centres at integer coordinates (as OpenCV calibrations do).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import assert_never

import torch

from evcap.errors import InputError, NumericalError
from evcap.recon.config import BACKENDS, Backend


@dataclass
class Camera:
    viewmat: torch.Tensor  # [4, 4] world to camera
    K: torch.Tensor  # [3, 3]
    width: int
    height: int

    @property
    def center(self) -> torch.Tensor:
        """The camera centre in world coordinates."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ t


@dataclass
class Render:
    color: torch.Tensor  # [H, W, D] alpha-composited features, background added
    depth: torch.Tensor  # [H, W] expected camera z (sum w z / sum w); 0 where alpha is 0
    alpha: torch.Tensor  # [H, W] accumulated opacity
    normal: torch.Tensor  # [H, W, 3] composited unit normals of the Gaussians, camera frame
    means2d: torch.Tensor  # [..., N, 2] projected centres, pixels; their .grad drives densification
    visible: torch.Tensor  # [N] bool, the Gaussians that touched a pixel
    # [N] each Gaussian's largest blending weight (alpha times the transmittance before it)
    # over the pixels, no gradient; None where the backend does not count it (gsplat)
    peak: torch.Tensor | None = None


def gaussian_normals(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """World-frame normal of each Gaussian: the axis of its smallest scale (unsigned)."""
    R = quat_to_rotmat(quats)
    axis = scales.argmin(dim=1)
    return torch.gather(R, 2, axis[:, None, None].expand(-1, 3, 1)).squeeze(2)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """[N, 4] quaternions (w, x, y, z; any norm) to [N, 3, 3] rotation matrices."""
    q = q / q.norm(dim=1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=1,
    ).reshape(-1, 3, 3)


def camera_normals(
    quats: torch.Tensor, scales: torch.Tensor, means: torch.Tensor, camera: Camera
) -> torch.Tensor:
    """Each Gaussian's normal in the camera frame, turned to face the camera."""
    R = camera.viewmat[:3, :3]
    n = gaussian_normals(quats, scales) @ R.T
    p = means @ R.T + camera.viewmat[:3, 3]
    flip = (n * p).sum(1, keepdim=True) > 0
    return torch.where(flip, -n, n)


def default_backend(device: torch.device | str) -> Backend:
    """cpu on the CPU; on a CUDA device gsplat when it imports and works, else torch."""
    if torch.device(device).type != "cuda":
        return "cpu"
    from evcap.recon.raster import _gsplat as _raster_gsplat

    return "gsplat" if _raster_gsplat.available() else "torch"


def pick_backend(name: Backend | None, device: torch.device | str) -> Backend:
    """The backend asked for (None: the device's default), if it can render on ``device``."""
    if name is None:
        return default_backend(device)
    if name not in BACKENDS:
        raise InputError(f"unknown rasterizer backend {name!r}; expected one of {BACKENDS}")
    on_cuda = torch.device(device).type == "cuda"
    match name:
        case "cpu":
            if on_cuda:
                raise InputError(
                    "--backend cpu renders on the CPU: use --device cpu, or gsplat or torch"
                )
        case "torch":
            pass
        case "gsplat":
            from evcap.recon.raster import _gsplat as _raster_gsplat

            if not on_cuda or not _raster_gsplat.available():
                raise InputError(
                    "--backend gsplat needs --device cuda, a CUDA GPU and gsplat (pip install "
                    "'evcap[cuda]'); use cpu or torch here"
                )
        case _:
            assert_never(name)
    return name


def _check_inputs(means, quats, scales, opacities, features) -> None:
    """Shapes that agree, and finite values: a NaN would render a finite image whose gradients
    are NaN, silently. The values are checked on the CPU only: on a GPU the check would make
    every render wait for the host (the trainers check their parameters every few steps)."""
    n = means.shape[0]
    shapes = {"means": [n, 3], "quats": [n, 4], "scales": [n, 3], "opacities": [n]}
    shapes["features"] = [n, features.shape[-1]]
    values = {"means": means, "quats": quats, "scales": scales, "opacities": opacities}
    for name, value in {**values, "features": features}.items():
        if list(value.shape) != shapes[name]:
            raise ValueError(f"rasterize: {name} must be {shapes[name]}, not {list(value.shape)}")
        if value.is_cuda or not n or math.isfinite(float(value.detach().sum())):
            continue  # a sum is finite only if every term is: one pass, the count only then
        bad = int((~torch.isfinite(value.detach())).reshape(n, -1).any(1).sum())
        if bad:
            raise NumericalError(
                f"rasterize: {name} not finite (NaN or infinite) for {bad:,} of {n:,} "
                "Gaussians: the optimisation diverged; lower its learning rates"
            )


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    camera: Camera,
    *,
    background: torch.Tensor | None = None,
    backend: Backend = "cpu",
    near: float = 0.01,
    surfels: bool = False,
    depth_squared: bool = False,
) -> Render:
    """Render N Gaussians (means [N, 3], quats [N, 4], scales [N, 3] (not log), opacities [N]
    in (0, 1), features [N, D] (colors, or any per-Gaussian values)) into ``camera``.
    ``background`` [H, W, D] or [D] is added where the Gaussians leave light through.
    ``surfels``: each Gaussian a flat disc met by each pixel's ray (recon/raster/surfels.py);
    with ``depth_squared`` the features' last channel is then each pair's depth squared (a
    3D Gaussian's depth is its centre's: the caller gives its square)."""
    _check_inputs(means, quats, scales, opacities, features)
    match backend, surfels:
        case "cpu", False:
            from evcap.recon.raster._cpu import rasterize_cpu as impl
        case "cpu", True:
            from evcap.recon.raster._cpu_surfels import rasterize_surfels_cpu as impl
        case "torch", False:
            from evcap.recon.raster._torch import rasterize_torch as impl
        case "torch", True:
            from evcap.recon.raster.surfels import rasterize_surfels_torch as impl
        case "gsplat", False:
            from evcap.recon.raster._gsplat import rasterize_gsplat as impl
        case "gsplat", True:
            raise InputError(
                "surfels render on the cpu or torch backend: gsplat's 2DGS rasterizer has not "
                "been run with evcap yet (--backend torch on a GPU)"
            )
        case _:
            assert_never(backend)
    more = {"depth_squared": True} if surfels and depth_squared else {}
    out = impl(means, quats, scales, opacities, features, camera, near, **more)
    if background is not None:
        out.color = out.color + (1 - out.alpha)[..., None] * background
    return out
