"""Stream decoder throughput on one core, as the recorder hands the stream over (1 MiB pieces):
a dense realistic stream (12 Mev/s of events, frames at 25 fps, IMU at 1 kHz), and the same
events alone (the event hot path: timestamp, row and column words only). The time is the
decoding thread's CPU time, so that other work on the machine does not count against it.

    .venv/bin/python bench/decode_throughput.py [--seconds S] [--piece BYTES] [--rounds N]
"""

from __future__ import annotations

import argparse
import time

from _common import report
from _streams import dense_events, dense_stream

from evcap.acquire.decoder import Geometry, StreamDecoder
from evcap.acquire.encoder import StreamEncoder


def best_time(data: bytes, n_events: int, piece: int, rounds: int = 3) -> tuple[float, dict]:
    """The fastest of ``rounds`` decodes of ``data`` (CPU seconds) and the last one's counters."""
    best = float("inf")
    for _ in range(rounds):
        decoder = StreamDecoder(Geometry(color_filter="RGBG"))
        start = time.thread_time()
        for i in range(0, len(data), piece):
            decoder.decode(data[i : i + piece])
        best = min(best, time.thread_time() - start)
    counters = decoder.counters
    assert counters["events"] == n_events, counters
    return best, counters


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=2.0, help="stream length (device time)")
    parser.add_argument("--piece", type=int, default=1 << 20, help="bytes per decode call")
    parser.add_argument(
        "--rounds", type=int, default=3, help="decodes of each stream; the fastest counts"
    )
    args = parser.parse_args(argv)
    data, n_events = dense_stream(args.seconds)
    events_only = StreamEncoder().encode(dense_events(args.seconds))
    StreamDecoder(Geometry()).decode(data[:4096])  # compile (or load the cached build)
    seconds, counters = best_time(data, n_events, args.piece, args.rounds)
    seconds_events, _ = best_time(events_only, n_events, args.piece, args.rounds)
    report(
        "decode_throughput",
        {
            "events": n_events,
            "frames": counters["frames"],
            "imu_samples": counters["imu_samples"],
            "bytes": len(data),
            "words_per_event": len(data) / 2 / n_events,
            "decode_Mev_per_s": n_events / seconds / 1e6,
            "decode_MB_per_s": len(data) / seconds / 1e6,
            "events_only_words_per_event": len(events_only) / 2 / n_events,
            "events_only_Mev_per_s": n_events / seconds_events / 1e6,
        },
    )


if __name__ == "__main__":
    main()
