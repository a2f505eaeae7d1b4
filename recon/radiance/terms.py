"""Stage I's loss, L = L_event + 0.1 L_GW + 0.05 L_normal (method.md) and the terms of ours, as a
list of terms built once where the stage starts: each its weight, the step after which it
counts, and what it computes from a step's renders. Stage II builds its own list of the same
``Term``s (recon/material/stage.py)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from evcap.errors import InputError
from evcap.recon.events.loss import event_loss, log_radiance
from evcap.recon.radiance.losses import (
    anchor_loss,
    depth_curvature_loss,
    quiet_variation_loss,
    structure_block_loss,
    surface_terms,
)
from evcap.recon.raster.rasterize import Render
from evcap.recon.scene.optics import RenderGrid
from evcap.recon.scene.support_plane import rays_meet
from evcap.recon.step_timer import UNTIMED, StepTimer

if TYPE_CHECKING:
    from evcap.recon.radiance.config import RadianceConfig
    from evcap.recon.radiance.pose_refinement import PoseCorrections
    from evcap.recon.radiance.stage import RadianceField, TrainingData


@dataclass(frozen=True)
class TermConfig:
    """A term's weight and when it starts."""

    weight: float = 0.0
    """Its weight in the loss (0: left out)."""
    start: float = 0.0
    """The fraction of the run after which it counts."""

    def __post_init__(self) -> None:
        if self.weight < 0 or not 0 <= self.start <= 1:
            raise InputError("a term's weight must be >= 0 and its start in [0, 1]")


@dataclass(frozen=True)
class AnchorConfig(TermConfig):
    """The brightness anchor (g): the events give changes, not levels."""

    weight: float = 0.1
    """Its weight in the loss (0: left out; always left out where the background is known)."""
    level: float = 0.5
    """g: the mean rendered brightness it holds."""


@dataclass(frozen=True)
class SmoothConfig(TermConfig):
    """Neighbouring normals alike where the depth is continuous (losses.normal_smoothness_loss)."""

    step: float = 0.02
    """The relative depth jump that counts as an outline (not smoothed across)."""


@dataclass(frozen=True)
class BlockConfig(TermConfig):
    """The stereo's points block their rays (losses.structure_block_loss)."""

    tolerance: float = 0.03
    """How far behind a point, as a share of its depth, the rendered depth may lie."""
    opaque: float = 1.0
    """The weight of a point's pixel left unblocked (1 - alpha) beside the depth past it: a
    point outside an outline (the stereo's strays off a smooth object's limb) then asks for
    fog against the backdrop."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.tolerance < 0 or self.opaque < 0:
            raise InputError("loss.block needs tolerance >= 0 and opaque >= 0")


@dataclass(frozen=True)
class LossConfig:
    """Stage I's terms beside the event loss, each with its weight and start."""

    anchor: AnchorConfig = AnchorConfig()
    """The brightness anchor L_GW (method.md: 0.1)."""
    normal: TermConfig = TermConfig(0.05)
    """Normal consistency: rendered normals against those of the rendered depth (method.md:
    0.05)."""
    spread: TermConfig = TermConfig()
    """Surfaces, not fog: the spread of the depths along each ray (losses.depth_spread_loss)."""
    smooth: SmoothConfig = SmoothConfig()
    """Neighbouring normals alike on one surface."""
    curvature: TermConfig = TermConfig()
    """The rendered depth's curvature (losses.depth_curvature_loss)."""
    quiet_tv: TermConfig = TermConfig()
    """Total variation of the log radiance where no event fired (losses.quiet_variation_loss):
    what no edge crosses, the events leave free."""
    background_tv: TermConfig = TermConfig()
    """The background's log radiance alike between neighbouring texels: where no outline
    crosses it (a plain backdrop), the events leave it free."""
    alpha: TermConfig = TermConfig()
    """The mean rendered alpha: what the background can explain, it should."""
    opacity: TermConfig = TermConfig(0.01)
    """The mean opacity, as gsplat's opacity_reg: where the events say nothing, the fewest
    Gaussians that explain them."""
    block: BlockConfig = BlockConfig()
    """Where the events' stereo found a surface (init.on_events), its rays are blocked."""
    binary: TermConfig = TermConfig(0.0, 0.5)
    """Opacities pushed to 0 or 1: the mean of o (1 - o)."""
    flatten: TermConfig = TermConfig()
    """Gaussians flattened: the mean of their smallest over their largest scale."""


@dataclass(frozen=True)
class Term:
    """A term of a stage's loss: ``weight`` times ``value(inputs)``, counted at the steps after
    ``after``; one ``on_gaussians`` waits while stage I fits the background alone."""

    name: str
    weight: float
    after: int
    value: Callable[[Any], torch.Tensor]
    on_gaussians: bool = True


def total_loss(terms: list[Term], inputs: Any, step: int, background_alone: bool) -> torch.Tensor:
    """The weighted sum of the terms that count at ``step``, in the list's order."""
    total = None
    for term in terms:
        if step <= term.after or (background_alone and term.on_gaussians):
            continue
        value = term.value(inputs)
        part = value if term.weight == 1 else term.weight * value
        total = part if total is None else total + part
    assert total is not None, "a stage's list of terms starts with its event loss"
    return total


def after(start: float, iterations: int) -> int:
    """The step after which a term that starts at the fraction ``start`` of the run counts."""
    return math.floor(start * iterations)


