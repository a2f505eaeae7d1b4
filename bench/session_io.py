"""Session file throughput: writing events (the recorder's path) and reading them back.

.venv/bin/python bench/session_io.py [--events N]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import report

from evcap.events import Events
from evcap.session import SensorInfo, Session, SessionWriter


def dense_stream(n: int, rate_hz: float, seed: int = 0) -> Events:
    """A realistic dense stream: moving edges (spatially clustered rows), Poisson timing."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.exponential(1e6 / rate_hz, n)).astype(np.int64)
    y = (130 + 100 * np.sin(t / 2e5) + rng.normal(0, 3, n)).clip(0, 259).astype(np.uint16)
    x = rng.integers(0, 346, n).astype(np.uint16)
    p = (rng.random(n) < 0.52).astype(np.uint8)
    return Events(x, y, t, p, 346, 260, "RGBG")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--events", type=int, default=20_000_000)
    parser.add_argument("--batch", type=int, default=100_000, help="events per append")
    args = parser.parse_args(argv)
    ev = dense_stream(args.events, rate_hz=12e6)
    batches = [ev._take(slice(i, i + args.batch)) for i in range(0, len(ev), args.batch)]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.h5"
        start = time.perf_counter()
        with SessionWriter(path, SensorInfo("simulated", 346, 260, "RGBG")) as w:
            for b in batches:
                w.append_events(b)
        write_s = time.perf_counter() - start
        size = path.stat().st_size
        start = time.perf_counter()
        with Session.open(path) as s:
            open_s = time.perf_counter() - start
            start = time.perf_counter()
            n = sum(len(b) for b in s.iter_events())
            read_s = time.perf_counter() - start
            start = time.perf_counter()
            reps = 200
            mid = int(ev.t[len(ev) // 2])
            for k in range(reps):
                s.events(mid + 997 * k, mid + 997 * k + 10_000)
            slice_ms = (time.perf_counter() - start) / reps * 1e3
    report(
        "session_io",
        {
            "events": n,
            "write_Mev_per_s": len(ev) / write_s / 1e6,
            "bytes_per_event": size / len(ev),
            "open_and_validate_Mev_per_s": n / open_s / 1e6,
            "read_Mev_per_s": n / read_s / 1e6,
            "slice_10ms_read_ms": slice_ms,
        },
    )


if __name__ == "__main__":
    main()
