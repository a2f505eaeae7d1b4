"""Stage II's settings: its own few and its parts' (the loss's weights, the edge maps, the
learning rates), named by dotted paths from here (``loss.tv``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import get_args

from evcap.errors import InputError
from evcap.recon.config import EFFECT_MODES, EffectMode, NormalsFrom


@dataclass(frozen=True)
class MaterialLossConfig:
    """L = L_event + 1.0 L_rad + 0.1 L_GW + 0.05 L_TV (method.md), the TV weighted by
    exp(-beta M_edge)."""

    distill: float = 1.0
    """L_rad: the renders against stage I's."""
    anchor: float = 0.1
    """L_GW: the mean brightness (left out where the background is known)."""
    tv: float = 0.05
    """L_TV: the base color's and normals' total variation away from the edges."""
    tv_normals: float = 0.1
    """lambda_n: the normals' share of the TV."""
    edge_beta: float = 10.0
    """beta: how fast the TV's weight falls at an edge of the edge maps."""

    def __post_init__(self) -> None:
        if min(self.distill, self.anchor, self.tv, self.tv_normals, self.edge_beta) < 0:
            raise InputError("stage II's loss weights must be >= 0")


@dataclass(frozen=True)
class EdgeMapsConfig:
    """The event edge maps that weight the TV; their views are stage II's training frames."""

    slice_ms: float = 10.0
    """The events warped into each edge map."""
    frames: int = 48
    """Views with an edge map: the training frames of stage II."""

    def __post_init__(self) -> None:
        if self.slice_ms <= 0 or self.frames < 2:
            raise InputError("edges.slice_ms must be above 0 and edges.frames at least 2")


@dataclass(frozen=True)
class MaterialRates:
    """Adam's learning rates of stage II's parameters."""

    base_color: float = 0.05
    """The base color's (logits)."""
    roughness: float = 0.05
    """The roughness's (logits)."""
    normals: float = 0.01
    """The shading normals' (0: stage I's kept)."""
    indirect: float = 0.02
    """The indirect light's (spherical harmonics)."""
    light: float = 0.05
    """The environment light's (cube map)."""


@dataclass(frozen=True)
class MaterialConfig:
    """Stage II: base color, roughness, normals and the light, geometry frozen (method.md)."""

    iterations: int = 400
    """Optimisation steps."""
    visibility: EffectMode = "auto"
    """Shadows: "on", "off", or "auto": modelled where stage II's starting base color varies
    least with them (material.base_variation)."""
    indirect: EffectMode = "auto"
    """Light from other surfaces (the bounce baked with the visibility): "on", "off", "auto"."""
    normals_from: NormalsFrom = "planes"
    """Stage II's starting normals: "planes" (through each Gaussian's neighbours) or
    "gaussians" (each Gaussian's flattest axis, what stage I's normal loss trained)."""
    loss: MaterialLossConfig = MaterialLossConfig()
    """The loss's weights."""
    edges: EdgeMapsConfig = EdgeMapsConfig()
    """The edge maps and the training frames."""
    lr: MaterialRates = MaterialRates()
    """The learning rates."""

    def __post_init__(self) -> None:
        if self.iterations < 0:
            raise InputError("stage II's iterations must be at least 0")
        for effect in ("visibility", "indirect"):
            if getattr(self, effect) not in EFFECT_MODES:
                raise InputError(f'{effect} must be "auto", "on" or "off"')
        if self.normals_from not in get_args(NormalsFrom):
            raise InputError(f"normals_from must be one of {', '.join(get_args(NormalsFrom))}")
