"""The monitor's widgets: pixel images drawn with half blocks, the rate chart, text panels."""

from __future__ import annotations

import numpy as np
from rich.color import Color
from rich.console import Console, ConsoleOptions, RenderResult
from rich.segment import Segment
from rich.style import Style
from textual.app import ComposeResult
from textual.containers import Horizontal, Vertical
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


class HalfBlocks:
    """A rich renderable: an RGB image, two pixels per character cell (upper half block)."""

    def __init__(self, rgb: np.ndarray) -> None:
        self.rgb = rgb

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        styles: dict[tuple, Style] = {}
        rgb = self.rgb
        if rgb.shape[0] % 2:
            rgb = np.concatenate([rgb, np.zeros_like(rgb[:1])])
        for top, bottom in zip(rgb[0::2].tolist(), rgb[1::2].tolist(), strict=True):
            for a, b in zip(top, bottom, strict=True):
                key = (*a, *b)
                style = styles.get(key)
                if style is None:
                    style = styles[key] = Style(
                        color=Color.from_rgb(*a), bgcolor=Color.from_rgb(*b)
                    )
                yield Segment("▀", style)
            yield Segment.line()


class PixelView(Widget):
    """An image that fills the widget, drawn with half blocks."""

    DEFAULT_CSS = "PixelView { height: 1fr; }"

    def __init__(self, pool: str = "max", **kwargs) -> None:
        super().__init__(**kwargs)
        self.pool = pool
        self.image: np.ndarray | None = None
        self.updates = 0  # how many images it was given (the refresh rate is measured on it)

    def show(self, image: np.ndarray | None) -> None:
        self.image = image
        self.updates += 1
        self.refresh()

    def render(self) -> HalfBlocks | str:
        if self.image is None:
            return "waiting for data..."
        return HalfBlocks(fit(self.image, self.size.width, 2 * self.size.height, self.pool))


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
                f"{name:>5} {si(now, 'ev/s'):>12} ▲{si(peak, '')}"
            )


class Panel(Static):
    """A titled text panel."""

    DEFAULT_CSS = "Panel { border: round $primary 40%; padding: 0 1; height: 100%; }"

    def __init__(self, title: str, **kwargs) -> None:
        super().__init__("", **kwargs)
        self.border_title = title
