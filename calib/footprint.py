"""The pixel's footprint, from the sharpest straight edges of an APS image: how wide a region of
the image one pixel sees (its photodiode's area and the lens's blur together), as the sigma of
one Gaussian, in pixels. A DAVIS pixel's APS and DVS circuits share one photodiode, so the
frames' footprint is the events'.

Each straight edge (strong gradient, one orientation over its 7 x 7 neighbourhood) is read as
in the slanted-edge method (ISO 12233): the pixels of a 5-pixel stretch of it, each placed by
its centre's signed distance across the edge, fitted with a step seen through a Gaussian,
a + b * Phi((d - d0) / sigma). No interpolation between pixels widens the step, so sigma is
the footprint itself. An edge of the scene is never sharper than a step, so its sigma is an
upper bound on the footprint; the image's sharpest edges give the estimate (a low quantile
over the edges, ``share``). The image must not be motion-blurred: a still camera's frames, or
their median, which also drops what moves through them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from evcap.errors import InputError

MIN_EDGES = 20  # fewer well-fitted edges than this say nothing
HALF_WIDTH = 4  # pixels read on each side of an edge
HALF_LENGTH = 2  # pixels read along it on each side


@dataclass(frozen=True)
class Footprint:
    sigma_px: float  # the ``share`` quantile of the edges' sigmas
    median_px: float  # the median edge's
    edges: int  # edges fitted


def footprint(image: np.ndarray, *, share: float = 0.1, min_contrast: float = 0.1) -> Footprint:
    """The footprint of the pixels that took ``image`` (a [H, W] linear image: an APS frame,
    dark level taken off or not); ``min_contrast``: the least step an edge must make, as a
    share of the image's 99th percentile."""
    import cv2
    from scipy.optimize import least_squares
    from scipy.special import ndtr

    img = np.asarray(image, np.float64)
    if img.ndim != 2 or min(img.shape) < 4 * HALF_WIDTH:
        raise InputError(f"the footprint needs a grey image of at least {4 * HALF_WIDTH} pixels")
    gx = cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3) / 8
    tensor = [cv2.GaussianBlur(g, (7, 7), 1.5) for g in (gx * gx, gx * gy, gy * gy)]
    trace = tensor[0] + tensor[2]
    spread = np.sqrt(np.maximum((tensor[0] - tensor[2]) ** 2 + 4 * tensor[1] ** 2, 0))
    coherence = spread / np.maximum(trace, 1e-12)
    magnitude = np.hypot(gx, gy)
    strong = magnitude > np.percentile(magnitude, 99)
    margin = HALF_WIDTH + HALF_LENGTH + 1
    strong[:margin], strong[-margin:], strong[:, :margin], strong[:, -margin:] = (False,) * 4
    ys, xs = np.nonzero(strong & (coherence > 0.9))
    step_least = min_contrast * np.percentile(img, 99)
    reach = np.arange(-margin, margin + 1)
    dy, dx = (a.ravel() for a in np.meshgrid(reach, reach, indexing="ij"))
    sigmas = []
    for y, x in zip(ys, xs, strict=True):
        # the edge's normal from the structure tensor (the gradient's sign kept)
        angle = 0.5 * math.atan2(2 * tensor[1][y, x], tensor[0][y, x] - tensor[2][y, x])
        n = np.array([math.cos(angle), math.sin(angle)])
        if n @ (gx[y, x], gy[y, x]) < 0:
            n = -n
        across = dx * n[0] + dy * n[1]
        along = -dx * n[1] + dy * n[0]
        near = (np.abs(across) <= HALF_WIDTH) & (np.abs(along) <= HALF_LENGTH)
        d, v = across[near], img[y + dy[near], x + dx[near]]
        low, high = v[d < -2].mean(), v[d > 2].mean()
        if high - low < step_least:
            continue

        def residual(q, d=d, v=v):
            return q[0] + q[1] * ndtr((d - q[2]) / max(abs(q[3]), 1e-3)) - v

        fit = least_squares(residual, [low, high - low, 0.0, 0.5])
        a, b, d0, sigma = fit.x
        explained = 1 - (fit.fun**2).sum() / max(((v - v.mean()) ** 2).sum(), 1e-12)
        if explained > 0.98 and abs(d0) < 1 and b > step_least:
            sigmas.append(abs(sigma))
    if len(sigmas) < MIN_EDGES:
        raise InputError(
            f"{len(sigmas)} straight edges fitted, the footprint needs {MIN_EDGES}: use frames "
            "of a textured scene, taken still (no motion blur)"
        )
    s = np.asarray(sigmas)
    return Footprint(float(np.quantile(s, share)), float(np.median(s)), len(s))
