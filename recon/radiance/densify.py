"""Densification as a strategy, in gsplat's shape: a strategy holds its settings in steps, the
trainer holds its state (a dict it never looks inside, saved with the training's) and calls its
hooks around backward; ``Strategy`` is the base another strategy swaps in for.

``DefaultStrategy`` is 3DGS's adaptive density control: clone small Gaussians and split large
ones where the screen-space positional gradient is high, prune transparent or huge ones, reset
opacities. Every change keeps the optimiser's moments in step with the parameters."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from evcap.errors import InputError
from evcap.recon.raster.rasterize import Render, quat_to_rotmat
from evcap.recon.scene.gaussians import PARAMS, Gaussians
from evcap.recon.scene.optics import RenderGrid
from evcap.recon.scene.volume import Ball


@dataclass(frozen=True)
class DensifyConfig:
    """3DGS's adaptive density control, as a stage's settings (fractions of the run, made
    steps where the stage starts: DefaultStrategy.for_run)."""

    start: float = 0.05
    """The fraction of the run after which it densifies."""
    stop: float = 0.6
    """The fraction of the run until which it densifies (and resets opacities)."""
    every: int = 100
    """Steps between two densifications."""
    grad_threshold: float = 2e-4
    """The mean screen-space gradient (NDC units) that densifies a Gaussian."""
    percent_dense: float = 0.01
    """Clone a Gaussian below, split one above this fraction of the scene's extent."""
    min_opacity: float = 0.005
    """Gaussians less opaque are pruned."""
    reset_every: int = 0
    """Steps between two opacity resets; 0: never (resets upset the event loss on short
    runs)."""
    max_gaussians: int = 15_000
    """It grows no further than this many Gaussians."""
    confine: float = 0.0
    """Gaussians that leave the foreground's ball (recon/scene/volume.py foreground_ball: as
    wide as the events' structure where stage I starts on it, else the ball the cameras
    converge on), grown by this factor, are pruned every ``every`` steps after ``start``, to
    the end of the run: what lies beyond is the background's (0: never)."""
    bounds: tuple[float, float, float, float, float, float] | None = None
    """The foreground's box, when given (x0 y0 z0 x1 y1 z1: its corners, scene units, as
    `evcap export --bounds` takes it): Gaussians outside it are pruned as they are outside
    ``confine``'s ball; None: no box."""
    min_weight: float = 0.0
    """Gaussians whose largest blending weight (alpha times the transmittance in front) over
    every pixel of the views rendered since the last densification stays under this are
    pruned, at each densification and every ``every`` steps after it stops (E-4DGS: 0.015):
    a Gaussian in the backdrop's colour makes no event, but neither does it show. 0: never;
    the cpu and torch rasterizers count the weights, gsplat does not (nothing pruned)."""

    def __post_init__(self) -> None:
        if not 0 <= self.start <= self.stop <= 1:
            raise InputError(
                "densify.start and densify.stop are fractions of the run, start <= stop"
            )
        if self.every < 1 or self.reset_every < 0 or self.max_gaussians < 1:
            raise InputError("densify.every and max_gaussians must be at least 1, reset_every >= 0")
        if self.bounds is not None and (
            len(self.bounds) != 6
            or not all(a < b for a, b in zip(self.bounds[:3], self.bounds[3:], strict=True))
        ):
            raise InputError(
                "stage1.densify.bounds is a box: x0 y0 z0 x1 y1 z1, each of the max corner "
                "above the min"
            )
        if not 0 <= self.min_weight < 1:
            raise InputError("densify.min_weight is a blending weight: 0 (never) up to under 1")


class Strategy:
    """A densification strategy: its hooks are called at every step, around backward, with
    the state ``initialize_state`` made (the trainer saves it with the training and gives it
    back on going on). This base changes nothing."""

    def initialize_state(self) -> dict[str, torch.Tensor]:
        return {}

    def step_pre_backward(
        self,
        gaussians: Gaussians,
        optimizer: torch.optim.Optimizer,
        state: dict[str, torch.Tensor],
        step: int,
        renders: list[Render],
    ) -> None:
        """Before backward (a strategy that needs the renders' gradients asks for them)."""

    def step_post_backward(
        self,
        gaussians: Gaussians,
        optimizer: torch.optim.Optimizer,
        state: dict[str, torch.Tensor],
        step: int,
        renders: list[Render],
        grid: RenderGrid,
    ) -> None:
        """After backward and the optimiser's step ``step`` (1-based)."""


