"""End-to-end recording throughput: a replay camera serving a dense stream (12 Mev/s of events,
frames at 25 fps, IMU at 1 kHz) as fast as it can, through the reader thread, the decoder and
the session writer, into a session file; profiled per stage, on the machine as it is and with
every core kept busy by another process (a machine under load). Then the event fields'
compression compared (evcap's deflate, and hdf5plugin's filters where it is installed), and
`evcap record` on the stream as a user runs it: its throughput less its start-up, its peak
memory, how soon it ends after Ctrl-C (SIGINT) with the backlog it has then, and its memory
and session length on 658 kB of random bytes (a flaky cable).

The throughput is the stream's events over the streaming time: from the camera's start to the
session closed (the decoder's compiled code is loaded before the camera starts; that start-up
is given apart). ``--baseline REF`` measures commit REF's code beside this one, each round in a
fresh process, the two alternating; the fastest of ``--rounds`` counts.

    .venv/bin/python bench/record_throughput.py [--seconds S] [--rounds N] [--baseline REF]
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import export_commit, markdown_table, report
from _event_codecs import compare
from _record_profile import busy_cores, profile, profile_in_child
from _streams import dense_events, dense_stream

from evcap.session import Session

ROOT = Path(__file__).resolve().parent.parent
STAGES = ("reader", "decoder", "writer")


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


def best_rounds(runs: list[dict]) -> dict:
    """The fastest round's recording, and each stage alone at its fastest over the rounds."""
    best = dict(min(runs, key=lambda r: r["streaming_s"]))
    for stage in STAGES:
        best[f"stage_{stage}_s"] = min(r[f"stage_{stage}_s"] for r in runs)
    return best


def summarize(run: dict, seconds: float) -> dict:
    """The figures of one code under one load: throughput, each stage's share and the
    bottleneck, alone and as the recording's threads spent their CPU."""
    n = run["events"]
    out = {
        "record_Mev_per_s": n / run["streaming_s"] / 1e6,
        "realtime_factor": seconds / run["streaming_s"],
        "startup_s": run["startup_s"],
        "record_Mev_per_s_with_startup": n / run["wall_s"] / 1e6,
        "session_MB": run["session_MB"],
    }
    alone = {stage: run[f"stage_{stage}_s"] for stage in STAGES}
    for stage, s in alone.items():
        out[f"{stage}_alone_Mev_per_s"] = n / s / 1e6
        out[f"{stage}_share"] = s / sum(alone.values())
    out["bottleneck_alone"] = max(alone, key=alone.get)
    cpu = {k[4:-2]: v for k, v in run.items() if k.startswith("cpu_")}
    if cpu:
        for thread, s in cpu.items():
            out[f"thread_{thread}_cpu_s"] = s
            out[f"thread_{thread}_busy"] = s / run["streaming_s"]
        out["cores_used"] = sum(cpu.values()) / run["streaming_s"]
        busiest = max((t for t in cpu if t != "other"), key=cpu.get)
        cores = os.cpu_count() or 1
        out["bottleneck"] = "all cores busy" if out["cores_used"] > 0.9 * cores else busiest
    return out


def measure(args, fixture: Path, data: bytes, folder: Path, baseline: Path | None) -> dict:
    """Both codes (this one; the baseline's, if any) on the idle and the loaded machine."""
    codes = {"": ROOT} if baseline is None else {"": ROOT, "baseline_": baseline}
    data_path = folder / "stream.bin"
    data_path.write_bytes(data)
    figures = {}
    for load, cores in (("", 0), ("loaded_", args.load_cores)):
        if load and not cores:
            continue
        runs: dict[str, list[dict]] = {key: [] for key in codes}
        with busy_cores(cores):
            figures[f"{load}load_average"] = os.getloadavg()[0]
            for k in range(args.rounds):
                for key, code in list(codes.items())[:: 1 if k % 2 == 0 else -1]:
                    if baseline is None:
                        run = profile(fixture, data, folder, args.transfer_size)
                    else:
                        run = profile_in_child(code, fixture, data_path, args.transfer_size)
                    runs[key].append(run)
        for key, rounds in runs.items():
            for name, value in summarize(best_rounds(rounds), args.seconds).items():
                figures[f"{key}{load}{name}"] = value
        if baseline is not None:
            ratio = figures[f"{load}record_Mev_per_s"] / figures[f"baseline_{load}record_Mev_per_s"]
            figures[f"{load}record_speedup"] = ratio
    return figures


