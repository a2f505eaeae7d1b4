"""The monitor: a textual app that shows a running camera live, and records it on request.

The capture (evcap.acquire.recorder.Recorder) runs in its own thread and reaches the UI only
through messages (evcap.tui.messages); the UI asks the capture for things only through the
recorder's request methods. Live views are throttled and replace each other in the message
queue, so a slow terminal drops drawing, never data.
"""

from __future__ import annotations

import datetime
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path

from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.widgets import Footer, Header

from evcap.acquire.backlog import BehindWatch
from evcap.acquire.decoder import Decoded
from evcap.acquire.recorder import (
    NORMAL_ENDS,
    BiasChanged,
    CameraLost,
    Recorder,
    RecorderError,
    RecordingStarted,
    RecordingStopped,
    Stats,
)
from evcap.errors import EvcapError
from evcap.tui.live import LiveView
from evcap.tui.messages import CaptureEnded, CaptureEvent, LiveUpdate, RecordingStatus
from evcap.tui.screens import BiasScreen, HelpScreen
from evcap.tui.widgets import Panel, PixelView, RateChart, si

DISK_WARNING_BYTES = 1 << 30  # warn below 1 GB free while recording
PANEL_PERIOD_S = 0.25  # the text panels are redrawn 4 times a second, the images at each update


def _free_space(folder: Path) -> int | None:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def session_name(now: datetime.datetime | None = None) -> str:
    now = now or datetime.datetime.now()
    return now.strftime("evcap-%Y%m%d-%H%M%S.h5")


