"""Bulk IN transfers on the data endpoint, several in flight: the transport seam of the reader.

``LibusbBulkStream`` keeps real asynchronous libusb transfers in flight (through the libusb that
pyusb loaded). ``SyncBulkStream`` serves any other pyusb backend (the replay backend, libusb0)
with synchronous reads, one after another. Both report completions in submission order, with
libusb's transfer statuses.
"""

from __future__ import annotations

import ctypes
import errno
import time
from collections import deque
from enum import IntEnum
from typing import Protocol

import usb.core


class Status(IntEnum):
    """libusb_transfer_status."""

    COMPLETED = 0
    ERROR = 1
    TIMED_OUT = 2
    CANCELLED = 3
    STALL = 4
    NO_DEVICE = 5
    OVERFLOW = 6


class BulkStream(Protocol):
    def submit(self, slot: int) -> None:
        """Start transfer ``slot`` (0 .. count-1)."""

    def poll(self, timeout_s: float) -> list[tuple[int, Status, bytes]]:
        """Completed transfers (slot, status, data), in order; waits up to ``timeout_s``."""

    def clear_halt(self) -> None:
        """Clear a stall of the endpoint."""

    def cancel(self) -> None:
        """Cancel what is in flight; the cancelled transfers still come out of ``poll``, with
        whatever data they had received."""

    @property
    def in_flight(self) -> int:
        """Transfers submitted and not yet returned by ``poll``."""

    def close(self) -> None:
        """Free the transfers (after ``cancel`` and once nothing is in flight)."""


def status_of(error: usb.core.USBError) -> Status:
    """The transfer status a pyusb error stands for."""
    if isinstance(error, usb.core.USBTimeoutError) or error.errno == errno.ETIMEDOUT:
        return Status.TIMED_OUT
    if error.errno == errno.EPIPE:
        return Status.STALL
    if error.errno in (errno.ENODEV, errno.ENOENT, errno.ESHUTDOWN):
        return Status.NO_DEVICE
    if error.errno == errno.EOVERFLOW:
        return Status.OVERFLOW
    return Status.ERROR


class SyncBulkStream:
    """Transfers served one after another with pyusb's synchronous read."""

    def __init__(
        self, device: usb.core.Device, endpoint: int, size: int, timeout_ms: int = 100
    ) -> None:
        self._dev = device
        self._ep = endpoint
        self._size = size
        self._timeout_ms = timeout_ms
        self._pending: deque[int] = deque()

    def submit(self, slot: int) -> None:
        self._pending.append(slot)

    def poll(self, timeout_s: float) -> list[tuple[int, Status, bytes]]:
        if not self._pending:
            time.sleep(timeout_s)
            return []
        slot = self._pending.popleft()
        try:
            data = self._dev.read(self._ep, self._size, self._timeout_ms)
        except usb.core.USBError as e:
            return [(slot, status_of(e), b"")]
        return [(slot, Status.COMPLETED, data.tobytes())]

    def clear_halt(self) -> None:
        self._dev.clear_halt(self._ep)

    def cancel(self) -> None:
        self._pending.clear()

    @property
    def in_flight(self) -> int:
        return len(self._pending)

    def close(self) -> None:
        self._pending.clear()


class _Timeval(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_usec", ctypes.c_long)]


class LibusbBulkStream:
    """Asynchronous libusb bulk transfers (as libcaer keeps them), through pyusb's libusb1.

    Uses pyusb's libusb1 backend internals (its library handle, context and the device
    handle), because pyusb itself only offers synchronous bulk reads."""

    def __init__(self, device: usb.core.Device, endpoint: int, size: int, count: int) -> None:
        from usb.backend import libusb1

        backend = device._ctx.backend
        device._ctx.managed_open()
        self._lib = lib = backend.lib
        self._ctx = backend.ctx
        self._ep = endpoint
        lib.libusb_handle_events_timeout_completed.argtypes = [
            ctypes.c_void_p,
            ctypes.POINTER(_Timeval),
            ctypes.POINTER(ctypes.c_int),
        ]
        lib.libusb_cancel_transfer.argtypes = [ctypes.POINTER(libusb1._libusb_transfer)]
        self._handle = device._ctx.handle.handle
        self._done: deque[tuple[int, Status, bytes]] = deque()
        self._callback = libusb1._libusb_transfer_cb_fn_p(self._on_complete)
        self._in_flight: set[int] = set()
        self._transfers = []
        self._buffers = []
        self._slot_of: dict[int, int] = {}
        for slot in range(count):
            transfer = lib.libusb_alloc_transfer(0)
            buffer = (ctypes.c_ubyte * size)()
            t = transfer.contents
            t.dev_handle = self._handle
            t.endpoint = endpoint
            t.type = 2  # LIBUSB_TRANSFER_TYPE_BULK
            t.timeout = 0  # as libcaer: transfers wait for data as long as it takes
            t.length = size
            t.callback = self._callback
            t.buffer = ctypes.cast(buffer, ctypes.c_void_p)
            t.num_iso_packets = 0
            self._transfers.append(transfer)
            self._buffers.append(buffer)
            self._slot_of[ctypes.addressof(t)] = slot

    def _on_complete(self, transfer_p) -> None:
        # Runs in whichever thread handles libusb events: the reader's poll, or another
        # thread's synchronous control transfer. deque append and popleft are atomic.
        t = transfer_p.contents
        slot = self._slot_of[ctypes.addressof(t)]
        data = ctypes.string_at(self._buffers[slot], t.actual_length)
        self._done.append((slot, Status(t.status), data))
        self._in_flight.discard(slot)

    def submit(self, slot: int) -> None:
        self._in_flight.add(slot)  # before submitting: the callback may come at once
        ret = self._lib.libusb_submit_transfer(self._transfers[slot])
        if ret != 0:  # LIBUSB_ERROR_NO_DEVICE (-4) and others: report as a completion
            self._in_flight.discard(slot)
            self._done.append((slot, Status.NO_DEVICE if ret == -4 else Status.ERROR, b""))

    def poll(self, timeout_s: float) -> list[tuple[int, Status, bytes]]:
        if not self._done:
            tv = _Timeval(int(timeout_s), int((timeout_s % 1) * 1e6))
            self._lib.libusb_handle_events_timeout_completed(self._ctx, ctypes.byref(tv), None)
        done = []
        while self._done:
            done.append(self._done.popleft())
        return done

    def clear_halt(self) -> None:
        self._lib.libusb_clear_halt(self._handle, self._ep)

    def cancel(self) -> None:
        for slot in list(self._in_flight):
            self._lib.libusb_cancel_transfer(self._transfers[slot])

    @property
    def in_flight(self) -> int:
        return len(self._in_flight) + len(self._done)

    def close(self) -> None:
        if self._in_flight:  # never free a transfer libusb still owns
            return
        for transfer in self._transfers:
            self._lib.libusb_free_transfer(transfer)
        self._transfers.clear()
