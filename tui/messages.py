"""The messages the capture thread posts to the monitor (the only way it reaches the UI)."""

from __future__ import annotations

from dataclasses import dataclass

from textual.message import Message

from evcap.tui.live import LiveSnapshot


@dataclass
class RecordingStatus:
    """The open recording, as the capture thread sees it."""

    path: str
    events: int
    frames: int
    duration_s: float  # device time since the recording started


@dataclass
class LiveUpdate(Message):
    """A new view of the stream. A newer one replaces one not drawn yet: drawing is dropped
    before data is."""

    snapshot: LiveSnapshot
    recording: RecordingStatus | None
    host_dropped: int  # events the decoder discarded (malformed)

    def can_replace(self, message: Message) -> bool:
        return isinstance(message, LiveUpdate)


@dataclass
class CaptureEvent(Message):
    """Something the recorder reports: a recording started or stopped, a bias written, the
    device's counters, the camera lost, a request that failed (evcap.acquire.recorder)."""

    event: object


@dataclass
class CaptureEnded(Message):
    """The capture thread has ended; ``error`` if it ended with one."""

    error: str | None = None