def cli_figures(args, fixture: Path, n_events: int, tmp: Path) -> dict:
    """`evcap record` as a user runs it (see the module's docstring)."""
    out = tmp / "cli.h5"
    record = [sys.executable, "-m", "evcap", "record", "--device", f"replay:{fixture}"]
    record += ["-o", str(out), "--no-tui", "-f"]
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    empty = tmp / "empty"
    make_fixture(empty, b"", args.transfer_size)
    startup = []
    for _ in range(2):
        begin = time.perf_counter()
        subprocess.run([*record[:5], f"replay:{empty}", *record[6:]], check=True, **quiet)
        startup.append(time.perf_counter() - begin)
    walls, peaks = [], []
    for _ in range(args.cli_runs):
        begin = time.perf_counter()
        peaks.append(peak_memory_mb(subprocess.Popen(record, **quiet)))
        walls.append(time.perf_counter() - begin)
    child = subprocess.Popen(record, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    time.sleep(args.interrupt_after)
    interrupted = time.perf_counter()
    child.send_signal(signal.SIGINT)
    child.wait()
    exit_s = time.perf_counter() - interrupted
    with Session.open(out) as s:  # opening validates it: complete, index and all
        kept = s.n_events
    # a flaky cable: 658 kB of random bytes for the stream
    noise = tmp / "noise"
    rng = np.random.default_rng(0)
    make_fixture(noise, rng.integers(0, 256, 658_000, np.uint8).tobytes(), args.transfer_size)
    record[record.index("--device") + 1] = f"replay:{noise}"
    noise_mb = peak_memory_mb(subprocess.Popen(record, **quiet))
    with Session.open(out) as s:
        noise_span_s = (s.time_range()[1] - s.time_range()[0]) / 1e6
    streaming = max(min(walls) - min(startup), 1e-6)
    return {
        "cli_startup_s": min(startup),
        "cli_record_Mev_per_s": n_events / streaming / 1e6,
        "cli_peak_memory_MB": max(peaks),
        "cli_exit_after_sigint_s": exit_s,
        "cli_events_kept_at_sigint": kept,
        "cli_random_bytes_peak_memory_MB": noise_mb,
        "cli_random_bytes_session_s": noise_span_s,
    }


def print_profile(figures: dict, prefixes: list[str]) -> None:
    rows = []
    for prefix in prefixes:
        if f"{prefix}record_Mev_per_s" not in figures:
            continue
        row = {"run": prefix.rstrip("_") or "this code, idle"}
        row |= {k: figures.get(f"{prefix}{k}") for k in ("record_Mev_per_s", "realtime_factor")}
        for stage in STAGES:
            row[f"{stage} alone %"] = 100 * figures[f"{prefix}{stage}_share"]
        for thread in ("reader", "recorder", "writer", "compressors"):
            busy = figures.get(f"{prefix}thread_{thread}_busy")
            row[f"{thread} busy"] = busy
        row["bottleneck"] = figures.get(f"{prefix}bottleneck", figures[f"{prefix}bottleneck_alone"])
        rows.append(row)
    if rows:
        print(markdown_table(rows, tuple(rows[0])))


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=4.0, help="stream length (device time)")
    parser.add_argument(
        "--transfer-size",
        type=int,
        default=8192,
        help="bytes per bulk transfer (the replay serves transfers this big)",
    )
    parser.add_argument("--rounds", type=int, default=3, help="the fastest of these counts")
    parser.add_argument("--baseline", help="a git commit to measure beside this code")
    parser.add_argument(
        "--load-cores",
        type=int,
        default=os.cpu_count() or 1,
        help="busy processes of the loaded run (default: one a core; 0: no loaded run)",
    )
    parser.add_argument("--cli-runs", type=int, default=3, help="`evcap record` runs timed")
    parser.add_argument(
        "--interrupt-after", type=float, default=2.0, help="seconds before the SIGINT"
    )
    args = parser.parse_args(argv)
    data, n_events = dense_stream(args.seconds)
    with tempfile.TemporaryDirectory() as folder:
        tmp = Path(folder)
        fixture = tmp / "fixture"
        make_fixture(fixture, data, args.transfer_size)
        baseline = export_commit(args.baseline, ROOT) if args.baseline else None
        try:
            figures = measure(args, fixture, data, tmp, baseline and Path(baseline.name))
        finally:
            if baseline is not None:
                baseline.cleanup()
        codecs = compare(dense_events(min(args.seconds, 1.0)))
        figures |= cli_figures(args, fixture, n_events, tmp)
    prefixes = ["", "loaded_", "baseline_", "baseline_loaded_"]
    print_profile(figures, prefixes)
    if codecs:
        print(markdown_table(codecs, tuple(codecs[0])))
    head = {
        "events": n_events,
        "stream_MB": len(data) / 1e6,
        "seconds": args.seconds,
        "transfer_size": args.transfer_size,
    }
    if args.baseline:
        head["baseline"] = args.baseline
    report("record_throughput", {**head, **figures, "codecs": codecs})
    return figures


if __name__ == "__main__":
    main()
