"""The host falling behind the camera: the backlog and the camera's drops, said while it
happens (the recorder's Stats, evcap record's warnings; the monitor's: tests/tui)."""

import subprocess
import sys
from pathlib import Path

import pytest

from evcap.acquire import recorder as recorder_module
from evcap.acquire import writer_thread
from evcap.acquire.backlog import Backlog, BehindWatch
from evcap.acquire.device import Davis346, DeviceSpec
from evcap.acquire.recorder import Recorder, Stats
from evcap.errors import DiskFullError
from evcap.session import Session, SessionWriter

FIXTURES = Path(__file__).resolve().parents[2] / "hw-fixtures"
MB = 1 << 20


def backlog(received_mb: float = 0, held: int = 0) -> Backlog:
    return Backlog(int(received_mb * MB), 32 * MB, held, 0, 64 * MB)


def test_behind_watch_says_when_the_host_falls_behind_catches_up_and_the_camera_drops():
    now = [0.0]
    watch = BehindWatch(clock=lambda: now[0])
    assert watch.update(backlog(1), dropped=500) == []  # the counters' start is no drop
    said = watch.update(backlog(12), dropped=500)
    assert said == [("warning", "the host is falling behind: 12.6 MB waiting (38 % of the buffer)")]
    assert watch.behind and watch.backlog.total_bytes == 12 * MB
    now[0] = 2.0
    assert watch.update(backlog(20), dropped=500) == []  # said already, 2 s ago
    now[0] = 6.0
    said = watch.update(backlog(33, held=3), dropped=1700)
    assert said[0][1].endswith("(103 % of the buffer), 3 USB transfers held back")
    assert said[1] == (
        "warning",
        "the camera dropped 1,200 events in the last second (1,700 since it started): the "
        "host or the USB link is not keeping up",
    )
    assert watch.new_drops == 1200
    said = watch.update(backlog(0.5), dropped=1700)
    assert said == [("information", "the host has caught up: 0.5 MB waiting (2 % of the buffer)")]
    assert not watch.behind and watch.new_drops == 0


def slow_disk(monkeypatch, seconds: float = 0.02) -> None:
    """Every append of events takes ``seconds`` more; the writer's queue holds one batch, so
    that every batch after the first waits (however the machine's load groups them)."""
    append = SessionWriter.append_events

    def slow(self, events):
        import time

        time.sleep(seconds)
        append(self, events)

    monkeypatch.setattr(SessionWriter, "append_events", slow)
    monkeypatch.setattr(writer_thread, "MAX_QUEUED_BYTES", 1)
    monkeypatch.setattr(recorder_module, "STATS_INTERVAL_S", 0.05)


def test_the_recorder_reports_the_backlog_while_it_waits_for_the_writer(tmp_path, monkeypatch):
    slow_disk(monkeypatch)
    stats = []
    spec = DeviceSpec("replay", path=FIXTURES / "color-scene", speed=4.0)
    with Davis346.open(spec) as cam:
        recorder = Recorder(cam, tmp_path / "s.h5", on_event=stats.append)
        result = recorder.run()
    stats = [s for s in stats if isinstance(s, Stats)]
    assert any(s.backlog.decoded_bytes > 0 and s.backlog.falling_behind for s in stats)
    assert result.behind_seconds > 0 and result.largest_backlog_bytes > 0
    with Session.open(tmp_path / "s.h5") as s:  # nothing lost for it
        assert s.complete and s.n_events == 60_000


SLOW_RECORD = r"""
import sys, time
from evcap.acquire import recorder, writer_thread
from evcap.acquire.device import Davis346
from evcap.app.cli import main
from evcap.session import SessionWriter

append = SessionWriter.append_events
def slow(self, events):
    time.sleep(0.02)
    append(self, events)
SessionWriter.append_events = slow
writer_thread.MAX_QUEUED_BYTES = 1
recorder.STATS_INTERVAL_S = 0.05
calls = [0]
def dropped_counters(self):
    calls[0] += 1
    return {"mux_dvs_dropped": 0, "mux_extinput_dropped": 0, "dvs_dropped": 1000 * calls[0]}
Davis346.dropped_counters = dropped_counters
sys.exit(main(sys.argv[1:]))
"""


def test_evcap_record_says_so_while_the_host_falls_behind(tmp_path):
    out = tmp_path / "s.h5"
    fixture = FIXTURES / "color-scene"
    r = subprocess.run(
        [sys.executable, "-c", SLOW_RECORD, "record", "--device", f"replay:{fixture}"]
        + ["-o", str(out), "--no-tui"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    lines = r.stderr.splitlines()
    assert any(line.startswith("warning: the host is falling behind: ") for line in lines)
    assert any("the camera dropped 1,000 events in the last second" in line for line in lines)
    assert "the host fell behind the camera while recording" in lines[-1]
    assert "60,000 events" in r.stdout
    with Session.open(out) as s:
        assert s.complete and s.n_events == 60_000


@pytest.mark.parametrize("tty", [False, True])
def test_the_warnings_go_over_the_status_line_on_a_terminal(capsys, tty):
    from evcap.app.commands_capture import _behind_warnings

    on_event = _behind_warnings(BehindWatch(), tty)
    on_event(Stats({"dvs_dropped": 0}, None, backlog(0)))
    on_event(Stats({"dvs_dropped": 5}, None, backlog(20)))
    on_event("something else")
    err = capsys.readouterr().err
    prefix = "\r\x1b[K" if tty else ""
    assert err.split("\n")[:-1] == [
        f"{prefix}warning: the host is falling behind: 21.0 MB waiting (62 % of the buffer)",
        f"{prefix}warning: the camera dropped 5 events in the last second (5 since it started): "
        "the host or the USB link is not keeping up",
    ]


def test_a_full_disk_found_while_waiting_for_the_writer_stops_the_recording(tmp_path, monkeypatch):
    """The recorder spends its time waiting for a slow writer, and reads the Stats there: a
    disk found almost full then still ends the recording, as "disk full", at once."""
    slow_disk(monkeypatch, seconds=0.1)
    reads = [0]

    def free_bytes(self):
        reads[0] += 1
        return (10 << 20) if reads[0] > 3 else (10 << 30)

    monkeypatch.setattr(SessionWriter, "free_bytes", free_bytes)
    spec = DeviceSpec("replay", path=FIXTURES / "color-scene", speed=1.0)
    with Davis346.open(spec) as cam, pytest.raises(DiskFullError, match="MB left on the disk"):
        Recorder(cam, tmp_path / "s.h5").run()
    with Session.open(tmp_path / "s.h5") as s:
        # stopped at the Stats that found it (before: nearly all of the 60,000 events went in)
        assert s.complete and 0 < s.n_events < 30_000
