"""The 3D Gaussians of the radiance field, their optimiser, and the learnable background."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from evcap.errors import InputError
from evcap.recon.scene.cube_map import cube_lookup
from evcap.recon.scene.neighbours import nearest
from evcap.recon.scene.sh import C0, eval_sh

PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")
# radiance = softplus(SH value): positive (its log is finite), linear for bright values
START_VALUE = math.log(math.expm1(0.5))  # softplus(START_VALUE) = 0.5, the anchor level


class Gaussians(torch.nn.Module):
    def __init__(
        self,
        means: torch.Tensor,
        log_scales: torch.Tensor,
        quats: torch.Tensor,
        opacity_logits: torch.Tensor,
        sh_dc: torch.Tensor,
        sh_rest: torch.Tensor,
    ) -> None:
        super().__init__()
        self.means = torch.nn.Parameter(means)
        self.log_scales = torch.nn.Parameter(log_scales)
        self.quats = torch.nn.Parameter(quats)
        self.opacity_logits = torch.nn.Parameter(opacity_logits)
        self.sh_dc = torch.nn.Parameter(sh_dc)  # [N, 1, 3]
        self.sh_rest = torch.nn.Parameter(sh_rest)  # [N, (degree + 1)^2 - 1, 3]

    @classmethod
    def random(
        cls,
        points: np.ndarray,
        sh_degree: int,
        generator: torch.Generator,
        max_scale: float = math.inf,
    ) -> Gaussians:
        """Gaussians at the given points, sized by the distance to their neighbours (at most
        ``max_scale``), mid-gray (with a little noise), faint, randomly turned."""
        means = torch.as_tensor(points, dtype=torch.float32)
        n = len(means)
        scale = _neighbour_distance(means).clamp(min=1e-7, max=max_scale)
        k = (sh_degree + 1) ** 2
        dc = START_VALUE / C0 + 0.1 * torch.randn(n, 1, 3, generator=generator)
        return cls(
            means,
            torch.log(scale)[:, None].repeat(1, 3),
            torch.randn(n, 4, generator=generator),
            torch.full((n,), math.log(0.1 / 0.9)),
            dc,
            torch.zeros(n, k - 1, 3),
        )

    @classmethod
    def on_surface(
        cls,
        points: np.ndarray,
        normals: np.ndarray,
        spacing: float,
        sh_degree: int,
        opacity: float = 0.95,
    ) -> Gaussians:
        """Flat, nearly opaque discs at surface ``points`` facing along their ``normals``, each
        as wide as the points' ``spacing``, mid-gray: a known surface to learn radiance on."""
        n = np.where(normals[:, 2:] < 0, -normals, normals)  # a disc is two-sided
        # the rotation taking +z to n: (w, x, y, z) = normalise(1 + n.z, z x n)
        quats = np.stack([1 + n[:, 2], -n[:, 1], n[:, 0], np.zeros(len(n))], 1)
        quats /= np.linalg.norm(quats, axis=1, keepdims=True)
        count = len(points)
        log_scales = np.log([0.8 * spacing, 0.8 * spacing, 0.02 * spacing])
        return cls(
            torch.as_tensor(points, dtype=torch.float32),
            torch.as_tensor(np.tile(log_scales, (count, 1)), dtype=torch.float32),
            torch.as_tensor(quats, dtype=torch.float32),
            torch.full((count,), math.log(opacity / (1 - opacity))),
            torch.full((count, 1, 3), START_VALUE / C0),
            torch.zeros(count, (sh_degree + 1) ** 2 - 1, 3),
        )

    @classmethod
    def joined(cls, parts: list[Gaussians]) -> Gaussians:
        """One set of the Gaussians of ``parts`` (their SH of one degree)."""
        return cls(*(torch.cat([getattr(p, k).detach() for p in parts]) for k in PARAMS))

    @torch.no_grad()
    def flatten_third_axis(self, ratio: float = 0.01) -> None:
        """Surfels (config.surfels): the third scale, which the discs do not use, a ``ratio``
        of the smaller of the other two, so that it stays the smallest (the normal's axis
        wherever the smallest axis is taken for it) and densification splits them within
        their planes."""
        s = self.log_scales
        s[:, 2] = s[:, :2].min(1).values + math.log(ratio)

    @classmethod
    def from_state(cls, state: dict[str, torch.Tensor]) -> Gaussians:
        """Gaussians from a state_dict (a checkpoint's)."""
        return cls(*(state[k].clone() for k in PARAMS))

    def __len__(self) -> int:
        return len(self.means)

    @property
    def sh_degree(self) -> int:
        return int(math.isqrt(self.sh_rest.shape[1] + 1)) - 1

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    def radiance(self, camera_center: torch.Tensor, degree: int | None = None) -> torch.Tensor:
        """[N, 3] linear radiance towards a camera at ``camera_center``."""
        degree = self.sh_degree if degree is None else min(degree, self.sh_degree)
        if degree == 0:
            return F.softplus(C0 * self.sh_dc[:, 0])
        dirs = F.normalize(self.means.detach() - camera_center, dim=1)
        coeffs = torch.cat([self.sh_dc, self.sh_rest], 1)
        return F.softplus(eval_sh(degree, coeffs, dirs))


