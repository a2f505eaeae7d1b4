"""The record path measured per stage, for bench/record_throughput.py.

One recording of a replay camera (``record_once``): its start-up (the decoder's compiled code
loaded, the camera configured) apart from its streaming time (the camera's start to the
session closed), and the CPU time of each of the recorder's threads while it streams (Linux:
/proc/self/task), so that each stage's share shows and the busiest thread, the bottleneck,
stands out. Then each stage alone (``stages``): the reader thread serving the replay, the
decoder, the session writer, each one's time for the whole stream.

Only public APIs that every evcap since the first recorder has are used, so that another
commit's code (bench/steps.py's ``use_code``) is measured by the same functions.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections import Counter
from contextlib import contextmanager
from pathlib import Path

# thread name (its prefix) -> the stage it runs
THREAD_STAGES = {
    "evcap-usb-reader": "reader",
    "MainThread": "recorder",  # take, decode; before the writer thread also the writing
    "evcap-session-writer": "writer",
    "ThreadPoolExecutor": "compressors",
}


def _stage_of(name: str) -> str:
    for prefix, stage in THREAD_STAGES.items():
        if name.startswith(prefix):
            return stage
    return "other"


def _task_cpu() -> dict[int, float]:
    """CPU seconds (user + system) of each thread of this process, by native id."""
    tick = os.sysconf("SC_CLK_TCK")
    out = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            fields = Path(f"/proc/self/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # ended meanwhile
        out[int(tid)] = (int(fields[11]) + int(fields[12])) / tick
    return out


class ThreadCpu:
    """CPU seconds per stage while it runs, from samples of every thread every 20 ms (a thread
    that ends keeps its last sample)."""

    def __init__(self) -> None:
        self.available = Path("/proc/self/task").is_dir()
        self._names: dict[int, str] = {}
        self._last: dict[int, float] = {}
        self._start: dict[int, float] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, name="bench-sampler", daemon=True)

    def _sample_once(self) -> None:
        for t in threading.enumerate():
            if t.native_id is not None:
                self._names[t.native_id] = t.name
        self._last.update(_task_cpu())

    def _sample(self) -> None:
        while not self._stop.wait(0.02):
            self._sample_once()

    def __enter__(self) -> ThreadCpu:
        if self.available:
            self._start = _task_cpu()
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        if self.available:
            self._stop.set()
            self._thread.join()
            self._sample_once()

    def by_stage(self) -> dict[str, float]:
        stages: Counter[str] = Counter()
        for tid, cpu in self._last.items():
            name = self._names.get(tid, "")
            if name == "bench-sampler":
                continue
            stages[_stage_of(name)] += cpu - self._start.get(tid, 0.0)
        return dict(stages)


def record_once(fixture: Path, out: Path, transfer_size: int) -> dict:
    """One recording of the replay camera at ``fixture`` into ``out``: its figures."""
    from evcap.acquire.device import Davis346
    from evcap.acquire.recorder import Recorder, RecordOptions

    with Davis346.open(f"replay:{fixture}") as cam:
        started: list[float] = []
        start = cam.start

        def timed_start(**kw):
            started.append(time.perf_counter())
            return start(**kw)

        cam.start = timed_start
        recorder = Recorder(cam, out, RecordOptions(transfer_size=transfer_size, overwrite=True))
        with ThreadCpu() as cpu:
            begin = time.perf_counter()
            result = recorder.run()
            end = time.perf_counter()
    figures = {
        "events": result.events,
        "frames": result.frames,
        "wall_s": end - begin,
        "startup_s": started[0] - begin,
        "streaming_s": end - started[0],
        "session_MB": out.stat().st_size / 1e6,
    }
    if cpu.available:
        figures |= {f"cpu_{stage}_s": s for stage, s in cpu.by_stage().items()}
    return figures


def stages(fixture: Path, data: bytes, out: Path, piece: int = 4 << 20) -> dict:
    """Each stage alone, over the whole stream: seconds of the reader (the replay camera
    through the reader thread, the bytes taken and dropped), of the decoder (``piece`` bytes
    a call, as the recorder takes them) and of the session writer (the decoded batches)."""
    from evcap.acquire.decoder import StreamDecoder
    from evcap.acquire.device import Davis346
    from evcap.session import SensorInfo, SessionWriter

    with Davis346.open(f"replay:{fixture}") as cam:
        geometry = cam.info.geometry
        begin = time.perf_counter()
        reader = cam.start()
        received = 0
        while received < len(data):
            received += sum(len(c) for c in reader.take(0.001))
            if reader.lost or reader.failure or time.perf_counter() - begin > 600:
                raise RuntimeError(f"the reader stopped at {received} of {len(data)} bytes")
        reader_s = time.perf_counter() - begin
        cam.stop()
    decoder = StreamDecoder(geometry)
    decoder.decode(b"")
    begin = time.perf_counter()
    batches = [decoder.decode(data[i : i + piece]) for i in range(0, len(data), piece)]
    decoder_s = time.perf_counter() - begin
    sensor = SensorInfo("bench", geometry.width, geometry.height, geometry.color_filter)
    begin = time.perf_counter()
    with SessionWriter(out, sensor, overwrite=True) as writer:
        for d in batches:
            writer.append_events(d.events)
            writer.append_frames(d.frames)
            writer.append_imu(d.imu)
            writer.append_triggers(d.triggers)
    writer_s = time.perf_counter() - begin
    return {"reader_s": reader_s, "decoder_s": decoder_s, "writer_s": writer_s}


def profile(fixture: Path, data: bytes, folder: Path, transfer_size: int) -> dict:
    """One round: a recording, then each stage alone."""
    figures = record_once(fixture, folder / "record.h5", transfer_size)
    figures |= {f"stage_{k}": v for k, v in stages(fixture, data, folder / "stages.h5").items()}
    return figures


def profile_in_child(code: Path, fixture: Path, data_path: Path, transfer_size: int) -> dict:
    """``profile`` run in a fresh process with the evcap of the checkout at ``code``."""
    import json

    bench = Path(__file__).resolve().parent
    script = (
        "import json, sys\n"
        f"sys.path.insert(0, {str(bench)!r})\n"
        "from pathlib import Path\n"
        "from steps import use_code\n"
        f"use_code(Path({str(code)!r}))\n"
        "import tempfile\n"
        "from _record_profile import profile\n"
        "with tempfile.TemporaryDirectory() as tmp:\n"
        f"    data = Path({str(data_path)!r}).read_bytes()\n"
        f"    figures = profile(Path({str(fixture)!r}), data, Path(tmp), {transfer_size})\n"
        "print(json.dumps(figures))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=False
    )
    if done.returncode:
        raise RuntimeError(f"the profile of {code} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


@contextmanager
def busy_cores(n: int):
    """``n`` processes that keep a core busy each (a machine under load) while in the block."""
    procs = [
        subprocess.Popen([sys.executable, "-c", "while True: pass"], stdin=subprocess.DEVNULL)
        for _ in range(n)
    ]
    try:
        time.sleep(0.2 if n else 0)  # let them start
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()
