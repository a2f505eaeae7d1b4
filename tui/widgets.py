"""The monitor's widgets: pixel images drawn with half blocks, the rate chart, text panels."""

from __future__ import annotations

import numpy as np
from rich.color import Color
from rich.segment import Segment
from rich.style import Style
from textual.app import ComposeResult
from textual.containers import Horizontal, Vertical
from textual.strip import Strip
from textual.widget import Widget
from textual.widgets import Label, Sparkline, Static

from evcap.tui.live import LiveSnapshot


def fit(image: np.ndarray, width: int, height: int, pool: str) -> np.ndarray:
    """``image`` shrunk to the largest size that fits width x height pixels with its aspect:
    each output pixel is the maximum of its block (sparse events stay visible) or the mean
    (frames). An image smaller than the space is shown as it is."""
    h, w = image.shape[:2]
    scale = min(1.0, max(width, 1) / w, max(height, 1) / h)
    out_w, out_h = max(1, int(w * scale)), max(1, int(h * scale))
    rows = np.linspace(0, h, out_h + 1).astype(int)[:-1]
    cols = np.linspace(0, w, out_w + 1).astype(int)[:-1]
    if pool == "max":
        out = np.maximum.reduceat(np.maximum.reduceat(image, rows, axis=0), cols, axis=1)
    else:
        sums = np.add.reduceat(
            np.add.reduceat(image.astype(np.float32), rows, axis=0), cols, axis=1
        )
        counts = np.outer(np.diff(np.append(rows, h)), np.diff(np.append(cols, w)))
        out = sums / counts[..., None]
    return out.astype(np.uint8)


class PixelView(Widget):
    """An RGB image that fills the widget with its aspect, two pixels per character cell
    (the upper half block: foreground on top, background below). Drawn line by line, with
    runs of equal cells merged, so a mostly dark event image costs little to draw."""

    DEFAULT_CSS = "PixelView { height: 1fr; }"

    def __init__(self, pool: str = "max", **kwargs) -> None:
        super().__init__(**kwargs)
        self.pool = pool
        self.image: np.ndarray | None = None
        self.updates = 0  # how many images it was given (the refresh rate is measured on it)
        self._cells: np.ndarray | None = None  # [rows, cols] int64: top RGB << 24 | bottom RGB
        self._styles: dict[int, Style] = {}

    def show(self, image: np.ndarray | None) -> None:
        self.image = image
        self.updates += 1
        self._cells = None
        self.refresh()

    def on_resize(self) -> None:
        self._cells = None

    def _fitted_cells(self) -> np.ndarray:
        if self._cells is None:
            rgb = fit(self.image, self.size.width, 2 * self.size.height, self.pool)
            if rgb.shape[0] % 2:
                rgb = np.concatenate([rgb, np.zeros_like(rgb[:1])])
            packed = (
                rgb[..., 0].astype(np.int64) << 16 | rgb[..., 1].astype(np.int64) << 8 | rgb[..., 2]
            )
            self._cells = packed[0::2] << 24 | packed[1::2]
        return self._cells

    def _style(self, key: int) -> Style:
        style = self._styles.get(key)
        if style is None:
            if len(self._styles) > 8192:
                self._styles.clear()
            top, bottom = key >> 24, key & 0xFFFFFF
            style = self._styles[key] = Style(
                color=Color.from_rgb(top >> 16, top >> 8 & 255, top & 255),
                bgcolor=Color.from_rgb(bottom >> 16, bottom >> 8 & 255, bottom & 255),
            )
        return style

    def render_line(self, y: int) -> Strip:
        width = self.size.width
        if self.image is None:
            text = "waiting for data..." if y == 0 else ""
            return Strip([Segment(text.ljust(width)[:width])], width)
        cells = self._fitted_cells()
        if y >= cells.shape[0]:
            return Strip([Segment(" " * width, self._style(0))], width)
        row = cells[y]
        starts = np.flatnonzero(np.diff(row, prepend=-1))
        ends = np.append(starts[1:], row.size)
        segments = [
            Segment("▀" * int(e - s), self._style(int(row[s])))
            for s, e in zip(starts, ends, strict=True)
        ]
        margin = max(0, width - row.size)  # the image is centred on black
        if margin:
            black = self._style(0)
            segments = [
                Segment(" " * (margin // 2), black),
                *segments,
                Segment(" " * (margin - margin // 2), black),
            ]
        return Strip(segments, width)


def si(value: float, unit: str) -> str:
    for factor, prefix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(value) >= factor:
            return f"{value / factor:.2f} {prefix}{unit}"
    return f"{value:.0f} {unit}"


class RateChart(Vertical):
    """Event rates over time: ON and OFF, and per color channel on a color camera; one line
    each, the rate now beside the chart of the last seconds."""

    DEFAULT_CSS = """
    RateChart { height: auto; border: round $primary 40%; }
    RateChart Horizontal { height: 1; }
    RateChart Label { width: 26; }
    RateChart Sparkline { width: 1fr; height: 1; }
    """

    def __init__(self, color: bool, **kwargs) -> None:
        super().__init__(**kwargs)
        self.series = ["on", "off", *(("red", "green", "blue") if color else ())]
        self.totals: dict[str, float] = {}  # events per series in the chart's bins

    def compose(self) -> ComposeResult:
        colors = {"on": "green", "off": "red", "red": "red", "green": "green", "blue": "blue"}
        self.border_title = "event rate (per 100 ms, last 12 s)"
        for name in self.series:
            with Horizontal():
                yield Label(f"{name:>5}", id=f"rate-label-{name}")
                yield Sparkline([0], id=f"rate-{name}", min_color="#303030", max_color=colors[name])

    def update_rates(self, snapshot: LiveSnapshot) -> None:
        seconds = snapshot.bin_us / 1e6
        for name in self.series:
            data = snapshot.rates[name]
            self.totals[name] = float(data.sum() * seconds)
            now = float(data[-2]) if data.size >= 2 else float(data.sum())
            peak = float(data.max()) if data.size else 0.0
            self.query_one(f"#rate-{name}", Sparkline).data = data.tolist()
            self.query_one(f"#rate-label-{name}", Label).update(
                f"{name:>5} {si(now, 'ev/s'):>12} ▲{si(peak, '').replace(' ', '')}"
            )


class Panel(Static):
    """A titled text panel of a fixed size."""

    DEFAULT_CSS = "Panel { border: round $primary 40%; padding: 0 1; height: 100%; }"

    def __init__(self, title: str, **kwargs) -> None:
        super().__init__("", **kwargs)
        self.border_title = title
        self.text = ""

    def show(self, text: str) -> None:
        """Show ``text``; nothing to do if it is what is shown."""
        if text != self.text:
            self.text = text
            self.update(text)
