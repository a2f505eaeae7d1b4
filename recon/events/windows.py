"""The events as the loss reads them: per-pixel ON and OFF counts over windows between frame
times, from a table prepared once.

The frames are a regular grid of times (the rendered frames); a window runs from one frame time
to a later one. Every event gets a key, (pixel * 2 + ON) * F + the frame interval it falls in,
and the table keeps each distinct key once, sorted, with the number of events under smaller
keys. The events of one pixel and polarity before frame f are then that number at the first key
at or after (pixel * 2 + ON) * F + f: one search per pixel, polarity and frame, and a window's
counts are the difference at its two frames. A step costs the same however many events its
windows hold, and the table lives on the training device: no event is touched during
training. Memory: 16 bytes per distinct (pixel, polarity, frame interval) that has events, at
most 16 bytes an event (docs/reconstruction.md gives the paper's scale).

A pixel's events closer together than twice its refractory period (the calibration's) come
from a pixel firing as fast as it can: the change it met during each refractory period is
lost, so the events of a window that holds them measure only part of its change. Those
"crowded" events are counted again in a second table of the same kind (``crowded``).

Timestamps stay int64 microseconds throughout.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
import torch

from evcap.errors import InputError
from evcap.event_filters import (
    CROWDED_PERIODS,
    BackgroundActivityFilter,
    Compose,
    RefractoryMarking,
)
from evcap.recon._threads import follow_torch_threads
from evcap.recon.resume import digest
from evcap.recon.scene.optics import SensorOptics
from evcap.session import Session

MIN_EVENTS = 500  # fewer than this say nothing of a scene: refused before minutes of fitting


@dataclass(frozen=True)
class WindowsConfig:
    """The events' time grid, what is counted, and the windows a training step draws."""

    frame_interval_ms: float = 5.0
    """One rendered frame every this many ms at most: the grid windows start and end on."""
    max_frames: int = 4000
    """The grid is made coarser for recordings longer than this many frames."""
    max_window_frames: int = 150
    """A window spans 1..this many frame intervals (long ones carry the edges' changes across
    flat regions)."""
    views_per_step: int = 3
    """Renders per step; every two of them make a window."""
    noise_filter_ms: float = 0.0
    """A background-activity filter (evcap.event_filters): only the events a neighbour's
    supports within this many ms are counted (0: all); for dim light, where noise is a
    sizeable share of the events."""
    refractory_bound: bool = False
    """A window whose pixel fired crowded events (closer than twice the calibration's
    refractory period) measures only part of its change: they are counted apart, and the loss
    takes its C_on ON - C_off OFF as a lower bound on the change's size, in its direction."""

    def __post_init__(self) -> None:
        if self.frame_interval_ms <= 0 or self.max_frames < 2 or self.max_window_frames < 1:
            raise InputError(
                "windows.frame_interval_ms must be > 0, max_frames >= 2, max_window_frames >= 1"
            )
        if self.views_per_step < 2:
            raise InputError("windows.views_per_step must be at least 2 (a window needs two)")
        if self.noise_filter_ms < 0:
            raise InputError("windows.noise_filter_ms must be 0 (no filter) or a positive time")

    def draw(self, rng: np.random.Generator, frames: int) -> np.ndarray:
        """views_per_step frame indices among ``frames``, increasing, each 1..max_window_frames
        after the last."""
        gaps = rng.integers(1, self.max_window_frames + 1, self.views_per_step - 1)
        span = int(gaps.sum())
        if span >= frames:
            gaps = np.maximum(gaps * (frames - 1) // span, 1)
            span = int(gaps.sum())
        start = int(rng.integers(0, max(frames - span, 1)))
        return np.minimum(start + np.concatenate([[0], np.cumsum(gaps)]), frames - 1)


@dataclass
class EventWindows:
    width: int
    height: int
    frame_times: np.ndarray  # [F] int64 us
    keys: torch.Tensor  # [U] int64, sorted and distinct: (pixel * 2 + ON) * F + interval
    before: torch.Tensor  # [U + 1] int64: the events under a smaller key (the last: all)
    rows: torch.Tensor  # [2 P + 1] int64: each (pixel, polarity)'s first key
    threshold_on: torch.Tensor  # [P]
    threshold_off: torch.Tensor
    crowded: EventWindows | None = None  # the crowded events alone (None: none counted)

    @classmethod
    def from_session(
        cls,
        session: Session,
        optics: SensorOptics,
        t_start: int,
        t_end: int,
        config: WindowsConfig = WindowsConfig(),
        device: torch.device | str = "cpu",
    ) -> EventWindows:
        """Frames every config.frame_interval_ms (or coarser, to stay within max_frames) over
        [t_start, t_end], with the events between them; with config.refractory_bound, the
        crowded events (by the optics' refractory period) counted again in ``crowded``; with a
        config.noise_filter_ms, only the events a neighbour's supports within that time
        (evcap.event_filters)."""
        interval_us, max_frames = round(config.frame_interval_ms * 1000), config.max_frames
        noise_filter_us = config.noise_filter_ms * 1000
        refractory_us = optics.refractory_us if config.refractory_bound else 0.0
        if t_end <= t_start:
            raise InputError(f"{session.path}: no time span with both events and poses")
        span = t_end - t_start
        interval = max(int(interval_us), -(-span // max(max_frames - 1, 1)), 1)
        times = np.arange(t_start, t_end + 1, interval, dtype=np.int64)
        if len(times) < 2:
            raise InputError(
                f"{session.path}: the recording ({span} us with poses) is shorter than one "
                f"frame interval ({interval} us)"
            )
        w, h = session.sensor.width, session.sensor.height
        i0, i1 = session.event_index(int(times[0])), session.event_index(int(times[-1]))
        if i1 - i0 < MIN_EVENTS:
            raise InputError(
                f"{session.path}: {i1 - i0:,} events in the {span / 1e6:.2f} s that have poses; "
                f"a reconstruction needs at least {MIN_EVENTS:,} (record the camera moving "
                "around the scene for a few seconds)"
            )
        parts, crowded_parts = [], []
        filters = [BackgroundActivityFilter(noise_filter_us)] if noise_filter_us > 0 else []
        keep = Compose(*filters).stream()
        crowded = None
        if refractory_us > 0:
            crowded = RefractoryMarking(refractory_us, CROWDED_PERIODS).stream()
        for ev in _blocks(session, i0, i1):
            ev = keep(ev)
            pixels = ev.y.astype(np.int64) * w + ev.x
            keys = (pixels * 2 + (ev.p > 0)) * len(times)
            keys += np.searchsorted(times, ev.t, side="right") - 1
            parts.append(np.unique(keys, return_counts=True))
            if crowded is not None:
                crowded_parts.append(np.unique(keys[crowded(ev)], return_counts=True))

        def table(parts):
            keys, counts = _merge(parts)
            thresholds = optics.threshold_on, optics.threshold_off
            return cls.from_keys(w, h, times, keys, counts, *thresholds, device)

        windows = table(parts)
        if crowded_parts:
            windows.crowded = table(crowded_parts)
        return windows

    @classmethod
    def from_codes(
        cls,
        width: int,
        height: int,
        frame_times: np.ndarray,
        codes: np.ndarray,
        starts: np.ndarray,
        threshold_on: np.ndarray | torch.Tensor,
        threshold_off: np.ndarray | torch.Tensor,
        device: torch.device | str = "cpu",
    ) -> EventWindows:
        """From events in time order given as codes (pixel * 2 + ON) [E] and the index of the
        first event at or after each frame time ``starts`` [F] (the events before the first
        frame time or at and after the last belong to no window)."""
        frame_times = np.asarray(frame_times, np.int64)
        codes, starts = np.asarray(codes, np.int64), np.asarray(starts, np.int64)
        index = np.arange(len(codes))
        slots = np.searchsorted(starts, index, side="right") - 1
        inside = (index >= starts[0]) & (index < starts[-1])
        keys = codes[inside] * len(frame_times) + slots[inside]
        keys, counts = np.unique(keys, return_counts=True)
        return cls.from_keys(
            width, height, frame_times, keys, counts, threshold_on, threshold_off, device
        )

    @classmethod
    def from_keys(
        cls,
        width: int,
        height: int,
        frame_times: np.ndarray,
        keys: np.ndarray,
        counts: np.ndarray,
        threshold_on: np.ndarray | torch.Tensor,
        threshold_off: np.ndarray | torch.Tensor,
        device: torch.device | str = "cpu",
    ) -> EventWindows:
        """From the distinct keys [U] (sorted) and the events under each [U]."""
        frames = len(frame_times)
        before = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)])
        rows = np.searchsorted(keys, np.arange(2 * width * height + 1, dtype=np.int64) * frames)

        def tensor(x, dtype):
            x = x if isinstance(x, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(x))
            return x.reshape(-1).to(device, dtype)

        return cls(
            width,
            height,
            np.asarray(frame_times, np.int64),
            tensor(keys, torch.int64),
            tensor(before, torch.int64),
            tensor(rows, torch.int64),
            tensor(threshold_on, torch.float32),
            tensor(threshold_off, torch.float32),
        )

    def __len__(self) -> int:
        return len(self.frame_times)

    def digest(self) -> str:
        """A digest of the tables (and the crowded events'): what a saved training was fitted
        to, checked when it goes on (the windows are counted again from the session: in
        integers, the same on every machine)."""
        crowded = self.crowded.digest() if self.crowded is not None else None
        arrays = (self.keys, self.before, self.rows, self.threshold_on, self.threshold_off)
        return digest(self.width, self.height, self.frame_times, *arrays, crowded)

    @property
    def events(self) -> int:
        """The events inside the frames."""
        return int(self.before[-1])

    def nbytes(self) -> int:
        """The memory the table takes on its device."""
        own = sum(t.element_size() * t.numel() for t in (self.keys, self.before, self.rows))
        return own + (self.crowded.nbytes() if self.crowded is not None else 0)

    def before_frames(self, frames: Sequence[int]) -> torch.Tensor:
        """[K, 2 P] the events of each pixel and polarity (column pixel * 2 + ON) before each
        of the ``frames`` (indices into frame_times, given on the host): on the CPU each
        pixel searching its own few keys (compiled), elsewhere one sorted search of all."""
        f = np.asarray(frames, np.int64)
        if self.keys.device.type == "cpu":
            return self.before_by_rows(f)
        return self.before_by_search(f)

    def before_by_rows(self, frames: np.ndarray) -> torch.Tensor:
        out = torch.empty(len(frames), len(self.rows) - 1, dtype=torch.int64)
        follow_torch_threads()
        _before_rows(
            self.keys.numpy(),
            self.before.numpy(),
            self.rows.numpy(),
            np.asarray(frames, np.int64),
            len(self.frame_times),
            out.numpy(),
        )
        return out

    def before_by_search(self, frames: np.ndarray) -> torch.Tensor:
        # each frame index added as a number: nothing is copied to the device
        codes = torch.arange(len(self.rows) - 1, device=self.keys.device) * len(self.frame_times)
        queries = torch.stack([codes + int(f) for f in frames])
        found = torch.searchsorted(self.keys, queries.reshape(-1))
        return self.before[found].reshape(len(frames), -1)

    def between(
        self, before_a: torch.Tensor, before_b: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(ON, OFF) counts [P] (float32) between two rows of before_frames."""
        c = (before_b - before_a).reshape(-1, 2).to(torch.float32)
        return c[:, 1], c[:, 0]

    def counts(self, a: int, b: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(ON, OFF) event counts [H * W] of each pixel between frame a and frame b > a."""
        n = self.before_frames([a, b])
        return self.between(n[0], n[1])

    def change(self, on: torch.Tensor, off: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(C_on ON - C_off OFF, ON + OFF) per pixel [H * W] from the counts."""
        return self.threshold_on * on - self.threshold_off * off, on + off

    def log_change(self, a: int, b: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(C_on ON - C_off OFF, ON + OFF) per pixel [H * W] between frames a and b."""
        return self.change(*self.counts(a, b))


@numba.njit(cache=True, parallel=True)
def _before_rows(keys, before, rows, frames, n_frames, out):
    """before_frames on the CPU: each (pixel, polarity) searches its own few keys."""
    for code in numba.prange(len(rows) - 1):
        first, last = rows[code], rows[code + 1]
        for k in range(len(frames)):
            query = code * n_frames + frames[k]
            lo, hi = first, last
            while lo < hi:
                mid = (lo + hi) >> 1
                if keys[mid] < query:
                    lo = mid + 1
                else:
                    hi = mid
            out[k, code] = before[lo]


def _merge(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """One sorted set of distinct keys, with their counts summed, from the blocks'."""
    if len(parts) == 1:
        return parts[0]
    keys = np.concatenate([k for k, _ in parts])
    counts = np.concatenate([c for _, c in parts])
    keys, inverse = np.unique(keys, return_inverse=True)
    return keys, np.bincount(inverse, weights=counts, minlength=len(keys)).astype(np.int64)


def _blocks(session: Session, i0: int, i1: int, block: int = 4_000_000):
    for s in range(i0, i1, block):
        yield session.events_by_index(s, min(s + block, i1))
