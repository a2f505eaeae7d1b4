"""The session writer in a thread of its own, so that the recorder decodes while it writes.

The recorder hands over decoded batches (the arrays themselves, not copies) and goes back to
the camera; this thread appends them to the session and flushes it every flush interval, so
that a crash or a kill keeps everything up to the last flush, as before. The batches waiting
are bounded: past the bound ``put`` waits, the reader's queue grows, and then the camera holds
the data (and drops what it cannot hold, counting it). A write error ends the thread; the
recorder gets it from its next call.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable

from evcap.acquire.decoder import Decoded
from evcap.session import SessionWriter

MAX_QUEUED_BYTES = 64 << 20
"""Decoded data waiting for the writer: a few of the recorder's largest batches."""
IDLE_WAKE_S = 0.1  # how often the thread looks at the flush clock while no data comes


def batch_bytes(d: Decoded) -> int:
    """The memory a decoded batch holds."""
    e = d.events
    return e.x.nbytes + e.y.nbytes + e.t.nbytes + e.p.nbytes + d.frames.data.nbytes


class WriterThread:
    """Appends decoded batches to ``writer`` in a thread of its own, in the order given."""

    def __init__(self, writer: SessionWriter, max_queued_bytes: int | None = None) -> None:
        self.writer = writer
        self.max_queued_bytes = max_queued_bytes or MAX_QUEUED_BYTES
        self._items: deque[tuple[int, Callable[[], None]]] = deque()
        self._queued = 0  # bytes in _items
        self._cond = threading.Condition()
        self._closing = False
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="evcap-session-writer", daemon=True)
        self._thread.start()

    @property
    def queued_bytes(self) -> int:
        """Decoded data handed over and not yet appended."""
        return self._queued

    def put(self, d: Decoded, wait: Callable[[], None] | None = None) -> None:
        """Queue a batch (its times already the session's). While the queue is full, waits,
        calling ``wait`` every 0.1 s (the recorder reports its state meanwhile)."""
        size = batch_bytes(d)

        def append() -> None:
            w = self.writer
            w.append_events(d.events)
            w.append_frames(d.frames)
            w.append_imu(d.imu)
            w.append_triggers(d.triggers)

        self._put(size, append, wait)

    def append_setting(self, t: int, name: str, value: int) -> None:
        """Log a setting change in the session, in its place among the batches."""
        self._put(0, lambda: self.writer.append_setting(t, name, value), None)

    def _put(self, size: int, item: Callable[[], None], wait: Callable[[], None] | None) -> None:
        while True:
            with self._cond:
                self._raise_error()
                if self._queued == 0 or self._queued + size <= self.max_queued_bytes:
                    self._items.append((size, item))
                    self._queued += size
                    self._cond.notify_all()
                    return
                self._cond.wait(IDLE_WAKE_S)
            if wait is not None:
                wait()

    def _raise_error(self) -> None:
        if self._error is not None:
            raise self._error

    def _run(self) -> None:
        w = self.writer
        while True:
            with self._cond:
                if not self._items:
                    if self._closing or self._error is not None:
                        return
                    self._cond.wait(IDLE_WAKE_S)
                # taken off now, counted in queued_bytes until appended
                size, item = self._items.popleft() if self._items else (0, None)
            try:
                if item is not None:
                    item()
                w.flush_if_due()  # also while no data comes, so that the last data is kept
            except BaseException as e:  # handed to the recorder at its next call
                with self._cond:
                    self._error = e
                    self._items.clear()
                    self._queued = 0
                    self._cond.notify_all()
                return
            if item is not None:
                with self._cond:
                    self._queued -= size
                    self._cond.notify_all()

    def _drop_queued(self) -> None:
        self._queued -= sum(size for size, _ in self._items)
        self._items.clear()

    def _stop(self) -> None:
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self._thread.join()

    def close(self, attrs: dict | None = None) -> None:
        """Append what is queued, then close the session (SessionWriter.close); after a
        write error, abort it (what was flushed is kept) and raise the error."""
        self._stop()
        if self._error is not None:
            self.writer.abort()
            raise self._error
        self.writer.close(attrs)

    def abort(self) -> None:
        """Stop without appending what is queued; keep what was flushed (SessionWriter.abort)."""
        with self._cond:
            self._drop_queued()
        self._stop()
        self.writer.abort()