@dataclass(frozen=True)
class DefaultStrategy(Strategy):
    """3DGS's adaptive density control, its schedule in steps."""

    start: int  # densifies after this step
    stop: int  # and up to this one
    every: int
    reset_every: int
    grad_threshold: float
    split_size: float  # scene units: clone below, split above
    min_opacity: float
    max_gaussians: int
    extent: float  # none larger than the scene survives
    confine_radius: float = 0.0  # scene units about ``center``; 0: not confined
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    box: tuple[float, ...] | None = None  # x0 y0 z0 x1 y1 z1: none outside survives
    min_weight: float = 0.0  # the largest blending weight a Gaussian must reach; 0: any

    @classmethod
    def for_run(
        cls, config: DensifyConfig, iterations: int, extent: float, bound: Ball | None
    ) -> DefaultStrategy:
        """The strategy of a run of ``iterations`` steps in a scene of ``extent``, its
        Gaussians confined to ``bound`` grown by config.confine (when both are given)."""
        confine = config.confine > 0 and bound is not None
        return cls(
            start=math.floor(config.start * iterations),
            stop=math.floor(config.stop * iterations),
            every=config.every,
            reset_every=config.reset_every,
            grad_threshold=config.grad_threshold,
            split_size=config.percent_dense * extent,
            min_opacity=config.min_opacity,
            max_gaussians=config.max_gaussians,
            extent=extent,
            confine_radius=config.confine * bound.radius if confine else 0.0,
            center=bound.center if confine else (0.0, 0.0, 0.0),
            box=config.bounds,
            min_weight=config.min_weight,
        )

    def initialize_state(self) -> dict[str, torch.Tensor]:
        """Each Gaussian's summed screen-space gradient, the views it was seen in and its
        largest blending weight, over the renders since the last densification (``views``
        of them counted that weight)."""
        return {
            "grad_sum": torch.zeros(0),
            "count": torch.zeros(0),
            "peak": torch.zeros(0),
            "views": torch.zeros(()),
        }

    def step_post_backward(
        self,
        gaussians: Gaussians,
        optimizer: torch.optim.Optimizer,
        state: dict[str, torch.Tensor],
        step: int,
        renders: list[Render],
        grid: RenderGrid,
    ) -> None:
        for r in renders:
            _observe(state, r, grid.width, grid.height)
        if self.start < step <= self.stop and step % self.every == 0:
            self.densify(gaussians, optimizer, state)
        elif step > self.start and step % self.every == 0:
            # after densification stops, what drifts out of the foreground or fades still goes
            keep = self.inside(gaussians) & self.shown(state, len(gaussians))
            if not keep.all():
                _select(gaussians, optimizer, keep)
            _restart(state, len(gaussians), gaussians.means.device)
        if self.reset_every and step % self.reset_every == 0 and step <= self.stop:
            reset_opacities(gaussians, optimizer)

    @torch.no_grad()
    def densify(
        self, model: Gaussians, optimizer: torch.optim.Optimizer, state: dict[str, torch.Tensor]
    ) -> dict[str, int]:
        n = len(model)
        device = model.means.device
        _fit(state, n, device)
        shown = self.shown(state, n)
        grad = state["grad_sum"] / state["count"].clamp(min=1)
        hot = grad >= self.grad_threshold
        big = model.scales.max(1).values > self.split_size
        room = max(self.max_gaussians - n, 0)
        clone = torch.nonzero(hot & ~big).squeeze(1)
        split = torch.nonzero(hot & big).squeeze(1)
        # when near the cap, the strongest gradients go first
        if len(clone) + len(split) > room:
            order = torch.argsort(grad[torch.cat([clone, split])], descending=True)[:room]
            chosen = torch.cat([clone, split])[order]
            clone, split = chosen[~big[chosen]], chosen[big[chosen]]
        new = {k: getattr(model, k).detach()[clone] for k in PARAMS}
        # a split Gaussian becomes two, drawn inside it and 1.6 times smaller
        s = model.scales[split]
        R = quat_to_rotmat(model.quats[split])
        for _ in range(2):
            offset = (R @ (torch.randn_like(s) * s)[:, :, None])[:, :, 0]
            part = {k: getattr(model, k).detach()[split] for k in PARAMS}
            part["means"] = part["means"] + offset
            part["log_scales"] = part["log_scales"] - math.log(1.6)
            new = {k: torch.cat([new[k], part[k]]) for k in PARAMS}
        _append(model, optimizer, new)
        keep = torch.ones(len(model), dtype=torch.bool, device=device)
        keep[:n] = shown  # the new ones have not been rendered yet
        keep[split] = False
        keep &= model.opacities >= self.min_opacity
        keep &= model.scales.max(1).values <= self.extent  # none larger than the scene
        keep &= torch.isfinite(model.means).all(1)
        keep &= self.inside(model)
        pruned = int((~keep).sum()) - len(split)
        _select(model, optimizer, keep)
        _restart(state, len(model), device)
        return {"cloned": len(clone), "split": len(split), "pruned": pruned}

    def inside(self, model: Gaussians) -> torch.Tensor:
        """[N] bool: the Gaussians inside the foreground's ball and box (all when neither)."""
        means = model.means.detach()
        inside = torch.ones(len(means), dtype=torch.bool, device=means.device)
        if self.confine_radius > 0:
            center = torch.as_tensor(self.center, dtype=means.dtype, device=means.device)
            inside &= (means - center).norm(dim=1) <= self.confine_radius
        if self.box is not None:
            box = torch.as_tensor(self.box, dtype=means.dtype, device=means.device)
            lo, hi = box[:3], box[3:]
            inside &= ((means >= lo) & (means <= hi)).all(1)
        return inside

    def shown(self, state: dict[str, torch.Tensor], n: int) -> torch.Tensor:
        """[n] bool: the Gaussians whose largest blending weight since the last densification
        reached min_weight (all when it is 0 or no render since counted the weights)."""
        _fit(state, n, state["grad_sum"].device)
        if self.min_weight <= 0 or not state["views"] > 0:
            return torch.ones(n, dtype=torch.bool, device=state["peak"].device)
        return state["peak"] >= self.min_weight


