"""Reading images as linear light: the simulator's textures and environments, the
reconstruction's relighting environments and the NeRF-Synthetic renders all come through here."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evcap.errors import InputError


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def read_image_linear(path: Path) -> np.ndarray:
    """An image as linear RGB float (HDR files as they are, 8/16-bit ones from sRGB)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_ANYCOLOR | cv2.IMREAD_ANYDEPTH | cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{path}: cannot read the image")
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = img[..., :3][..., ::-1]  # BGR -> RGB
    if img.dtype == np.uint8:
        return srgb_to_linear(img.astype(np.float64) / 255)
    if img.dtype == np.uint16:
        return srgb_to_linear(img.astype(np.float64) / 65535)
    return img.astype(np.float64)
