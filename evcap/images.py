"""Images as linear light and as displayed: reading them (the simulator's textures and
environments, the reconstruction's relighting environments and the NeRF-Synthetic renders all
come through here), sRGB encoding, and the per-channel color correction that event-based
renders are compared after."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evcap.errors import InputError


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def srgb(linear: np.ndarray) -> np.ndarray:
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def fit_color_correction(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """[C, 2] gain and offset per channel that best map ``pred`` onto ``gt`` (least squares)."""
    p = pred.reshape(-1, pred.shape[-1]).astype(np.float64)
    g = gt.reshape(-1, gt.shape[-1]).astype(np.float64)
    out = np.zeros((p.shape[1], 2))
    for c in range(p.shape[1]):
        A = np.stack([p[:, c], np.ones(len(p))], 1)
        out[c] = np.linalg.lstsq(A, g[:, c], rcond=None)[0]
    return out


def fit_gain(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """[C] gain per channel that best maps ``pred`` onto ``gt`` (least squares, no offset):
    all that events leave undetermined of a radiance."""
    p = pred.reshape(-1, pred.shape[-1]).astype(np.float64)
    g = gt.reshape(-1, gt.shape[-1]).astype(np.float64)
    return (p * g).sum(0) / np.maximum((p * p).sum(0), 1e-30)


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
