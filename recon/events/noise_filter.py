"""A background-activity filter, as a DVS camera's own (jAER's BackgroundActivityFilter; the
DAVIS346's logic has one too): an event is kept when one of its pixel's eight neighbours fired
at most ``within_us`` before it (or at the same time). A moving edge crosses neighbouring
pixels together; a noise event (background activity, shot noise) comes alone. Every event,
kept or not, counts as a neighbour's support, as in the camera's filter."""

from __future__ import annotations

import numba
import numpy as np

NEIGHBOURS = np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dx or dy], np.int64)


def supported(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, last: np.ndarray, within_us: float
) -> np.ndarray:
    """[E] bool: which events (in time order) a neighbour's event at most ``within_us`` before
    supports. ``last`` [height, width] int64, each pixel's last event time (a very negative
    number where none yet), is read and updated: events read in blocks share it."""
    if within_us <= 0:
        raise ValueError(f"the filter's time must be positive, not {within_us}")
    return _supported(
        x.astype(np.int64), y.astype(np.int64), t.astype(np.int64), last, int(within_us)
    )


@numba.njit(cache=True)
def _supported(x, y, t, last, within):
    h, w = last.shape
    out = np.zeros(len(t), np.bool_)
    for k in range(len(t)):
        for n in range(len(NEIGHBOURS)):
            u, v = x[k] + NEIGHBOURS[n, 0], y[k] + NEIGHBOURS[n, 1]
            if 0 <= u < w and 0 <= v < h and t[k] - last[v, u] <= within:
                out[k] = True
                break
        last[y[k], x[k]] = t[k]
    return out
