"""End-to-end recording throughput: a replay camera serving a dense stream (12 Mev/s of events,
frames at 25 fps, IMU at 1 kHz) as fast as it can, through the reader thread, the decoder and
the session writer, into a session file. Then `evcap record` on it as a user runs it: its peak
memory, how soon it ends after Ctrl-C (SIGINT) with the backlog it has then, and its memory
and session length on 658 kB of random bytes (a flaky cable).

    .venv/bin/python bench/record_throughput.py [--seconds S]
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import report
from _streams import dense_stream

from evcap.acquire.device import Davis346
from evcap.acquire.recorder import Recorder, RecordOptions
from evcap.session import Session


def make_fixture(folder: Path, data: bytes, transfer_size: int) -> None:
    folder.mkdir()
    np.full(len(data) // transfer_size + 1, transfer_size, "<u4").tofile(folder / "transfers.u32")
    (folder / "device.toml").write_text(
        '[usb]\nidVendor = 0x152A\nidProduct = 0x841A\nbcdDevice = 0x0006\nserial = "BENCH001"\n'
        'product = "DAVIS FX3"\n\n[registers]\n"2.3" = 1\n'
    )
    (folder / "bulk.bin").write_bytes(data)


def peak_memory_mb(child: subprocess.Popen) -> float:
    """The child's peak resident memory (VmHWM, Linux), followed until it ends."""
    peak = 0.0
    while child.poll() is None:
        try:
            status = Path(f"/proc/{child.pid}/status").read_text()
        except OSError:
            break
        for line in status.splitlines():
            if line.startswith("VmHWM:"):
                peak = max(peak, int(line.split()[1]) / 1024)
        time.sleep(0.05)
    if child.wait():
        raise RuntimeError(f"evcap record failed ({child.returncode})")
    return peak


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=4.0, help="stream length (device time)")
    parser.add_argument(
        "--transfer-size",
        type=int,
        default=8192,
        help="bytes per bulk transfer (the replay serves transfers this big)",
    )
    parser.add_argument(
        "--interrupt-after", type=float, default=2.0, help="seconds before the SIGINT"
    )
    args = parser.parse_args(argv)
    data, n_events = dense_stream(args.seconds)
    with tempfile.TemporaryDirectory() as tmp:
        fixture = Path(tmp) / "fixture"
        make_fixture(fixture, data, args.transfer_size)
        out = Path(tmp) / "bench.h5"
        options = RecordOptions(transfer_size=args.transfer_size)
        with Davis346.open(f"replay:{fixture}") as cam:
            recorder = Recorder(cam, out, options)
            start = time.perf_counter()
            result = recorder.run()
            wall = time.perf_counter() - start
        with Session.open(out) as s:
            assert s.n_events == n_events, (s.n_events, n_events)
            size = out.stat().st_size
        record = [sys.executable, "-m", "evcap", "record", "--device", f"replay:{fixture}"]
        record += ["-o", str(out), "--no-tui", "-f"]
        peak_mb = peak_memory_mb(subprocess.Popen(record))
        child = subprocess.Popen(record, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        time.sleep(args.interrupt_after)
        interrupted = time.perf_counter()
        child.send_signal(signal.SIGINT)
        child.wait()
        exit_s = time.perf_counter() - interrupted
        with Session.open(out) as s:  # opening validates it: complete, index and all
            kept = s.n_events
        # a flaky cable: 658 kB of random bytes for the stream
        noise = Path(tmp) / "noise"
        rng = np.random.default_rng(0)
        make_fixture(noise, rng.integers(0, 256, 658_000, np.uint8).tobytes(), args.transfer_size)
        record[record.index("--device") + 1] = f"replay:{noise}"
        noise_mb = peak_memory_mb(subprocess.Popen(record, stderr=subprocess.DEVNULL))
        with Session.open(out) as s:
            noise_span_s = (s.time_range()[1] - s.time_range()[0]) / 1e6
    report(
        "record_throughput",
        {
            "events": n_events,
            "frames": result.frames,
            "stream_MB": len(data) / 1e6,
            "wall_s": wall,
            "transfer_size": args.transfer_size,
            "record_Mev_per_s": n_events / wall / 1e6,
            "realtime_factor": args.seconds / wall,
            "session_MB": size / 1e6,
            "cli_peak_memory_MB": peak_mb,
            "cli_exit_after_sigint_s": exit_s,
            "cli_events_kept_at_sigint": kept,
            "cli_random_bytes_peak_memory_MB": noise_mb,
            "cli_random_bytes_session_s": noise_span_s,
        },
    )


if __name__ == "__main__":
    main()
