"""Renders of the held-out views, read at the sensor's pixels (through its lens distortion), and
their metrics when the session has the ground truth."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from evcap.recon.metrics import (
    depth_abs_err,
    image_metrics,
    lpips_if_available,
    normal_mae_deg,
    srgb,
)
from evcap.recon.optics import SensorOptics, render_grid
from evcap.recon.radiance import RadianceField
from evcap.session import Session


@torch.no_grad()
def render_views(
    field: RadianceField, poses: np.ndarray, optics: SensorOptics, device: str = "cpu"
) -> dict[str, np.ndarray]:
    """radiance [N, H, W, 3] (linear), depth [N, H, W] (camera z), normal [N, H, W, 3] (unit,
    camera frame; 0 where nothing was rendered) and alpha [N, H, W], at the sensor's pixels."""
    grid = render_grid(optics, 1.0, device)
    H, W = optics.height, optics.width
    out: dict[str, list] = {"radiance": [], "depth": [], "normal": [], "alpha": []}
    for T in poses:
        r = field.render(T, grid)
        alpha = r.alpha[..., None]
        maps = torch.cat([r.color, r.depth[..., None] * alpha, alpha, r.normal], -1)
        s = grid.sample(maps).reshape(H, W, -1)
        a = s[..., 4]
        out["radiance"].append(s[..., :3])
        out["depth"].append(torch.where(a > 1e-6, s[..., 3] / a.clamp(min=1e-6), 0))
        out["alpha"].append(a)
        n = s[..., 5:8]
        out["normal"].append(torch.where(a[..., None] > 0.05, F.normalize(n, dim=-1), 0))
    return {k: torch.stack(v).cpu().numpy() for k, v in out.items()}


def test_views(session: Session) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The held-out poses [N, 4, 4] and whatever truth the session has for them."""
    if "gt" not in session.groups:
        return np.zeros((0, 4, 4)), {}
    g = session.group("gt")
    if "test_T_world_cam" not in g:
        return np.zeros((0, 4, 4)), {}
    truth = {k[5:]: g[k][:] for k in g if k.startswith("test_") and k != "test_T_world_cam"}
    return g["test_T_world_cam"][:], truth


def metrics(views: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> dict[str, float | None]:
    out: dict[str, float | None] = {}
    if "radiance" in truth:
        out.update(image_metrics(views["radiance"], truth["radiance"], "render"))
        out["lpips"] = lpips_if_available(srgb(views["radiance"]), srgb(truth["radiance"]))
    if "depth" in truth:
        out["depth_abs_err"] = depth_abs_err(views["depth"], truth["depth"])
    if "normal" in truth:
        out["normal_mae_deg"] = normal_mae_deg(views["normal"], truth["normal"])
    return out
