"""Plots as inline SVG (no plotting library): line plots with axes, ticks and a legend, and the
camera path seen from above and from the side.

Non-finite points are left out; a line breaks where they were."""

from __future__ import annotations

import math
from dataclasses import dataclass
from html import escape

import numpy as np

COLORS = ("#1f5fa8", "#d1495b", "#2a9d8f", "#e9a23b", "#6d597a", "#555555")
FONT = 'font-family="sans-serif" font-size="12"'


def _box(width: int, height: int) -> tuple[float, float, float, float]:
    """The plot box (left, top, width, height) in an SVG of this size: room for the title
    above, tick labels left and below, the axis label and the legend under them."""
    return 70.0, 28.0, width - 90.0, height - 96.0


MAX_MARKERS = 40  # a series with at most this many points shows each as a dot


@dataclass
class Series:
    """One line of a plot."""

    label: str
    x: np.ndarray
    y: np.ndarray
    color: str = COLORS[0]
    dashed: bool = False


@dataclass
class Track:
    """One camera path: centres [N, 3] in world units and, optionally, viewing directions
    [N, 3] (the cameras' z axes), a few of which are drawn as short strokes."""

    label: str
    centres: np.ndarray
    color: str = COLORS[0]
    forward: np.ndarray | None = None
    dashed: bool = False  # drawn dashed, so that a path under it still shows


