"""Image and geometry metrics against a simulated session's ground truth.

Images are compared as displayed: linear radiance clipped to [0, 1], sRGB-encoded. Raw figures
come first. Events leave a radiance undetermined up to one gain per color channel, nothing more,
so the corrected (``_gain``) figures are taken after one gain per channel fitted once by least
squares on linear radiance over the scored pixels of all held-out views together (``gain_fit``);
a relit view keeps the gain of its un-relit fit. An affine fit per view also forgives haze and a
wrong tint; it is given only as a diagnostic (``_affine_per_view``).

Whole-image figures reward a blur: most pixels are the environment, and a smooth guess at it
scores well. The ``object_`` figures are taken on the object's pixels only (where the truth
has a surface), beside what a render without the object reaches there: the best constant
color. ``blur_psnr`` is what the truth itself, blurred, scores over the whole image; a
render below it has not resolved anything finer than that blur.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from evcap.images import fit_color_correction, fit_gain, srgb


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return 10 * math.log10(1.0 / max(mse, 1e-12))


def ssim_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SSIM per pixel [N, H, W] (11 x 11 Gaussian window, mean over channels) of images
    [N, H, W, C] in [0, 1]."""
    from kornia.metrics import ssim as kornia_ssim

    ta = torch.as_tensor(np.asarray(a, np.float32)).permute(0, 3, 1, 2)
    tb = torch.as_tensor(np.asarray(b, np.float32)).permute(0, 3, 1, 2)
    return kornia_ssim(ta, tb, 11, max_val=1.0).mean(1).numpy()


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Mean SSIM (11 x 11 Gaussian window) of images [N, H, W, C] in [0, 1]."""
    return float(ssim_map(a, b).mean())


def gain_fit(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """[3] the one gain per channel of linear renders [N, H, W, 3] against the truth, fitted by
    least squares over the pixels of all views together (those of ``mask`` [N, H, W])."""
    return fit_gain(pred, gt) if mask is None else fit_gain(pred[mask], gt[mask])


def image_metrics(
    pred: np.ndarray, gt: np.ndarray, prefix: str, gain: np.ndarray | None = None
) -> dict[str, float]:
    """PSNR and SSIM of linear images [N, H, W, 3], raw and after one gain per channel (fitted
    over all of them unless given)."""
    gain = gain_fit(pred, gt) if gain is None else gain
    a, b, c = srgb(pred), srgb(gt), srgb(pred * gain)
    return {
        f"{prefix}_psnr": psnr(a, b),
        f"{prefix}_ssim": ssim(a, b),
        f"{prefix}_psnr_gain": psnr(c, b),
        f"{prefix}_ssim_gain": ssim(c, b),
    }


BLUR_PX = 25  # the blur of blur_psnr: a Gaussian of this standard deviation, in sensor pixels


def constant_psnr(truth: np.ndarray) -> float:
    """The PSNR of the best single constant color for sRGB pixels [P, 3]: their mean."""
    return psnr(np.broadcast_to(truth.mean(0), truth.shape), truth)


def object_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """Figures of linear renders [N, H, W, 3] on the object's pixels (``mask`` [N, H, W]):
    sRGB PSNR as rendered, PSNR and mean SSIM after one gain per channel fitted there over all
    views, the PSNR of the best single constant color there, and (a diagnostic) the PSNR after
    an affine fit per view; {} without an object."""
    if not mask.any():
        return {}
    truth = srgb(gt)
    corrected = srgb(pred * gain_fit(pred, gt, mask))
    return {
        "object_psnr": psnr(srgb(pred)[mask], truth[mask]),
        "object_psnr_gain": psnr(corrected[mask], truth[mask]),
        "object_ssim_gain": float(ssim_map(corrected, truth)[mask].mean()),
        "object_psnr_constant": constant_psnr(truth[mask]),
        "object_psnr_affine_per_view": affine_per_view_psnr(pred, gt, mask),
    }


def affine_per_view_psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """The mean over the views of the PSNR on ``mask`` after a gain and an offset per channel
    fitted in each view alone: a diagnostic, never a result (it absorbs haze and tint)."""
    scores = []
    for p, g, m in zip(pred, gt, mask, strict=True):
        if m.any():
            cc = fit_color_correction(p[m], g[m])
            scores.append(psnr(srgb(p[m] * cc[:, 0] + cc[:, 1]), srgb(g[m])))
    return float(np.mean(scores))


def blur_psnr(gt: np.ndarray) -> float:
    """PSNR over whole images of the truth [N, H, W, 3] (linear) blurred by BLUR_PX, in sRGB."""
    import cv2

    truth = srgb(gt).astype(np.float32)
    return psnr(np.stack([cv2.GaussianBlur(t, (0, 0), BLUR_PX) for t in truth]), truth)


def depth_abs_err(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean |depth error| (scene units) where the truth has a surface."""
    m = gt > 0
    return float(np.abs(pred[m] - gt[m]).mean()) if m.any() else float("nan")