@dataclass
class StepInputs:
    """What stage I's terms read of a step: its renders on ``grid`` at ``frames`` (their colors
    at the sensor's pixels in ``seen``), and ``logged``, where the terms put what the step's log
    shows."""

    field: RadianceField
    data: TrainingData
    grid: RenderGrid
    frames: np.ndarray
    renders: list[Render]
    seen: list[torch.Tensor]
    corrections: PoseCorrections | None = None  # when the poses are refined at this step
    step: int = 0
    timer: StepTimer = UNTIMED
    logged: dict[str, torch.Tensor] = field(default_factory=dict)


def stage_one_terms(config: RadianceConfig, refines_poses: bool) -> list[Term]:
    """Stage I's terms, in the order they are summed (the event loss first; those of the
    Gaussians after those of the background), the terms of weight 0 left out."""
    n = config.iterations
    loss = config.loss

    def event(x: StepInputs) -> torch.Tensor:
        ev = event_loss(x.seen, x.frames, x.data, config.event_loss, x.timer)
        x.logged["event"] = ev.detach()
        return ev

    def anchor(x: StepInputs) -> torch.Tensor:
        an = anchor_loss(torch.cat(x.seen), loss.anchor.level)
        x.logged["anchor"] = an.detach()
        return an

    def quiet_tv(x: StepInputs) -> torch.Tensor:
        H, W = x.data.optics.height, x.data.optics.width
        _, counts = x.data.windows.log_change(int(x.frames[0]), int(x.frames[-1]))
        loud = ((counts > 0) | ~x.data.mask).reshape(H, W)
        eps = config.event_loss.log_eps
        tv = sum(quiet_variation_loss(log_radiance(s, eps).reshape(H, W, 3), loud) for s in x.seen)
        return tv / len(x.seen)

    surfaces = (loss.normal, loss.spread, loss.smooth)
    starts = [after(t.start, n) for t in surfaces]

    def surface(x: StepInputs) -> torch.Tensor:
        # the three share one compiled pass: one term, their weighted sum
        which = tuple(t.weight > 0 and x.step > s for t, s in zip(surfaces, starts, strict=True))
        parts = sum(
            surface_terms(
                r.normal,
                r.depth,
                r.alpha,
                r.color[..., 3] if which[1] else None,
                x.grid.K,
                loss.smooth.step,
                which,
            )
            for r in x.renders
        ) / len(x.renders)
        x.logged["normal"] = parts[0].detach()
        return sum(t.weight * parts[k] for k, t in enumerate(surfaces) if which[k])

    def curvature(x: StepInputs) -> torch.Tensor:
        return sum(depth_curvature_loss(r.depth, r.alpha) for r in x.renders) / len(x.renders)

    def alpha(x: StepInputs) -> torch.Tensor:
        support, ball = x.data.support, x.data.bound
        if config.init.on_support == 0 or support is None or ball is None:
            return torch.stack([r.alpha.mean() for r in x.renders]).mean()
        # the backdrop is not seen through the support: its pixels are asked to be opaque
        total = x.renders[0].alpha.new_zeros(())
        for f, r in zip(x.frames, x.renders, strict=True):
            viewmat = x.data.viewmats()[int(f)]
            origin = -viewmat[:3, :3].T @ viewmat[:3, 3]
            meets = rays_meet(support, ball, x.grid.directions(viewmat), origin)
            total = total + torch.where(meets, 1 - r.alpha, r.alpha).mean()
        return total / len(x.renders)

    def block(x: StepInputs) -> torch.Tensor:
        if x.data.structure is None:
            return x.renders[0].alpha.new_zeros(())
        points = torch.as_tensor(x.data.structure, dtype=torch.float32, device=x.grid.K.device)
        viewmats = x.data.viewmats()
        total = sum(
            structure_block_loss(
                r.depth,
                r.alpha,
                points,
                viewmats[int(f)],
                x.grid.K,
                loss.block.tolerance,
                loss.block.opaque,
            )
            for f, r in zip(x.frames, x.renders, strict=True)
        )
        return total / len(x.renders)

    def binary(x: StepInputs) -> torch.Tensor:
        o = x.field.gaussians.opacities
        return (o * (1 - o)).mean()

    def flatten(x: StepInputs) -> torch.Tensor:
        s = x.field.gaussians.log_scales
        return (s.min(1).values - s.max(1).values).exp().mean()

    terms = [Term("event", 1.0, 0, event, on_gaussians=False)]
    if config.background.known is None and loss.anchor.weight > 0:
        terms.append(Term("anchor", loss.anchor.weight, after(loss.anchor.start, n), anchor, False))
    if refines_poses and config.poses.smooth_weight > 0:
        smooth = config.poses.smooth_weight
        terms.append(
            Term("pose_smooth", smooth, after(config.poses.start, n), _pose_smoothness, False)
        )
    for name, term, value in (
        ("quiet_tv", loss.quiet_tv, quiet_tv),
        ("background_tv", loss.background_tv, lambda x: x.field.background.log_variation()),
    ):
        if term.weight > 0:
            terms.append(Term(name, term.weight, after(term.start, n), value, False))
    if any(t.weight > 0 for t in surfaces):
        first = min(s for t, s in zip(surfaces, starts, strict=True) if t.weight > 0)
        terms.append(Term("surface", 1.0, first, surface))
    for name, term, value in (
        ("curvature", loss.curvature, curvature),
        ("alpha", loss.alpha, alpha),
        ("block", loss.block, block),
        ("opacity", loss.opacity, lambda x: x.field.gaussians.opacities.mean()),
        ("binary", loss.binary, binary),
        ("flatten", loss.flatten, flatten),
    ):
        if term.weight > 0:
            terms.append(Term(name, term.weight, after(term.start, n), value))
    return terms


def _pose_smoothness(x: StepInputs) -> torch.Tensor:
    assert x.corrections is not None, "the term counts only while the poses are refined"
    return x.corrections.smoothness()
