"""Stream decoder throughput on one core: a dense realistic stream (12 Mev/s of events, frames
at 25 fps, IMU at 1 kHz) decoded in 1 MiB pieces, as the recorder hands them over.

    .venv/bin/python bench/decode_throughput.py [--seconds S]
"""

from __future__ import annotations

import argparse
import time

from _common import report
from _streams import dense_stream

from evcap.acquire.decoder import Geometry, StreamDecoder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=2.0, help="stream length (device time)")
    parser.add_argument("--piece", type=int, default=1 << 20, help="bytes per decode call")
    args = parser.parse_args()
    data, n_events = dense_stream(args.seconds)
    StreamDecoder(Geometry()).decode(data[:4096])  # compile (or load the cached build)
    best = float("inf")
    for _ in range(3):
        decoder = StreamDecoder(Geometry(color_filter="RGBG"))
        start = time.perf_counter()
        for i in range(0, len(data), args.piece):
            decoder.decode(data[i : i + args.piece])
        best = min(best, time.perf_counter() - start)
    counters = decoder.counters
    assert counters["events"] == n_events, counters
    report(
        "decode_throughput",
        {
            "events": n_events,
            "frames": counters["frames"],
            "imu_samples": counters["imu_samples"],
            "bytes": len(data),
            "words_per_event": len(data) / 2 / n_events,
            "decode_Mev_per_s": n_events / best / 1e6,
            "decode_MB_per_s": len(data) / best / 1e6,
        },
    )


if __name__ == "__main__":
    main()
