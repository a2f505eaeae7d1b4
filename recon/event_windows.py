"""The events as the loss reads them: per-pixel signed sums over windows between frame times.

The frames are a regular grid of times (the rendered frames); a window runs from one frame time
to a later one. The events are kept in memory as one int32 per event (pixel * 2 + polarity) in
time order, with the index of the first event at or after each frame time, so that any
window's per-pixel counts are one bincount over its events, however many there are.
Timestamps stay int64 microseconds throughout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from evcap.errors import InputError
from evcap.recon.optics import SensorOptics
from evcap.session import Session

MIN_EVENTS = 500  # fewer than this say nothing of a scene: refused before minutes of fitting


@dataclass
class EventWindows:
    width: int
    height: int
    frame_times: np.ndarray  # [F] int64 us
    codes: np.ndarray  # [E] int32: pixel * 2 + (1 if ON)
    starts: np.ndarray  # [F] int64: index of the first event at or after each frame time
    threshold_on: torch.Tensor  # [H * W]
    threshold_off: torch.Tensor

    @classmethod
    def from_session(
        cls,
        session: Session,
        optics: SensorOptics,
        t_start: int,
        t_end: int,
        interval_us: int,
        max_frames: int,
    ) -> EventWindows:
        """Frames every ``interval_us`` (or coarser, to stay within ``max_frames``) over
        [t_start, t_end], with the events between them."""
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
        w = session.sensor.width
        i0, i1 = session.event_index(int(times[0])), session.event_index(int(times[-1]))
        if i1 - i0 < MIN_EVENTS:
            raise InputError(
                f"{session.path}: {i1 - i0:,} events in the {span / 1e6:.2f} s that have poses; "
                f"a reconstruction needs at least {MIN_EVENTS:,} (record the camera moving "
                "around the scene for a few seconds)"
            )
        codes = np.empty(i1 - i0, np.int32)
        starts = np.zeros(len(times), np.int64)
        done = 0
        for ev in _blocks(session, i0, i1):
            n = len(ev)
            codes[done : done + n] = (ev.y.astype(np.int32) * w + ev.x) * 2 + (ev.p > 0)
            starts += np.searchsorted(ev.t, times, side="left")
            done += n
        return cls(
            w,
            session.sensor.height,
            times,
            codes,
            starts,
            torch.from_numpy(optics.threshold_on.ravel().copy()),
            torch.from_numpy(optics.threshold_off.ravel().copy()),
        )

    def __len__(self) -> int:
        return len(self.frame_times)

    def counts(self, a: int, b: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(ON, OFF) event counts [H * W] of each pixel between frame a and frame b > a."""
        codes = self.codes[self.starts[a] : self.starts[b]]
        n = self.width * self.height
        c = np.bincount(codes, minlength=2 * n).reshape(n, 2)
        return torch.from_numpy(c[:, 1].astype(np.float32)), torch.from_numpy(
            c[:, 0].astype(np.float32)
        )

    def log_change(self, a: int, b: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(C_on ON - C_off OFF, ON + OFF) per pixel [H * W] between frames a and b."""
        on, off = self.counts(a, b)
        return self.threshold_on * on - self.threshold_off * off, on + off


def _blocks(session: Session, i0: int, i1: int, block: int = 4_000_000):
    for s in range(i0, i1, block):
        yield session.events_by_index(s, min(s + block, i1))