def nice_ticks(lo: float, hi: float, count: int = 5) -> list[float]:
    """About ``count`` round values (1, 2 or 5 times a power of ten apart) covering lo..hi."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return []
    if hi <= lo:
        hi = lo + 1.0 if lo == 0 else lo + abs(lo) * 0.1
    raw = (hi - lo) / max(count, 1)
    power = 10 ** math.floor(math.log10(raw))
    step = next(m * power for m in (1, 2, 5, 10) if m * power >= raw)
    first = math.floor(lo / step + 1e-9) * step
    n = math.ceil((hi - first) / step - 1e-9)
    return [first + k * step for k in range(n + 1)]


def _label(v: float, step: float) -> str:
    """A tick value with the decimals its step needs."""
    if abs(v) < step * 1e-6:
        return "0"
    if abs(v) >= 1e5 or abs(v) < 1e-3:
        return f"{v:.2g}"
    decimals = max(0, -math.floor(math.log10(step) + 1e-9)) if step > 0 else 0
    return f"{v:.{decimals}f}"


class _Frame:
    """A plot box: data (x0..x1, y0..y1) mapped onto pixels (y up), with its axes drawn."""

    def __init__(self, box: tuple[float, float, float, float], xr, yr) -> None:
        self.left, self.top, self.width, self.height = box
        self.x0, self.x1 = xr
        self.y0, self.y1 = yr

    def px(self, x: np.ndarray) -> np.ndarray:
        return self.left + (x - self.x0) / (self.x1 - self.x0) * self.width

    def py(self, y: np.ndarray) -> np.ndarray:
        return self.top + self.height - (y - self.y0) / (self.y1 - self.y0) * self.height

    def axes(self, xticks, yticks, x_label: str, y_label: str, y_format=None) -> list[str]:
        """The box, grid lines, tick labels and axis labels."""
        left, top, w, h = self.left, self.top, self.width, self.height
        out = [
            f'<rect x="{left:.1f}" y="{top:.1f}" width="{w:.1f}" height="{h:.1f}" '
            'fill="white" stroke="#444"/>'
        ]
        xstep = xticks[1] - xticks[0] if len(xticks) > 1 else 1.0
        for v in xticks:
            if self.x0 - 1e-9 <= v <= self.x1 + 1e-9:
                x = float(self.px(np.float64(v)))
                out.append(
                    f'<line x1="{x:.1f}" y1="{top:.1f}" x2="{x:.1f}" y2="{top + h:.1f}" '
                    'stroke="#e4e4e4"/>'
                )
                out.append(
                    f'<text x="{x:.1f}" y="{top + h + 15:.1f}" text-anchor="middle" {FONT}>'
                    f"{escape(_label(v, xstep))}</text>"
                )
        ystep = yticks[1] - yticks[0] if len(yticks) > 1 else 1.0
        for v in yticks:
            if self.y0 - 1e-9 <= v <= self.y1 + 1e-9:
                y = float(self.py(np.float64(v)))
                text = y_format(v) if y_format else _label(v, ystep)
                out.append(
                    f'<line x1="{left:.1f}" y1="{y:.1f}" x2="{left + w:.1f}" y2="{y:.1f}" '
                    'stroke="#e4e4e4"/>'
                )
                out.append(
                    f'<text x="{left - 5:.1f}" y="{y + 4:.1f}" text-anchor="end" {FONT}>'
                    f"{escape(text)}</text>"
                )
        out.append(
            f'<rect x="{left:.1f}" y="{top:.1f}" width="{w:.1f}" height="{h:.1f}" '
            'fill="none" stroke="#444"/>'
        )
        out.append(
            f'<text x="{left + w / 2:.1f}" y="{top + h + 34:.1f}" text-anchor="middle" '
            f"{FONT}>{escape(x_label)}</text>"
        )
        cy = top + h / 2
        out.append(
            f'<text x="14" y="{cy:.1f}" text-anchor="middle" transform="rotate(-90 14 {cy:.1f})" '
            f"{FONT}>{escape(y_label)}</text>"
        )
        return out


def _polylines(xs: np.ndarray, ys: np.ndarray, style: str) -> list[str]:
    """Polylines through the points [N] (pixels), broken where a point is not finite."""
    ok = np.isfinite(xs) & np.isfinite(ys)
    out, run = [], []
    for x, y, good in zip(xs, ys, ok, strict=True):
        if good:
            run.append(f"{x:.1f},{y:.1f}")
        elif run:
            out.append(run)
            run = []
    if run:
        out.append(run)
    return [f'<polyline points="{" ".join(r)}" fill="none" {style}/>' for r in out if len(r) > 1]


def _svg(width: int, height: int, title: str, body: list[str]) -> str:
    return (
        f'<svg width="{width}" height="{height}" '
        f'viewBox="0 0 {width} {height}" role="img" aria-label="{escape(title)}">'
        f'<text x="{width / 2:.1f}" y="16" text-anchor="middle" font-family="sans-serif" '
        f'font-size="13" font-weight="bold">{escape(title)}</text>' + "".join(body) + "</svg>"
    )


def line_plot(
    series: list[Series],
    *,
    title: str,
    x_label: str,
    y_label: str,
    log_y: bool = False,
    width: int = 560,
    height: int = 340,
) -> str:
    """An SVG line plot of ``series`` (their non-finite points, and on ``log_y`` their
    non-positive ones, left out); a note in place of the plot when no point is left."""
    cleaned = []
    for s in series:
        x, y = np.asarray(s.x, np.float64), np.asarray(s.y, np.float64)
        if log_y:
            y = np.where(y > 0, np.log10(np.where(y > 0, y, 1.0)), np.nan)
        cleaned.append((s, x, y))
    ok = [(x, y) for _, x, y in cleaned]
    xs = np.concatenate([x[np.isfinite(x) & np.isfinite(y)] for x, y in ok] or [np.zeros(0)])
    ys = np.concatenate([y[np.isfinite(x) & np.isfinite(y)] for x, y in ok] or [np.zeros(0)])
    if xs.size == 0:
        body = [
            f'<text x="{width / 2}" y="{height / 2}" text-anchor="middle" {FONT}>'
            "no finite values to plot</text>"
        ]
        return _svg(width, height, title, body)
    xt = nice_ticks(float(xs.min()), float(xs.max()))
    if log_y:
        lo, hi = math.floor(float(ys.min())), math.ceil(float(ys.max()))
        yt = [float(k) for k in range(lo, max(hi, lo + 1) + 1)]
        if len(yt) <= 3:  # under two decades: 2 and 5 between the powers of ten too
            yt = sorted({v + math.log10(m) for v in yt[:-1] for m in (1, 2, 5)} | {yt[-1]})
        lo_y, hi_y = float(ys.min()), float(ys.max())
        pad = max(hi_y - lo_y, 0.05) * 0.05
        yr = (lo_y - pad, hi_y + pad)
        y_format = _power_label
    else:
        yt = nice_ticks(float(ys.min()), float(ys.max()))
        yr = (yt[0], yt[-1])
        y_format = None
    frame = _Frame(_box(width, height), (xt[0], xt[-1]), yr)
    body = frame.axes(xt, yt, x_label, y_label, y_format)
    for s, x, y in cleaned:
        px, py = frame.px(x), frame.py(y)
        dash = ' stroke-dasharray="6 4"' if s.dashed else ""
        body += _polylines(px, py, f'stroke="{s.color}" stroke-width="2"{dash}')
        good = np.isfinite(px) & np.isfinite(py)
        if good.sum() <= MAX_MARKERS:
            body += [
                f'<circle cx="{a:.1f}" cy="{b:.1f}" r="3" fill="{s.color}"/>'
                for a, b in zip(px[good], py[good], strict=True)
            ]
    body += _legend([(s.label, s.color, s.dashed) for s in series], frame, height - 8)
    return _svg(width, height, title, body)


def _power_label(v: float) -> str:
    value = 10**v
    return f"{value:.0e}" if abs(v - round(v)) < 1e-9 and abs(v) > 3 else f"{value:.3g}"


def _legend(items: list[tuple[str, str, bool]], frame: _Frame, y: float) -> list[str]:
    """The labels in a row under the plot box, at height ``y``."""
    out, x = [], frame.left
    for label, color, dashed in items:
        dash = ' stroke-dasharray="6 4"' if dashed else ""
        out.append(
            f'<line x1="{x:.1f}" y1="{y - 4:.1f}" x2="{x + 20:.1f}" y2="{y - 4:.1f}" '
            f'stroke="{color}" stroke-width="2"{dash}/>'
        )
        out.append(f'<text x="{x + 25:.1f}" y="{y:.1f}" {FONT}>{escape(label)}</text>')
        x += 25 + len(label) * 6.5 + 16
    return out


def trajectory_views(
    tracks: list[Track], *, units: str = "scene units", width: int = 460, height: int = 400
) -> str:
    """Two SVG panels side by side: the camera centres from above (world x, y) and from the
    side (world x, z), at one scale on both axes of both panels; a dot at each path's
    start."""
    points = [np.asarray(t.centres, np.float64).reshape(-1, 3) for t in tracks]
    p = np.concatenate(points) if points else np.zeros((0, 3))
    p = p[np.isfinite(p).all(1)]
    span = float((p.max(0) - p.min(0)).max()) * 1.1 if len(p) else 0.0
    span = max(span, 1e-9)
    panels = [
        _track_panel(tracks, (0, 1), "top view", ("x", "y"), units, span, width, height),
        _track_panel(tracks, (0, 2), "side view", ("x", "z"), units, span, width, height),
    ]
    return '<div class="plots">' + "".join(panels) + "</div>"


def _track_panel(
    tracks: list[Track],
    axes: tuple[int, int],
    title: str,
    names: tuple[str, str],
    units: str,
    span: float,
    width: int,
    height: int,
) -> str:
    a, b = axes
    points = [t.centres[:, [a, b]] for t in tracks if len(t.centres)]
    p = np.concatenate(points) if points else np.zeros((0, 2))
    p = p[np.isfinite(p).all(1)]
    if len(p) == 0:
        body = [
            f'<text x="{width / 2}" y="{height / 2}" text-anchor="middle" {FONT}>no poses</text>'
        ]
        return _svg(width, height, title, body)
    box = _box(width, height)
    lo, hi = p.min(0), p.max(0)
    # equal scale: the data fill the box along the axis that needs it most
    per_px = max(span / box[2], span / box[3])
    mid = (lo + hi) / 2
    xr = (mid[0] - per_px * box[2] / 2, mid[0] + per_px * box[2] / 2)
    yr = (mid[1] - per_px * box[3] / 2, mid[1] + per_px * box[3] / 2)
    frame = _Frame(box, xr, yr)
    # one tick spacing on both axes, so that the grid is square
    wide = xr if xr[1] - xr[0] >= yr[1] - yr[0] else yr
    step = np.diff(nice_ticks(*wide, 6)[:2])[0]
    xt, yt = (np.arange(np.ceil(r[0] / step), np.floor(r[1] / step) + 1) * step for r in (xr, yr))
    body = frame.axes(list(xt), list(yt), f"{names[0]} ({units})", f"{names[1]} ({units})")
    stroke = span * 0.06
    for t in tracks:
        c = np.asarray(t.centres, np.float64)
        if len(c) == 0:
            continue
        dash = ' stroke-dasharray="6 4"' if t.dashed else ""
        body += _polylines(
            frame.px(c[:, a]), frame.py(c[:, b]), f'stroke="{t.color}" stroke-width="2"{dash}'
        )
        if t.forward is not None:
            for i in np.linspace(0, len(c) - 1, min(len(c), 12)).round().astype(int):
                end = c[i] + np.asarray(t.forward[i], np.float64) * stroke
                if not (np.isfinite(c[i]).all() and np.isfinite(end).all()):
                    continue
                body.append(
                    f'<line x1="{frame.px(c[i, a]):.1f}" y1="{frame.py(c[i, b]):.1f}" '
                    f'x2="{frame.px(end[a]):.1f}" y2="{frame.py(end[b]):.1f}" '
                    f'stroke="{t.color}" stroke-width="1" opacity="0.7"/>'
                )
        if np.isfinite(c[0]).all():
            body.append(
                f'<circle cx="{frame.px(c[0, a]):.1f}" cy="{frame.py(c[0, b]):.1f}" r="4" '
                f'fill="{t.color}"/>'
            )
    body += _legend([(t.label, t.color, t.dashed) for t in tracks], frame, height - 8)
    return _svg(width, height, title, body)