class MonitorApp(App):
    """Live view of one camera. Build it with ``make_app``."""

    TITLE = "evcap monitor"
    CSS = """
    #images { height: 1fr; min-height: 6; }
    #images > Vertical { width: 1fr; border: round $primary 40%; }
    #panels { height: 8; }
    #panels > Panel { width: 1fr; }
    #warnings.alarm { color: $error; text-style: bold; }
    """
    BINDINGS = [
        Binding("r", "record", "Record"),
        Binding("b", "biases", "Biases"),
        Binding("c", "color_by", "Color by"),
        Binding("question_mark", "help", "Help"),
        Binding("q", "quit_monitor", "Quit", priority=True),
        Binding("ctrl+c", "quit_monitor", "Quit", priority=True, show=False),
    ]

    def __init__(
        self,
        recorder: Recorder,
        *,
        record_mode: bool,
        output_dir: Path,
        snapshot_hz: float = 25.0,
        clock: Callable[[], float] = time.monotonic,
        free_space: Callable[[Path], int | None] | None = None,
    ) -> None:
        super().__init__()
        self.recorder = recorder
        self.record_mode = record_mode  # evcap record: one recording, the app ends with it
        self.output_dir = output_dir
        info = recorder.device.info
        g = info.geometry
        self.live = LiveView(g.width, g.height, info.color_filter)
        self._snapshot_period = 1.0 / snapshot_hz
        self._clock = clock
        self._next_snapshot = float("-inf")
        self._thread = threading.Thread(target=self._capture, name="evcap-capture", daemon=True)
        self.capture_error: BaseException | None = None  # what ended the capture, if anything
        self.ended = False
        self.quitting = False
        self.camera_lost: str | None = None
        self.free_bytes: int | None = None
        self._free_space = free_space or _free_space
        self.device_dropped = 0
        self.behind = BehindWatch(clock)  # the backlog and the camera's drops, from Stats
        self.biases = dict(recorder.biases)
        self.recording_path: Path | None = None
        self.last_result = None  # of the last recording that stopped
        self._frame_shown: int | None = None
        self._panels_drawn = float("-inf")
        self._last_update: LiveUpdate | None = None
        recorder.on_batch = self._on_batch
        recorder.on_event = self._on_event
        recorder.on_tick = self._on_tick

    # -- the capture thread ------------------------------------------------------------------

    def _capture(self) -> None:
        error = None
        try:
            self.recorder.run()
        except BaseException as e:  # handed to the UI, and to the CLI after the app
            self.capture_error = e
            error = str(e) if isinstance(e, EvcapError) else repr(e)
        finally:
            self.post_message(self._live_update())  # the last data, even if throttled
            self.post_message(CaptureEnded(error))

    def _live_update(self) -> LiveUpdate:
        r = self.recorder
        rec = r.recording
        status = None
        if rec is not None:
            status = RecordingStatus(
                str(rec.writer.path),
                rec.result.events,
                rec.result.frames,
                (r.decoder.now_us - rec.t0) / 1e6,
            )
        dropped = r.decoder.counters["dvs_out_of_range"] if r.decoder is not None else 0
        return LiveUpdate(self.live.snapshot(), status, dropped)

    def _on_batch(self, batch: Decoded) -> None:
        self.live.add(batch)

    def _on_tick(self) -> None:
        now = self._clock()
        if now >= self._next_snapshot:  # on a fixed schedule, so the rate does not drift
            self._next_snapshot = max(self._next_snapshot + self._snapshot_period, now)
            self.post_message(self._live_update())

    def _on_event(self, event: object) -> None:
        self.post_message(CaptureEvent(event))

    # -- the UI ----------------------------------------------------------------------------------

    def compose(self) -> ComposeResult:
        info = self.recorder.device.info
        yield Header()
        with Horizontal(id="images"):
            with Vertical(id="events-box") as box:
                box.border_title = "events (last 33 ms)"
                yield PixelView(pool="max", id="events")
            with Vertical(id="frame-box") as box:
                box.border_title = "APS frame"
                yield PixelView(pool="mean", id="frame")
        yield RateChart(color=info.color_filter != "MONO", id="rates")
        with Horizontal(id="panels"):
            yield Panel("camera · IMU m/s², rad/s", id="device")
            yield Panel("recording", id="recording")
            yield Panel("warnings", id="warnings")
        yield Footer()

    def on_mount(self) -> None:
        info = self.recorder.device.info
        self.sub_title = f"{info.model} {info.serial}"
        self._show_panels()
        self._thread.start()

    def _show_device(self, snapshot) -> None:
        i = self.recorder.device.info
        lines = [
            f"serial {i.serial}",
            f"fw {i.firmware} logic {i.logic}.{i.logic_patch} {i.color_filter}",
        ]
        if snapshot is not None and snapshot.accel is not None:
            a, g = snapshot.accel, snapshot.gyro
            lines += [
                f"{snapshot.temperature:.1f} °C",
                f"acc {a[0]:+.1f} {a[1]:+.1f} {a[2]:+.1f}",
                f"gyr {g[0]:+.2f} {g[1]:+.2f} {g[2]:+.2f}",
            ]
        if snapshot is not None:
            t = snapshot.totals
            lines.append(f"{t['events']:,} ev {t['frames']:,} fr")
        self.query_one("#device", Panel).show("\n".join(lines))

    def _show_recording(self, update: LiveUpdate | None) -> None:
        status = update.recording if update is not None else None
        if status is None:
            last = self.last_result
            lines = ["not recording" + ("" if self.record_mode else " (r)")]
            if last is not None:
                lines += [f"last {last.path.name}", f"{last.events:,} ev, {last.end_reason}"]
        else:
            path = Path(status.path)
            size = path.stat().st_size if path.exists() else 0
            lines = [
                f"● {path.name}",
                f"{status.duration_s:.1f} s  {size / 1e6:.1f} MB",
                f"{status.events:,} ev {status.frames:,} fr",
                f"backlog {si(self.behind.backlog.total_bytes, 'B')}",
            ]
        dropped = update.host_dropped if update is not None else 0
        lines.append(f"dropped dev {self.device_dropped:,} host {dropped:,}")
        if self.free_bytes is not None:
            lines.append(f"free {si(self.free_bytes, 'B')}")
        self.query_one("#recording", Panel).show("\n".join(lines))

    def _show_warnings(self, snapshot) -> None:
        warnings = []
        if self.camera_lost:
            warnings.append(f"CAMERA LOST\n  {self.camera_lost}")
        if self.free_bytes is not None and self.free_bytes < DISK_WARNING_BYTES:
            warnings.append(f"disk almost full\n  {si(self.free_bytes, 'B')} free")
        if self.behind.behind:
            b = self.behind.backlog
            warnings.append(
                f"HOST FALLING BEHIND\n  {si(b.total_bytes, 'B')} waiting ({100 * b.fill:.0f} %)"
            )
        if self.behind.new_drops:
            warnings.append(f"camera dropped {self.behind.new_drops:,}\n  events (last second)")
        if snapshot is not None and snapshot.hot_pixels_dominate:
            share = 100 * snapshot.hot_pixel_share
            warnings.append(f"hot pixels: 0.1 % of the\n  pixels make {share:.0f} % of events")
        if self.ended and not self.camera_lost:
            warnings.append("the capture has ended")
        panel = self.query_one("#warnings", Panel)
        panel.set_class(bool(warnings), "alarm")
        panel.show("\n".join(warnings) or "none")

    def _widgets_gone(self) -> bool:
        # The capture thread's last messages can arrive while the app shuts down, after its
        # screen's widgets are removed: there is nothing to draw then.
        return not self.query("#device")

    def on_live_update(self, message: LiveUpdate) -> None:
        if self._widgets_gone():
            return
        s = message.snapshot
        self.query_one("#events", PixelView).show(s.image)
        if s.frame is not None and s.frame_t_us != self._frame_shown:
            self._frame_shown = s.frame_t_us
            self.query_one("#frame", PixelView).show(s.frame)
        self.query_one(RateChart).update_rates(s)
        self._last_update = message
        now = self._clock()
        if now - self._panels_drawn >= PANEL_PERIOD_S:
            self._panels_drawn = now
            self._show_panels()

    def _show_panels(self) -> None:
        if self._widgets_gone():
            return
        update = self._last_update
        snapshot = update.snapshot if update is not None else None
        self._show_device(snapshot)
        self._show_recording(update)
        self._show_warnings(snapshot)

    def on_capture_event(self, message: CaptureEvent) -> None:
        event = message.event
        if isinstance(event, RecordingStarted):
            self.recording_path = event.path
            self.notify(f"recording into {event.path}")
        elif isinstance(event, RecordingStopped):
            self.recording_path = None
            r = self.last_result = event.result
            severity = "information" if r.end_reason in NORMAL_ENDS else "error"
            self.notify(f"{r.path.name}: {r.events:,} events ({r.end_reason})", severity=severity)
        elif isinstance(event, BiasChanged):
            self.biases[event.name] = event.code
            if isinstance(self.screen, BiasScreen):
                self.screen.show_bias(event.name, event.code)
        elif isinstance(event, CameraLost):
            self.camera_lost = event.reason
            self._show_panels()
        elif isinstance(event, Stats):
            self.device_dropped = event.dropped
            self.free_bytes = event.free_bytes
            if self.free_bytes is None:  # not recording: the disk recordings would go to
                self.free_bytes = self._free_space(self.output_dir)
            for severity, text in self.behind.update(event.backlog, event.dropped):
                self.notify(text, severity=severity, timeout=4)
            self._show_panels()
        elif isinstance(event, RecorderError):
            self.notify(event.message, severity="error")

    def on_capture_ended(self, message: CaptureEnded) -> None:
        self.ended = True
        self._show_panels()
        if message.error and not self.camera_lost:
            self.notify(message.error, severity="error", timeout=30)
        # evcap record ends with its recording, unless something went wrong: then the
        # warning stays on screen until q.
        if self.quitting or (self.record_mode and not message.error and not self.camera_lost):
            self.exit()

    # -- keys ------------------------------------------------------------------------------------

    def action_record(self) -> None:
        if self.record_mode:
            self.notify("evcap record records until you quit (q)")
        elif self.ended:
            self.notify("the capture has ended", severity="error")
        elif self.recorder.recording is None and self.recording_path is None:
            path = self.output_dir / session_name()
            self.recording_path = path
            self.recorder.start_recording(path)
        else:
            self.recorder.stop_recording()

    def action_biases(self) -> None:
        self.push_screen(BiasScreen(self.biases, self.recorder.set_bias))

    def action_color_by(self) -> None:
        # A flag the capture thread reads when it next draws the image.
        self.live.by_channel = not self.live.by_channel

    def action_help(self) -> None:
        self.push_screen(HelpScreen())

    def action_quit_monitor(self) -> None:
        """Stop the capture (it closes a recording in progress), then leave."""
        self.quitting = True
        self.recorder.stop()
        if self.ended:
            self.exit()


def make_app(
    recorder: Recorder,
    *,
    record_mode: bool = False,
    output_dir: str | Path = ".",
    snapshot_hz: float = 25.0,
    clock: Callable[[], float] = time.monotonic,
    free_space: Callable[[Path], int | None] | None = None,
) -> MonitorApp:
    """The monitor for a recorder that has not run yet (the app runs it in its thread).
    ``record_mode``: the recorder records for the whole run (evcap record); the app ends with
    it. ``free_space`` tells the free bytes of a folder (injected by tests)."""
    return MonitorApp(
        recorder,
        record_mode=record_mode,
        output_dir=Path(output_dir),
        snapshot_hz=snapshot_hz,
        clock=clock,
        free_space=free_space,
    )
