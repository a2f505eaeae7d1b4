"""`evcap calibrate --report OUT.png`: one image of maps, so a person can see the sensor: the ON
and OFF thresholds, the fit's confidence, the event rate with the hot pixels, and the
reprojection error of each view of the board."""

from __future__ import annotations

import textwrap
from pathlib import Path

import cv2
import numpy as np

from evcap.calib.calibrate import CalibrationRun
from evcap.errors import InputError

SCALE = 2  # sensor pixels are drawn as SCALE x SCALE blocks
TITLE_H, BAR_H, PAD = 28, 34, 12
FONT = cv2.FONT_HERSHEY_SIMPLEX


def _text(img: np.ndarray, text: str, org: tuple[int, int], size: float = 0.5) -> None:
    cv2.putText(img, text, org, FONT, size, (20, 20, 20), 1, cv2.LINE_AA)


def _panel(title: str, body: np.ndarray, bar: tuple[float, float, str] | None) -> np.ndarray:
    """A titled map (BGR uint8), with a color bar (low, high, unit) under it."""
    h, w = body.shape[:2]
    out = np.full((TITLE_H + h + BAR_H, w, 3), 255, np.uint8)
    _text(out, title, (4, 19))
    out[TITLE_H : TITLE_H + h] = body
    if bar is not None:
        lo, hi, unit = bar
        ramp = np.linspace(0, 255, w // 2).astype(np.uint8)[None].repeat(10, 0)
        x0 = w // 4
        out[TITLE_H + h + 4 : TITLE_H + h + 14, x0 : x0 + ramp.shape[1]] = cv2.applyColorMap(
            ramp, cv2.COLORMAP_VIRIDIS
        )
        y = TITLE_H + h + 30
        _text(out, f"{lo:.3g}", (x0 - 50, y - 16), 0.4)
        _text(out, f"{hi:.3g} {unit}", (x0 + ramp.shape[1] + 4, y - 16), 0.4)
    return out


def _colored(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    v = np.nan_to_num((values - lo) / max(hi - lo, 1e-12), nan=0.0)
    u8 = (np.clip(v, 0, 1) * 255).astype(np.uint8)
    img = cv2.applyColorMap(u8, cv2.COLORMAP_VIRIDIS)
    return cv2.resize(img, None, fx=SCALE, fy=SCALE, interpolation=cv2.INTER_NEAREST)


def _threshold_panel(name: str, m: np.ndarray, confident: np.ndarray | None) -> np.ndarray:
    ref = m[confident] if confident is not None and confident.any() else m.ravel()
    lo, hi = np.percentile(ref, [1, 99])
    return _panel(
        f"{name} threshold (mean {ref.mean():.3f}, spread {ref.std():.3f})",
        _colored(m, lo, hi),
        (lo, hi, "log"),
    )


def _rate_panel(cal: CalibrationRun) -> np.ndarray:
    rate = np.log10(np.maximum(cal.noise.rate_hz, 1e-3))
    lo, hi = np.percentile(rate, [1, 99.9])
    body = _colored(rate, lo, hi)
    for y, x in zip(*np.nonzero(cal.noise.hot_pixels), strict=True):
        c = (int(x * SCALE + SCALE // 2), int(y * SCALE + SCALE // 2))
        cv2.circle(body, c, 5 * SCALE, (0, 0, 255), 1, cv2.LINE_AA)
    n = int(cal.noise.hot_pixels.sum())
    return _panel(f"event rate, {n} hot pixels circled", body, (lo, hi, "log10 Hz"))


def _views_panel(cal: CalibrationRun, w: int, h: int) -> np.ndarray:
    """Reprojection RMS of each view used, as bars over time."""
    body = np.full((h, w, 3), 255, np.uint8)
    i = cal.intrinsics
    if i is None or not i.per_view:
        _text(body, f"intrinsics: {cal.intrinsics_source}", (10, h // 2))
        return _panel("reprojection error per view", body, None)
    rms = np.array([v[1] for v in i.per_view])
    top = max(float(rms.max()) * 1.15, 0.05)
    left, bottom = 50, h - 30
    cv2.line(body, (left, 10), (left, bottom), (0, 0, 0), 1)
    cv2.line(body, (left, bottom), (w - 10, bottom), (0, 0, 0), 1)
    width = (w - 20 - left) / len(rms)
    for k, r in enumerate(rms):
        x0 = int(left + k * width + 1)
        y0 = int(bottom - (bottom - 10) * r / top)
        cv2.rectangle(
            body, (x0, y0), (max(x0 + 1, int(x0 + width - 2)), bottom), (180, 120, 40), -1
        )
    y_rms = int(bottom - (bottom - 10) * i.rms_px / top)
    cv2.line(body, (left, y_rms), (w - 10, y_rms), (0, 0, 200), 1)
    _text(body, f"RMS {i.rms_px:.3f} px", (left + 6, max(y_rms - 6, 20)), 0.45)
    _text(body, f"{top:.2f}", (4, 18), 0.4)
    _text(body, "0", (30, bottom + 4), 0.4)
    _text(body, f"{len(rms)} views in time order, {len(i.rejected)} not used", (left, h - 8), 0.45)
    return _panel("reprojection error per view (px)", body, None)


def write_report(cal: CalibrationRun, path: str | Path) -> None:
    """Write the maps of ``cal`` to ``path`` (PNG)."""
    c = cal.threshold_confidence
    confident = None if c is None else c >= 0.5
    w, h = cal.width * SCALE, cal.height * SCALE
    conf = np.zeros((cal.height, cal.width)) if c is None else c
    panels = [
        _threshold_panel("ON", cal.threshold_on, confident),
        _threshold_panel("OFF", cal.threshold_off, confident),
        _panel(
            f"threshold fit confidence ({(conf >= 0.5).mean():.0%} of pixels >= 0.5)",
            _colored(conf, 0.0, 1.0),
            (0.0, 1.0, ""),
        ),
        _rate_panel(cal),
        _views_panel(cal, w, h),
    ]
    blank = np.full_like(panels[0], 255)
    lines = [part for line in cal.summary().split("\n") for part in textwrap.wrap(line, 58)]
    for k, line in enumerate(lines[: (blank.shape[0] - 40) // 18]):
        _text(blank, line, (8, 40 + 18 * k), 0.4)
    panels.append(blank)
    rows = [np.hstack([panels[k], panels[k + 1], panels[k + 2]]) for k in (0, 3)]
    sheet = cv2.copyMakeBorder(
        np.vstack(rows), PAD, PAD, PAD, PAD, cv2.BORDER_CONSTANT, value=(255, 255, 255)
    )
    path = Path(path)
    try:
        ok = cv2.imwrite(str(path), sheet)
    except cv2.error as e:
        raise InputError(f"cannot write the report {path}: {e}") from None
    if not ok:
        raise InputError(f"cannot write the report {path} (is the folder there, is it a .png?)")
