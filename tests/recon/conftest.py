import numpy as np
import pytest


@pytest.fixture(scope="session")
def random_events():
    """random_events(seed) -> (width, height, frame times, event times, codes, starts): 4,000
    events of a 9 x 7 sensor over 23 frame times and a little beyond, with a hot spot (many
    events of one pixel within one frame interval); ``starts``: the first event at or after
    each frame time (EventWindows.from_codes)."""

    def make(seed: int, width: int = 9, height: int = 7, frames: int = 23):
        rng = np.random.default_rng(seed)
        times = np.arange(frames, dtype=np.int64) * 1000 + 50_000
        t = np.sort(rng.integers(times[0] - 3000, times[-1] + 3000, 4000))
        codes = rng.integers(0, 2 * width * height, len(t))
        # hot spots: many events of one pixel within one frame interval
        codes[100:400] = 17
        starts = np.searchsorted(t, times, side="left")
        return width, height, times, t, codes, starts

    return make
