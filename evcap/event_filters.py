"""Event filters: small transforms of the event container (evcap.events), composed as tonic's.

Each filter is a frozen dataclass called on an ``Events``; it returns the events it keeps
(``RefractoryMarking``: a bool mask over them instead). Called so, it sees one whole stream.
``stream()`` gives a callable that carries what a filter remembers (each pixel's last event
time) from one block to the next of one stream read in blocks, so that the blocks come out
exactly as the stream whole.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import numba
import numpy as np

from evcap.errors import InputError
from evcap.events import Events

_NONE_YET = np.iinfo(np.int64).min // 2  # a pixel's last event time before its first: far off
# an event this many refractory periods or less after its pixel's previous one is crowded
CROWDED_PERIODS = 2.0
_NEIGHBOURS = np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dx or dy], np.int64)

_Out = TypeVar("_Out")


class Transform(Generic[_Out]):
    """Something done to the events; ``stream()`` does it block by block to one stream."""

    def __call__(self, events: Events) -> _Out:
        """On a whole stream: nothing came before ``events``."""
        return self.stream()(events)

    def stream(self) -> Callable[[Events], _Out]:
        """A callable for the consecutive blocks of one stream, in time order."""
        raise NotImplementedError


class EventFilter(Transform[Events]):
    """A transform that returns the events it keeps, in their order."""


class _PixelTimes:
    """Each pixel's last event time in one stream, carried across its blocks; refuses a block
    of another sensor size, or one that starts before the last block ended."""

    def __init__(self) -> None:
        self.last: np.ndarray | None = None  # [height, width] int64 us
        self.end = _NONE_YET

    def of(self, events: Events) -> np.ndarray:
        shape = (events.height, events.width)
        if self.last is None:
            self.last = np.full(shape, _NONE_YET, np.int64)
        elif self.last.shape != shape:
            raise InputError(
                f"events: a block of a {events.width} x {events.height} sensor in a stream of "
                f"{self.last.shape[1]} x {self.last.shape[0]}"
            )
        if len(events):
            if events.t[0] < self.end:
                raise InputError(
                    f"events: a block starts at t={int(events.t[0])}, before the previous "
                    f"one's last event (t={self.end})"
                )
            self.end = int(events.t[-1])
        return self.last


def _positive(name: str, value: float) -> None:
    if not (math.isfinite(value) and value > 0):
        raise InputError(f"{name} must be a positive number, not {value!r}")


@dataclass(frozen=True)
class BackgroundActivityFilter(EventFilter):
    """A DVS camera's background-activity filter (jAER's; the DAVIS346's logic has one too):
    an event is kept when one of its pixel's eight neighbours fired at most ``within_us``
    before it (or at the same time). A moving edge crosses neighbouring pixels together; a
    noise event (background activity, shot noise) comes alone. Every event, kept or not,
    counts as a neighbour's support, as in the camera."""

    within_us: float  # how long a neighbour's event supports the next (microseconds, > 0)

    def __post_init__(self) -> None:
        _positive("within_us", self.within_us)

    def stream(self) -> Callable[[Events], Events]:
        times, within = _PixelTimes(), int(self.within_us)

        def keep(events: Events) -> Events:
            x, y = events.x.astype(np.int64), events.y.astype(np.int64)
            return events.select(_supported(x, y, events.t, times.of(events), within))

        return keep


@dataclass(frozen=True)
class RefractoryMarking(Transform[np.ndarray]):
    """Marks (a bool mask) the events that come at most ``periods`` x ``period_us`` after
    their pixel's previous event, of either polarity: a pixel firing as fast as its refractory
    period lets it ("crowded" events)."""

    period_us: float  # the pixels' refractory period (microseconds, > 0)
    periods: float = CROWDED_PERIODS  # how many of them after the previous event is crowded

    def __post_init__(self) -> None:
        _positive("period_us", self.period_us)
        _positive("periods", self.periods)

    def stream(self) -> Callable[[Events], np.ndarray]:
        times, within = _PixelTimes(), self.periods * float(self.period_us)
        return lambda events: _crowded(events.x, events.y, events.t, times.of(events), within)


@dataclass(frozen=True, eq=False)
class HotPixelMask(EventFilter):
    """Drops the events of the pixels ``mask`` marks (such as the calibration's hot pixels)."""

    mask: np.ndarray  # [height, width] bool, True: drop the pixel's events

    def __post_init__(self) -> None:
        mask = np.asarray(self.mask)
        if mask.ndim != 2 or mask.dtype != bool:
            raise InputError(
                f"mask must be a [height, width] bool array, not {mask.dtype} {mask.shape}"
            )
        mask = mask.copy()
        mask.flags.writeable = False
        object.__setattr__(self, "mask", mask)

    def __call__(self, events: Events) -> Events:
        if self.mask.shape != (events.height, events.width):
            raise InputError(
                f"a {self.mask.shape[1]} x {self.mask.shape[0]} pixel mask for events of a "
                f"{events.width} x {events.height} sensor"
            )
        return events.select(~self.mask[events.y, events.x])

    def stream(self) -> Callable[[Events], Events]:
        return self


@dataclass(frozen=True, init=False)
class Compose(EventFilter):
    """Several filters, each applied to the events the one before kept."""

    filters: tuple[EventFilter, ...]

    def __init__(self, *filters: EventFilter) -> None:
        for f in filters:
            if not isinstance(f, EventFilter):
                raise TypeError(f"Compose takes event filters, not {f!r}")
        object.__setattr__(self, "filters", filters)

    def stream(self) -> Callable[[Events], Events]:
        streams = [f.stream() for f in self.filters]

        def apply(events: Events) -> Events:
            for s in streams:
                events = s(events)
            return events

        return apply


@numba.njit(cache=True)
def _supported(x, y, t, last, within):
    h, w = last.shape
    out = np.zeros(len(t), np.bool_)
    for k in range(len(t)):
        for n in range(len(_NEIGHBOURS)):
            u, v = x[k] + _NEIGHBOURS[n, 0], y[k] + _NEIGHBOURS[n, 1]
            if 0 <= u < w and 0 <= v < h and t[k] - last[v, u] <= within:
                out[k] = True
                break
        last[y[k], x[k]] = t[k]
    return out


@numba.njit(cache=True)
def _crowded(x, y, t, last, within):
    out = np.empty(len(t), np.bool_)
    for k in range(len(t)):
        out[k] = t[k] - last[y[k], x[k]] <= within
        last[y[k], x[k]] = t[k]
    return out