def depth_rel_err(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean |depth error| as a share of the camera's distance to the surface, where the truth
    has one."""
    m = gt > 0
    return float((np.abs(pred[m] - gt[m]) / gt[m]).mean()) if m.any() else float("nan")


def depth_within(pred: np.ndarray, gt: np.ndarray, share: float = 0.05) -> float:
    """The share of the pixels where the truth has a surface whose depth is within ``share``
    of it (does the depth map show the object's shape, not a slope that averages well)."""
    m = gt > 0
    return float((np.abs(pred[m] - gt[m]) <= share * gt[m]).mean()) if m.any() else float("nan")


def background_clear(alpha: np.ndarray, mask: np.ndarray) -> float:
    """The share of the pixels off the object (``mask`` False) where the Gaussians' alpha is
    below 0.5: the environment seen through, not fog."""
    off = ~mask
    return float((alpha[off] < 0.5).mean()) if off.any() else float("nan")


def silhouette_iou(alpha: np.ndarray, mask: np.ndarray) -> float:
    """Intersection over union of the rendered silhouette (alpha >= 0.5) and the object's
    pixels (``mask``): the shape a user sees against the truth's, fog and holes alike."""
    shown = alpha >= 0.5
    union = (shown | mask).sum()
    return float((shown & mask).sum() / union) if union else float("nan")


def normal_mae_deg(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean angle (degrees) between unit normals where the truth has a surface; a missing
    prediction (zero vector) counts as 90 degrees."""
    m = np.linalg.norm(gt, axis=-1) > 0.5
    if not m.any():
        return float("nan")
    p = pred[m] / np.maximum(np.linalg.norm(pred[m], axis=-1, keepdims=True), 1e-12)
    g = gt[m] / np.linalg.norm(gt[m], axis=-1, keepdims=True)
    cos = np.clip((p * g).sum(-1), -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)).mean())


def local_lpips_weights() -> tuple[Path, Path] | None:
    """The LPIPS weights already on this machine, if any: torchvision's AlexNet in torch's hub
    cache and the linear heads the lpips package ships (never downloaded)."""
    import importlib.util

    from torch.hub import get_dir

    backbone = Path(get_dir()) / "checkpoints" / "alexnet-owt-7be5be79.pth"
    spec = importlib.util.find_spec("lpips")
    if spec is None or spec.origin is None or not backbone.exists():
        return None
    heads = Path(spec.origin).parent / "weights" / "v0.1" / "alex.pth"
    return (backbone, heads) if heads.exists() else None


def lpips_if_available(pred: np.ndarray, gt: np.ndarray) -> float | None:
    """LPIPS (AlexNet) of sRGB images [N, H, W, 3] when its weights are on this machine
    (local_lpips_weights); None otherwise."""
    from evcap.recon.evaluate.lpips import Lpips

    weights = local_lpips_weights()
    return None if weights is None else Lpips(*weights)(pred, gt)


def surface_metrics(
    pred: np.ndarray,
    gt: np.ndarray,
    mask: np.ndarray,
    prefix: str,
    regions: dict | None = None,
    gain: np.ndarray | None = None,
) -> dict[str, float]:
    """PSNR and SSIM of a map [N, H, W, 3] on the surface only (``mask`` [N, H, W]), raw and
    after one gain per channel (fitted there over all views unless given); off the surface
    both images are 0 for SSIM; the PSNR of the best single constant color there
    (``_psnr_constant``). ``regions``: name -> mask, a PSNR (corrected) inside each."""
    if not mask.any():
        return {}
    gain = gain_fit(pred, gt, mask) if gain is None else gain
    corrected = np.where(mask[..., None], pred * gain, 0)
    raw = np.where(mask[..., None], pred, 0)
    truth = np.where(mask[..., None], gt, 0)
    a, b, c = srgb(raw), srgb(truth), srgb(corrected)
    out = {
        f"{prefix}_psnr": psnr(a[mask], b[mask]),
        f"{prefix}_ssim": ssim(a, b),
        f"{prefix}_psnr_gain": psnr(c[mask], b[mask]),
        f"{prefix}_ssim_gain": ssim(c, b),
        f"{prefix}_psnr_constant": constant_psnr(b[mask]),
    }
    for name, region in (regions or {}).items():
        region = region & mask
        if region.any():
            out[f"{prefix}_psnr_gain_{name}"] = psnr(c[region], b[region])
            out[f"{name}_share"] = float(region.sum() / mask.sum())
    return out
