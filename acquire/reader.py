"""The reader thread: keeps bulk transfers in flight and hands the bytes over, in order.

Nothing received is dropped. The bytes waiting for the consumer are bounded: past the bound a
completed transfer is not resubmitted until the consumer catches up, so the camera holds the
data (and, if it overflows, drops events and counts them in its own registers) instead of this
process's memory growing without end. Timeouts and stalls are recovered from (a stall is cleared
and the transfer resubmitted); a vanished device ends the reader with ``lost`` set.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass

from evcap.acquire.transfers import BulkStream, Status

MAX_CONSECUTIVE_ERRORS = 20
# received and not yet taken; a consumer decodes and writes this much in well under a second
MAX_QUEUED_BYTES = 32 << 20


@dataclass
class ReaderStats:
    transfers: int = 0  # completed with data
    bytes: int = 0
    timeouts: int = 0
    stalls: int = 0
    errors: int = 0
    waits: int = 0  # transfers held back while the consumer caught up


class BulkReader:
    """Runs ``stream`` with ``count`` transfers in flight in its own thread."""

    def __init__(
        self, stream: BulkStream, count: int, max_queued_bytes: int = MAX_QUEUED_BYTES
    ) -> None:
        self._stream = stream
        self._count = count
        self._chunks: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        self._max_queued = max_queued_bytes
        self._queued = 0  # bytes in _chunks
        self._queued_lock = threading.Lock()
        self._held: list[int] = []  # slots not resubmitted while the queue is full
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="evcap-usb-reader", daemon=True)
        self.stats = ReaderStats()
        self.lost: str | None = None  # why the device was lost, if it was
        self.failure: BaseException | None = None

    def start(self) -> None:
        self._thread.start()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    @property
    def queued_bytes(self) -> int:
        """Received and not yet taken: the host's backlog."""
        return self._queued

    @property
    def max_queued_bytes(self) -> int:
        """Past this the reader holds transfers back, and the camera holds the data."""
        return self._max_queued

    @property
    def held_transfers(self) -> int:
        """Transfers held back now (0 while the consumer keeps up)."""
        return len(self._held)

    def stop(self, timeout_s: float = 5.0) -> bool:
        """Cancel the transfers, keep the data they received, and end the thread. False if
        the thread did not end in time (its transfers may still be in flight)."""
        self._stop.set()
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def take(self, timeout_s: float = 0.0, max_bytes: int = 4 << 20) -> list[bytes]:
        """The chunks received so far, up to about ``max_bytes`` (waiting up to ``timeout_s``
        for the first)."""
        chunks = []
        size = 0
        if timeout_s > 0 and self._chunks.empty():
            # not SimpleQueue.get(timeout=): on CPython 3.11 a signal whose handling outlasts
            # the timeout leaves it waiting forever (a recorder hung so after SIGTERM)
            time.sleep(timeout_s)
        try:
            chunk = self._chunks.get_nowait()
            while True:
                chunks.append(chunk)
                size += len(chunk)
                if size >= max_bytes:
                    break
                chunk = self._chunks.get_nowait()
        except queue.Empty:
            pass
        with self._queued_lock:
            self._queued -= size
        return chunks

    def _handle(self, slot: int, status: Status, data: bytes, resubmit: bool) -> None:
        s = self._stream
        if data:  # a cancelled or failed transfer may still carry data: keep it
            with self._queued_lock:
                self._queued += len(data)
            self._chunks.put(data)
            self.stats.transfers += 1
            self.stats.bytes += len(data)
        if status == Status.NO_DEVICE:
            self.lost = "the camera was disconnected"
            return
        if status == Status.STALL:
            self.stats.stalls += 1
            s.clear_halt()
        elif status == Status.TIMED_OUT:
            self.stats.timeouts += 1
        elif status in (Status.ERROR, Status.OVERFLOW):
            self.stats.errors += 1
            self._errors_in_a_row += 1
            if self._errors_in_a_row >= MAX_CONSECUTIVE_ERRORS:
                self.lost = f"{self._errors_in_a_row} USB transfers failed in a row"
                return
        if status == Status.COMPLETED:
            self._errors_in_a_row = 0
        if resubmit and status != Status.CANCELLED:
            if self._queued > self._max_queued:
                self._held.append(slot)
                self.stats.waits += 1
            else:
                s.submit(slot)

    def _run(self) -> None:
        s = self._stream
        self._errors_in_a_row = 0
        try:
            for slot in range(self._count):
                s.submit(slot)
            while not self._stop.is_set() and self.lost is None:
                for slot, status, data in s.poll(0.05):
                    self._handle(slot, status, data, resubmit=self.lost is None)
                if self._held and self._queued <= self._max_queued // 2:
                    for slot in self._held:
                        s.submit(slot)
                    self._held.clear()
            s.cancel()
            while s.in_flight:
                for slot, status, data in s.poll(0.05):
                    self._handle(slot, status, data, resubmit=False)
            s.close()
        except BaseException as e:  # surfaced to the consumer, never lost silently
            self.failure = e
