"""The pixel's footprint from an image's straight edges (evcap.calib.footprint)."""

import numpy as np
import pytest

from evcap.calib.footprint import footprint
from evcap.errors import InputError

FINE = 16  # sub-pixel samples a pixel when drawing the truth


def slanted_edges(sigma_px: float, noise: float = 1.0, seed: int = 0) -> np.ndarray:
    """A 96 x 96 image of four squares, each cut by an edge at its own angle, seen through a
    Gaussian footprint of ``sigma_px`` (drawn finely, blurred, read at the pixel centres)."""
    import cv2

    size = 96 * FINE
    yy, xx = (np.mgrid[0:size, 0:size] + 0.5) / FINE
    img = np.full((size, size), 50.0)
    for cx, cy, degrees in ((24, 24, 5), (72, 24, 20), (24, 72, 35), (72, 72, 60)):
        a = np.radians(degrees)
        square = (np.abs(xx - cx) < 16) & (np.abs(yy - cy) < 16)
        img[square & ((xx - cx) * np.cos(a) + (yy - cy) * np.sin(a) > 0)] = 200.0
    img = cv2.GaussianBlur(img, (0, 0), sigma_px * FINE)
    pixels = img[FINE // 2 :: FINE, FINE // 2 :: FINE]
    return pixels + np.random.default_rng(seed).normal(0, noise, pixels.shape)


@pytest.mark.parametrize("sigma", [0.25, 0.5, 0.8])
def test_the_footprint_of_slanted_edges(sigma):
    fit = footprint(slanted_edges(sigma))
    assert fit.edges >= 40
    assert fit.median_px == pytest.approx(sigma, abs=0.03)
    assert sigma - 0.05 < fit.sigma_px <= fit.median_px


def test_an_image_without_edges_is_refused():
    flat = np.random.default_rng(0).normal(100, 1, (64, 64))
    with pytest.raises(InputError, match="straight edges"):
        footprint(flat)
    with pytest.raises(InputError, match="grey image"):
        footprint(np.zeros((64, 64, 3)))
