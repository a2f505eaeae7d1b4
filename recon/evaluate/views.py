"""Renders of the held-out views, read at the sensor's pixels (through its lens distortion), and
their metrics when the session has the ground truth."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from evcap.recon.evaluate.metrics import (
    background_clear,
    blur_psnr,
    depth_abs_err,
    depth_rel_err,
    depth_within,
    gain_fit,
    image_metrics,
    lpips_if_available,
    normal_mae_deg,
    object_metrics,
    silhouette_iou,
    srgb,
    surface_metrics,
)
from evcap.recon.material.stage import CHANNELS, MaterialField
from evcap.recon.radiance.stage import RadianceField
from evcap.recon.scene.optics import SensorOptics, render_grid
from evcap.records import TruthViews


@torch.no_grad()
def render_views(
    field: RadianceField | MaterialField,
    poses: np.ndarray,
    optics: SensorOptics,
    device: str = "cpu",
    light: list[torch.Tensor] | None = None,
) -> dict[str, np.ndarray]:
    """radiance [N, H, W, 3] (linear), depth [N, H, W] (camera z), normal [N, H, W, 3] (unit,
    camera frame; 0 where nothing was rendered) and alpha [N, H, W], at the sensor's pixels;
    from a stage-II field also base_color [N, H, W, 3] and roughness [N, H, W], its normals
    the shading normals, and its radiance lit by ``light`` when given."""
    grid = render_grid(optics, 1.0, device)
    H, W = optics.height, optics.width
    channels = CHANNELS if isinstance(field, MaterialField) else {"radiance": 3}
    names = [k for k in channels if k != "shading_normal"]
    out: dict[str, list] = {k: [] for k in ["depth", "normal", "alpha", *names]}
    for T in poses:
        r = field.render(T, grid) if light is None else field.render(T, grid, light)
        alpha = r.alpha[..., None]
        maps = torch.cat([r.depth[..., None] * alpha, alpha, r.normal, r.color], -1)
        s = grid.sample(maps).reshape(H, W, -1)
        a = s[..., 1]
        out["depth"].append(torch.where(a > 1e-6, s[..., 0] / a.clamp(min=1e-6), 0))
        out["alpha"].append(a)
        n, start = s[..., 2:5], 5
        for name, size in channels.items():
            value = s[..., start : start + size].squeeze(-1)
            start += size
            if name == "shading_normal":
                n = value
            else:
                out[name].append(value)
        out["normal"].append(torch.where(a[..., None] > 0.05, F.normalize(n, dim=-1), 0))
    return {k: torch.stack(v).cpu().numpy() for k, v in out.items()}


def shown_gain(radiance: np.ndarray, truth: TruthViews) -> np.ndarray | None:
    """[3] the gain a render's radiance [N, H, W, 3] is shown with beside the truth: the one
    ``object_psnr_gain`` is taken after (over the whole images without an object); None
    without the truth's radiance."""
    if truth.radiance is None:
        return None
    mask = truth.object_mask()
    return gain_fit(radiance, truth.radiance, mask if mask is not None and mask.any() else None)


def metrics(views: dict[str, np.ndarray], truth: TruthViews) -> dict[str, float | None]:
    """Stage I against the truth: the render (whole image and the object's pixels), depth and
    normals."""
    out: dict[str, float | None] = {}
    mask = truth.object_mask()
    if truth.radiance is not None and mask is not None:
        out.update(object_metrics(views["radiance"], truth.radiance, mask))
    if truth.radiance is not None:
        out["blur_psnr"] = blur_psnr(truth.radiance)
        out.update(image_metrics(views["radiance"], truth.radiance, "render"))
        out["lpips"] = lpips_if_available(srgb(views["radiance"]), srgb(truth.radiance))
    if truth.depth is not None:
        out["depth_abs_err"] = depth_abs_err(views["depth"], truth.depth)
        out["depth_rel_err"] = depth_rel_err(views["depth"], truth.depth)
        out["depth_within_5pct"] = depth_within(views["depth"], truth.depth)
    if mask is not None:
        out["background_clear"] = background_clear(views["alpha"], mask)
        out["silhouette_iou"] = silhouette_iou(views["alpha"], mask)
    if truth.normal is not None:
        out["normal_mae_deg"] = normal_mae_deg(views["normal"], truth.normal)
    return out


