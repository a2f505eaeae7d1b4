"""3DGS's adaptive density control: clone small Gaussians and split large ones where the
screen-space positional gradient is high, prune transparent or huge ones, reset opacities.
Every change keeps the optimiser's moments in step with the parameters."""

from __future__ import annotations

import math

import torch

from evcap.recon.config import RadianceConfig
from evcap.recon.raster.rasterize import Render, quat_to_rotmat
from evcap.recon.scene.gaussians import PARAMS, Gaussians
from evcap.recon.scene.volume import SceneVolume


class Densifier:
    def __init__(
        self, config: RadianceConfig, extent: float, volume: SceneVolume | None = None
    ) -> None:
        self.config = config
        self.extent = extent
        self.volume = volume
        self.grad_sum = torch.zeros(0)
        self.count = torch.zeros(0)

    def _fit(self, n: int, device: torch.device) -> None:
        if len(self.grad_sum) != n or self.grad_sum.device != device:
            self.grad_sum = torch.zeros(n, device=device)
            self.count = torch.zeros(n, device=device)

    @torch.no_grad()
    def observe(self, render: Render, width: int, height: int) -> None:
        """Accumulate a render's screen-space gradients (after backward), in NDC units as 3DGS."""
        g = render.means2d.grad
        if g is None:
            return
        g = g.reshape(-1, 2).detach()
        # the two scales as numbers: a tensor of them copied to a GPU would wait for it
        g = torch.stack([g[:, 0] * (width / 2), g[:, 1] * (height / 2)], 1)
        self._fit(len(g), g.device)
        seen = render.visible.to(g.dtype)  # as weights, not an index: no wait for the device
        self.grad_sum += g.norm(dim=1) * seen
        self.count += seen

    def due(self, step: int) -> tuple[bool, bool]:
        """(densify now, reset opacities now) after optimisation step ``step`` (1-based)."""
        c = self.config
        start, stop = c.densify_from * c.iterations, c.densify_until * c.iterations
        densify = start < step <= stop and step % c.densify_every == 0
        reset = bool(c.opacity_reset_every) and step % c.opacity_reset_every == 0 and step <= stop
        return densify, reset

    @torch.no_grad()
    def densify(self, model: Gaussians, optimizer: torch.optim.Optimizer) -> dict[str, int]:
        c = self.config
        n = len(model)
        device = model.means.device
        self._fit(n, device)
        grad = self.grad_sum / self.count.clamp(min=1)
        hot = grad >= c.grad_threshold
        big = model.scales.max(1).values > c.percent_dense * self.extent
        room = max(c.max_gaussians - n, 0)
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
        keep[split] = False
        keep &= model.opacities >= c.min_opacity
        keep &= model.scales.max(1).values <= self.extent  # none larger than the scene
        keep &= torch.isfinite(model.means).all(1)
        v = self.volume
        if c.confine > 0 and v is not None and v.converging:
            center = torch.as_tensor(v.center, dtype=model.means.dtype, device=model.means.device)
            keep &= (model.means.detach() - center).norm(dim=1) <= c.confine * v.radius
        pruned = int((~keep).sum()) - len(split)
        _select(model, optimizer, keep)
        self.grad_sum = torch.zeros(len(model), device=device)
        self.count = torch.zeros(len(model), device=device)
        return {"cloned": len(clone), "split": len(split), "pruned": pruned}

    @torch.no_grad()
    def reset_opacities(self, model: Gaussians, optimizer: torch.optim.Optimizer) -> None:
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