def _fit(state: dict[str, torch.Tensor], n: int, device: torch.device) -> None:
    """The state made anew for n Gaussians when it is not theirs (their number changed, or
    saved before it counted the weights)."""
    if "peak" not in state or len(state["grad_sum"]) != n or state["grad_sum"].device != device:
        _restart(state, n, device)


def _restart(state: dict[str, torch.Tensor], n: int, device: torch.device) -> None:
    """Nothing observed yet for n Gaussians."""
    for name in ("grad_sum", "count", "peak"):
        state[name] = torch.zeros(n, device=device)
    state["views"] = torch.zeros((), device=device)


@torch.no_grad()
def _observe(state: dict[str, torch.Tensor], render: Render, width: int, height: int) -> None:
    """Accumulate a render's screen-space gradients (after backward), in NDC units as 3DGS."""
    g = render.means2d.grad
    if g is None:
        return
    g = g.reshape(-1, 2).detach()
    # the two scales as numbers: a tensor of them copied to a GPU would wait for it
    g = torch.stack([g[:, 0] * (width / 2), g[:, 1] * (height / 2)], 1)
    _fit(state, len(g), g.device)
    seen = render.visible.to(g.dtype)  # as weights, not an index: no wait for the device
    state["grad_sum"] += g.norm(dim=1) * seen
    state["count"] += seen
    if render.peak is not None:
        state["peak"] = torch.maximum(state["peak"], render.peak.to(g.dtype))
        state["views"] += 1


@torch.no_grad()
def reset_opacities(model: Gaussians, optimizer: torch.optim.Optimizer) -> None:
    low = torch.logit(torch.clamp(model.opacities, max=0.01))
    _replace(model, optimizer, {"opacity_logits": low})


def _group(optimizer: torch.optim.Optimizer, name: str) -> dict:
    return next(g for g in optimizer.param_groups if g.get("name") == name)


def _swap(model: Gaussians, optimizer: torch.optim.Optimizer, name: str, value, moments) -> None:
    """Put a new tensor in place of a parameter, in the model and in the optimiser."""
    group = _group(optimizer, name)
    old = group["params"][0]
    state = optimizer.state.pop(old, None)
    param = torch.nn.Parameter(value)
    group["params"][0] = param
    setattr(model, name, param)
    if state is not None:
        state["exp_avg"], state["exp_avg_sq"] = moments(state["exp_avg"], state["exp_avg_sq"])
        optimizer.state[param] = state


def _append(model: Gaussians, optimizer: torch.optim.Optimizer, new: dict) -> None:
    for name in PARAMS:
        extra = new[name]
        _swap(
            model,
            optimizer,
            name,
            torch.cat([getattr(model, name).detach(), extra]),
            lambda m, v, e=extra: (
                torch.cat([m, torch.zeros_like(e)]),
                torch.cat([v, torch.zeros_like(e)]),
            ),
        )


def _select(model: Gaussians, optimizer: torch.optim.Optimizer, keep: torch.Tensor) -> None:
    for name in PARAMS:
        _swap(
            model,
            optimizer,
            name,
            getattr(model, name).detach()[keep],
            lambda m, v: (m[keep], v[keep]),
        )


def _replace(model: Gaussians, optimizer: torch.optim.Optimizer, values: dict) -> None:
    for name, value in values.items():
        _swap(
            model, optimizer, name, value, lambda m, v: (torch.zeros_like(m), torch.zeros_like(v))
        )