SHADOW_BELOW = 0.7  # a surface point in shadow: less than this of its direct light reaches it
BLEEDING_ABOVE = 0.1  # color bleeding: the bounce brings more than this share of its radiance


def material_metrics(
    views: dict[str, np.ndarray], truth: TruthViews, radiance: np.ndarray | None = None
) -> dict[str, float | None]:
    """Stage II against the truth: base color (on the surface; also inside shadows and color
    bleeding when the truth marks them), roughness, normals, and the physically based render.
    ``radiance``: stage I's render of the same views, scored as a base color
    (``base_color_psnr_gain_baseline``: what no decomposition at all reaches)."""
    out: dict[str, float | None] = {}
    if truth.radiance is not None:
        out.update(image_metrics(views["radiance"], truth.radiance, "pbr_render"))
    if truth.normal is not None:
        out["normal_mae_deg"] = normal_mae_deg(views["normal"], truth.normal)
        surface = np.linalg.norm(truth.normal, axis=-1) > 0.5
        regions = {}
        if truth.visibility is not None:
            regions["shadow"] = truth.visibility < SHADOW_BELOW
        if truth.indirect is not None and truth.radiance is not None:
            lum = np.array([0.2126, 0.7152, 0.0722])
            bounce, total = truth.indirect @ lum, truth.radiance @ lum
            regions["bleeding"] = bounce > BLEEDING_ABOVE * np.maximum(total, 1e-6)
        if truth.base_color is not None:
            out.update(
                surface_metrics(
                    views["base_color"], truth.base_color, surface, "base_color", regions
                )
            )
            if radiance is not None and surface.any():
                same = surface_metrics(radiance, truth.base_color, surface, "base_color")
                out["base_color_psnr_gain_baseline"] = same["base_color_psnr_gain"]
        if truth.roughness is not None and surface.any():
            err = np.abs(views["roughness"] - truth.roughness)[surface]
            out["roughness_mae"] = float(err.mean())
    return out


def relit_metrics(
    relit: np.ndarray,
    corrected: np.ndarray,
    truth: TruthViews,
    radiance: np.ndarray | None = None,
) -> dict[str, float]:
    """The held-out views rendered under the truth's second light against its renders, over
    the image and on the object's pixels (``relit_object_``): raw, ``relit`` as rendered under
    the light as given; ``_gain``, ``corrected``: rendered under that light brought into the
    model's units by the un-relit fit's gain (shown_gain) and taken back by it, so that nothing
    is fitted to the relit truth and the new light's tint is the model's to get right.
    ``radiance``: stage I's views, never relit, after their own gain
    (``relit_object_psnr_gain_baseline``)."""
    one, seen = np.ones(3), truth.relit_radiance

    def raw_and_corrected(score) -> dict[str, float]:
        """``score``'s raw figures of ``relit``, its ``_gain`` ones of ``corrected``."""
        out = {k: v for k, v in score(relit).items() if "_gain" not in k}
        return out | {k: v for k, v in score(corrected).items() if "_gain" in k}

    out = raw_and_corrected(lambda x: image_metrics(x, seen, "relit", one))
    mask = truth.object_mask()
    if mask is not None and mask.any():
        out.update(
            raw_and_corrected(lambda x: surface_metrics(x, seen, mask, "relit_object", gain=one))
        )
        if radiance is not None and truth.radiance is not None:
            gain = gain_fit(radiance, truth.radiance, mask)
            same = surface_metrics(radiance, seen, mask, "relit_object", gain=gain)
            out["relit_object_psnr_gain_baseline"] = same["relit_object_psnr_gain"]
    return out