def _neighbour_distance(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """Root mean square distance of each point to its k nearest neighbours (3DGS's start size)."""
    k = min(k, len(points) - 1)
    if k < 1:
        return torch.ones(len(points))
    distances, _ = nearest(points, points, k + 1)
    near = distances[:, 1:]  # the first is the point itself
    return torch.from_numpy(np.sqrt((near * near).mean(1))).to(points.dtype)


class Background(torch.nn.Module):
    """The distant background: radiance as a function of the world direction, seen wherever
    the Gaussians leave light through. A cube map (six square faces, bilinear, through a
    softplus): sharp where the distance has edges (a horizon, a skyline), which low-order
    spherical harmonics smear into rings that Gaussians then try to cover as fog; and it has no
    preferred "up", which the poses of a real session do not give."""

    def __init__(self, size: int) -> None:
        super().__init__()
        self.faces = torch.nn.Parameter(torch.full((6, 3, size, size), START_VALUE))

    @classmethod
    def from_faces(cls, faces: torch.Tensor) -> Background:
        background = cls(faces.shape[-1])
        background.faces.data.copy_(faces)
        return background

    def forward(self, dirs: torch.Tensor) -> torch.Tensor:
        """Radiance [..., 3] in world directions [..., 3]."""
        return F.softplus(cube_lookup(self.faces, dirs))

    def log_variation(self) -> torch.Tensor:
        """Mean absolute difference of the log radiance between neighbouring texels of each
        face (the seams between faces left out)."""
        log = torch.log(F.softplus(self.faces) + 1e-3)
        dx = (log[..., 1:] - log[..., :-1]).abs().mean()
        dy = (log[..., 1:, :] - log[..., :-1, :]).abs().mean()
        return dx + dy

    def radiance_faces(self) -> torch.Tensor:
        """The cube map's radiance [6, 3, S, S]."""
        return F.softplus(self.faces)


@dataclass(frozen=True)
class BackgroundConfig:
    """The distant background (Background)."""

    size: int = 64
    """Texels along an edge of each face of the cube map."""
    known: tuple[float, float, float] | None = None
    """The backdrop's radiance (linear RGB) when it is known, as a NeRF-Synthetic release's
    white behind every view: held there, not learnt, it fixes the gain the anchor is for (the
    anchor is then left out) and leaves no room for fog of its colour; none: it is learnt."""
    first: float = 0.0
    """The fraction of the run, at its start, that fits the background alone (the Gaussians
    hidden); never where the background is known."""

    def __post_init__(self) -> None:
        if self.size < 1 or not 0 <= self.first <= 1:
            raise InputError("background.size must be at least 1, background.first in [0, 1]")
        if self.known is not None and (len(self.known) != 3 or not all(v > 0 for v in self.known)):
            raise InputError("background.known is a radiance: three numbers above 0 (linear RGB)")


@dataclass(frozen=True)
class LearningRates:
    """Adam's learning rates of stage I's parameters."""

    means: float = 1.6e-4
    """The positions', in units of the scene's extent, at the start; they decay exponentially
    to ``means_final`` by the end of the run (3DGS)."""
    means_final: float = 1.6e-6
    """The positions' at the end of the run."""
    scales: float = 5e-3
    """The log scales'."""
    quats: float = 1e-3
    """The rotations'."""
    opacity: float = 0.025
    """The opacities' (logits)."""
    sh: float = 2.5e-3
    """The degree-0 radiance coefficients'; the higher bands take a twentieth of it."""
    background: float = 0.1
    """The background's: it must be learnt fast; where it lags, Gaussians grow in front of
    it."""

    def __post_init__(self) -> None:
        if min(self.means, self.means_final) <= 0:
            raise InputError("lr.means and lr.means_final must be above 0 (they decay by a log)")


def make_optimizer(
    model: Gaussians, background: Background, lr: LearningRates, extent: float
) -> torch.optim.Adam:
    groups = [
        {"params": [model.means], "lr": lr.means * extent, "name": "means"},
        {"params": [model.log_scales], "lr": lr.scales, "name": "log_scales"},
        {"params": [model.quats], "lr": lr.quats, "name": "quats"},
        {"params": [model.opacity_logits], "lr": lr.opacity, "name": "opacity_logits"},
        {"params": [model.sh_dc], "lr": lr.sh, "name": "sh_dc"},
        {"params": [model.sh_rest], "lr": lr.sh / 20, "name": "sh_rest"},
        {"params": [background.faces], "lr": lr.background, "name": "background"},
    ]
    return torch.optim.Adam(groups, lr=0.0, eps=1e-15)


def means_lr(lr: LearningRates, extent: float, step: int, iterations: int) -> float:
    """Exponential decay of the positions' learning rate over the run (3DGS)."""
    s = min(step / max(iterations, 1), 1.0)
    a, b = lr.means * extent, lr.means_final * extent
    return math.exp((1 - s) * math.log(a) + s * math.log(b))
