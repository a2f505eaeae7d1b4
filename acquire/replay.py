"""A pyusb backend that emulates a DAVIS346 from a hardware-replay fixture folder.

The driver finds it with ``usb.core.find(backend=ReplayBackend(path))`` and talks to it exactly
as to the camera: it enumerates with the fixture's descriptor, answers the vendor requests from
its register file (registers the fixture does not list report what a real DAVIS346 reports;
writes are stored and read back), streams bulk.bin in the recorded transfer sizes once the
camera's USB output runs, and plays the faults the fixture lists. When bulk.bin is exhausted the
camera goes idle (reads time out).

Fixture format (hw-fixtures/README.md):
- ``device.toml``: ``[usb]`` idVendor, idProduct, bcdDevice, serial, product;
  ``[registers]`` "module.param" = value.
- ``bulk.bin``: the bytes of bulk-IN endpoint 0x82.
- ``transfers.u32`` (optional): little-endian uint32 sizes of the successive transfers
  (default 8192 bytes each).
- ``faults.toml`` (optional): ``[[fault]]`` tables with ``at_byte`` and ``kind`` =
  "disconnect", "timeout" (with ``count``) or "stall".
"""

from __future__ import annotations

import array
import errno
import mmap
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import usb.backend
import usb.core

from evcap.acquire import protocol as P
from evcap.acquire.decoder import MAX_WRAPS_PER_WORD
from evcap.errors import InputError
from evcap.toml_file import Table, read_toml

DEFAULT_TRANSFER = 8192
RELEASE_BYTES = 16 << 20  # served pages of bulk.bin are given back in steps this big (page-aligned)
IDLE_WAIT_S = 0.005  # how long a read that times out blocks (a real one waits its timeout)
# libusb error codes, as pyusb's libusb1 backend reports them.
_LIBUSB_ERROR_TIMEOUT = -7
_LIBUSB_ERROR_PIPE = -9
_LIBUSB_ERROR_NO_DEVICE = -4


@dataclass(frozen=True)
class Fault:
    at_byte: int  # offset in bulk.bin where the fault happens
    kind: str  # "disconnect", "timeout" or "stall"
    count: int = 1  # timeouts: how many reads time out


@dataclass
class Fixture:
    """A fixture folder, loaded."""

    path: Path
    usb: dict
    registers: dict[tuple[int, int], int]
    bulk: bytes | mmap.mmap  # mapped, not read: a long fixture is no part of a recorder's memory
    transfers: np.ndarray
    faults: list[Fault]

    @classmethod
    def load(cls, path: str | Path) -> Fixture:
        path = Path(path)
        if not (path / "device.toml").is_file() or not (path / "bulk.bin").is_file():
            raise InputError(f"{path} is not a replay fixture (needs device.toml and bulk.bin)")
        where = path / "device.toml"
        device = Table(read_toml(where, "fixture device"), str(where))
        usb_t = device.table("usb")
        usb_desc = {k: usb_t.get(k, int, required=True) for k in ("idVendor", "idProduct")}
        usb_desc["bcdDevice"] = usb_t.get("bcdDevice", int, required=True)
        usb_desc |= {k: usb_t.get(k, str, required=True) for k in ("serial", "product")}
        usb_t.done()
        registers = {}
        for key, value in device.get("registers", dict, {}).items():
            module, _, param = key.partition(".")
            if (
                not (module.isdigit() and param.isdigit())
                or not isinstance(value, int)
                or not 0 <= value < 2**32
            ):
                raise InputError(f"{where}: bad register {key!r} = {value!r}")
            registers[(int(module), int(param))] = value
        device.done()
        transfers = np.zeros(0, np.uint32)
        if (path / "transfers.u32").is_file():
            transfers = np.fromfile(path / "transfers.u32", dtype="<u4")
            if transfers.size and int(transfers.min()) == 0:
                raise InputError(f"{path / 'transfers.u32'}: transfer sizes must be positive")
        faults = []
        if (path / "faults.toml").is_file():
            where = path / "faults.toml"
            doc = Table(read_toml(where, "fixture faults"), str(where))
            for i, f in enumerate(doc.get("fault", list, [])):
                t = Table(f if isinstance(f, dict) else {}, f"{where} [[fault]] #{i + 1}")
                kind = t.get("kind", str, required=True)
                if kind not in ("disconnect", "timeout", "stall"):
                    raise InputError(f"{t.where}: unknown fault kind {kind!r}")
                at_byte, count = t.get("at_byte", int, required=True), t.get("count", int, 1)
                if at_byte < 0 or count < 1:
                    raise InputError(f"{t.where}: at_byte must be 0 or more and count 1 or more")
                t.done()
                faults.append(Fault(at_byte, kind, count))
            doc.done()
        faults.sort(key=lambda f: f.at_byte)
        return cls(path, usb_desc, registers, _map(path / "bulk.bin"), transfers, faults)


def _map(path: Path) -> bytes | mmap.mmap:
    with path.open("rb") as f:
        if f.seek(0, 2) == 0:
            return b""  # an empty file cannot be mapped
        return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)


def stream_times(bulk: bytes) -> np.ndarray:
    """The stream's time (us, host-continuous) at each of its words: the last timestamp
    before it, with wraps counted (as the decoder counts them: an implausible jump as one wrap)
    and timestamp resets continuing from the time they came."""
    w = np.frombuffer(bulk, "<u2", count=len(bulk) // 2).astype(np.int64)
    is_ts = (w & 0x8000) != 0
    code = (w >> 12) & 7
    is_wrap = ~is_ts & (code == 7)
    is_reset = ~is_ts & (code == 0) & ((w & 0xFFF) == 1)
    wraps = np.where((w & 0xFFF) > MAX_WRAPS_PER_WORD, 1, w & 0xFFF)
    times = np.zeros(w.size, np.int64)
    base = 0
    bounds = [0, *np.flatnonzero(is_reset).tolist(), w.size]
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):  # one segment per reset
        wrap = np.cumsum(np.where(is_wrap[a:b], wraps[a:b] * 0x8000, 0))
        value = np.where(is_ts[a:b], wrap + (w[a:b] & 0x7FFF), np.where(is_wrap[a:b], wrap, 0))
        times[a:b] = base + np.maximum.accumulate(value) if b > a else 0
        base = int(times[b - 1]) if b > a else base
    return times


def _usb_error(code: int, err: int, text: str) -> usb.core.USBError:
    if code == _LIBUSB_ERROR_TIMEOUT:
        return usb.core.USBTimeoutError(text, code, err)
    return usb.core.USBError(text, code, err)


def _no_device() -> usb.core.USBError:
    return _usb_error(
        _LIBUSB_ERROR_NO_DEVICE, errno.ENODEV, "No such device (it may have been disconnected)"
    )


class ReplayBackend(usb.backend.IBackend):
    """The emulated camera. One device; thread-safe (bulk reads and control transfers may come
    from different threads, as with libusb)."""

    def __init__(self, fixture: str | Path | Fixture, speed: float | None = None) -> None:
        """``speed``: serve the stream at this multiple of its own time (1 = as the camera
        sent it, by the timestamps in it); None: as fast as the host reads."""
        self.fixture = fixture if isinstance(fixture, Fixture) else Fixture.load(fixture)
        if speed is not None and speed <= 0:
            raise InputError(f"replay speed must be positive, got {speed}")
        self.speed = speed
        self._times = stream_times(self.fixture.bulk) if speed is not None else np.zeros(0)
        self._wall_start: float | None = None
        self._t_start = 0
        self.registers: dict[tuple[int, int], int] = {
            **P.DAVIS346_READ_ONLY,
            **self.fixture.registers,
        }
        self.writes: list[tuple[int, int, int]] = []  # every register write, in order
        self._lock = threading.Lock()
        self._pos = 0  # bytes of bulk.bin served
        self._released = 0  # bytes of bulk.bin whose pages were given back
        self._transfer = 0  # index into transfers.u32
        self._faults = list(self.fixture.faults)
        self._timeouts_left = 0
        self._halted = False
        self.gone = False  # disconnected
        self.clear_halt_calls = 0

    # -- state the driver and tests can look at ---------------------------------------------

    @property
    def exhausted(self) -> bool:
        """bulk.bin has been served entirely (the camera is idle from now on)."""
        return self._pos >= len(self.fixture.bulk) and not self._faults and not self._timeouts_left

    @property
    def bytes_served(self) -> int:
        return self._pos

    def _check_present(self) -> None:
        if self.gone:
            raise _no_device()

    # -- enumeration and descriptors ---------------------------------------------------------

    def enumerate_devices(self):
        if not self.gone:
            yield "replay"

    def get_device_descriptor(self, dev):
        u = self.fixture.usb
        return SimpleNamespace(
            bLength=18,
            bDescriptorType=1,
            bcdUSB=0x0300,
            bDeviceClass=0,
            bDeviceSubClass=0,
            bDeviceProtocol=0,
            bMaxPacketSize0=9,
            idVendor=u["idVendor"],
            idProduct=u["idProduct"],
            bcdDevice=u["bcdDevice"],
            iManufacturer=1,
            iProduct=2,
            iSerialNumber=3,
            bNumConfigurations=1,
            bus=1,
            address=1,
            port_number=1,
            port_numbers=(1,),
            speed=5,
        )

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError(config)
        return SimpleNamespace(
            bLength=9,
            bDescriptorType=2,
            wTotalLength=39,
            bNumInterfaces=1,
            bConfigurationValue=P.CONFIGURATION,
            iConfiguration=0,
            bmAttributes=0x80,
            bMaxPower=112,
            extra_descriptors=[],
        )

    def get_interface_descriptor(self, dev, intf, alt, config):
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError((intf, alt, config))
        return SimpleNamespace(
            bLength=9,
            bDescriptorType=4,
            bInterfaceNumber=P.INTERFACE,
            bAlternateSetting=0,
            bNumEndpoints=2,
            bInterfaceClass=0xFF,
            bInterfaceSubClass=0,
            bInterfaceProtocol=0,
            iInterface=0,
            extra_descriptors=[],
        )

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        if (intf, alt, config) != (0, 0, 0) or ep not in (0, 1):
            raise IndexError((ep, intf, alt, config))
        address, attributes, size = (
            (P.DEBUG_ENDPOINT, 0x03, 64) if ep == 0 else (P.DATA_ENDPOINT, 0x02, 1024)
        )
        return SimpleNamespace(
            bLength=7,
            bDescriptorType=5,
            bEndpointAddress=address,
            bmAttributes=attributes,
            wMaxPacketSize=size,
            bInterval=0,
            bRefresh=0,
            bSynchAddress=0,
            extra_descriptors=[],
        )

    # -- handles -------------------------------------------------------------------------------

    def open_device(self, dev):
        self._check_present()
        return "handle"

    def close_device(self, dev_handle):
        pass

    def get_configuration(self, dev_handle):
        self._check_present()
        return P.CONFIGURATION

    def set_configuration(self, dev_handle, config_value):
        self._check_present()

    def claim_interface(self, dev_handle, intf):
        self._check_present()

    def release_interface(self, dev_handle, intf):
        pass

    def is_kernel_driver_active(self, dev_handle, intf):
        return False

    def clear_halt(self, dev_handle, ep):
        self._check_present()
        with self._lock:
            self._halted = False
            self.clear_halt_calls += 1

    # -- control transfers: strings and the register file -------------------------------------

    def _string(self, index: int) -> bytes:
        if index == 0:
            return bytes([4, 3, 0x09, 0x04])  # supported language: en-US
        u = self.fixture.usb
        text = {1: "iniVation", 2: u["product"], 3: u["serial"]}.get(index)
        if text is None:
            raise _usb_error(_LIBUSB_ERROR_PIPE, errno.EPIPE, "Pipe error")
        encoded = text.encode("utf-16-le")
        return bytes([2 + len(encoded), 3]) + encoded

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        self._check_present()
        if bmRequestType == 0x80 and bRequest == 6 and wValue >> 8 == 3:  # GET_DESCRIPTOR string
            reply = self._string(wValue & 0xFF)[: len(data)]
            data[: len(reply)] = array.array("B", reply)
            return len(reply)
        if bmRequestType == P.VENDOR_IN and bRequest == P.REQUEST_CONFIG and len(data) == 4:
            with self._lock:
                value = self.registers.get((wValue, wIndex), 0)
            data[:4] = array.array("B", value.to_bytes(4, "big"))
            return 4
        if bmRequestType == P.VENDOR_OUT and bRequest == P.REQUEST_CONFIG and len(data) == 4:
            self._write(wValue, wIndex, int.from_bytes(bytes(data), "big"))
            return 4
        if bmRequestType == P.VENDOR_OUT and bRequest == P.REQUEST_CONFIG_MULTIPLE:
            raw = bytes(data)
            if len(raw) != 6 * wValue:
                raise _usb_error(_LIBUSB_ERROR_PIPE, errno.EPIPE, "Pipe error")
            for i in range(wValue):
                entry = raw[6 * i : 6 * i + 6]
                self._write(entry[0], entry[1], int.from_bytes(entry[2:], "big"))
            return len(raw)
        raise _usb_error(_LIBUSB_ERROR_PIPE, errno.EPIPE, "Pipe error")  # a device stalls

    def _write(self, module: int, param: int, value: int) -> None:
        if module == P.Module.SYSINFO:
            return  # read-only
        with self._lock:
            self.registers[(module, param)] = value
            self.writes.append((module, param, value))

    # -- the bulk stream ------------------------------------------------------------------------

    def _streaming(self) -> bool:
        r = self.registers
        return bool(r.get(P.USB_RUN, 0) and r.get(P.MUX_RUN, 0))

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        self._check_present()
        try:
            return self._bulk_read(ep, buff, timeout)
        except usb.core.USBTimeoutError:
            time.sleep(min(IDLE_WAIT_S, timeout / 1000))
            raise

    def _wait_for(self, end: int, timeout_ms: int) -> None:
        """With a speed, hold the bytes up to ``end`` until their time has come."""
        if self.speed is None:
            return
        t = self._times[(end - 1) // 2] if self._times.size else 0
        now = time.monotonic()
        if self._wall_start is None:
            self._wall_start, self._t_start = now, t
        wait = self._wall_start + (t - self._t_start) / 1e6 / self.speed - now
        if wait > timeout_ms / 1000:
            time.sleep(timeout_ms / 1000)
            raise _usb_error(_LIBUSB_ERROR_TIMEOUT, errno.ETIMEDOUT, "Operation timed out")
        if wait > 0:
            time.sleep(wait)

    def _bulk_read(self, ep, buff, timeout_ms) -> int:
        with self._lock:
            if ep != P.DATA_ENDPOINT:
                raise _usb_error(_LIBUSB_ERROR_TIMEOUT, errno.ETIMEDOUT, "Operation timed out")
            # Faults at or before this byte play in order, each to its end (the timeouts
            # used up, the stall cleared) before the next.
            while True:
                if self.gone:
                    raise _no_device()
                if self._halted:
                    raise _usb_error(_LIBUSB_ERROR_PIPE, errno.EPIPE, "Pipe error")
                if self._timeouts_left:
                    self._timeouts_left -= 1
                    raise _usb_error(_LIBUSB_ERROR_TIMEOUT, errno.ETIMEDOUT, "Operation timed out")
                if not (self._faults and self._faults[0].at_byte <= self._pos):
                    break
                fault = self._faults.pop(0)
                if fault.kind == "disconnect":
                    self.gone = True
                elif fault.kind == "timeout":
                    self._timeouts_left = fault.count
                else:
                    self._halted = True
            bulk = self.fixture.bulk
            if not self._streaming() or self._pos >= len(bulk):
                raise _usb_error(_LIBUSB_ERROR_TIMEOUT, errno.ETIMEDOUT, "Operation timed out")
            t = self.fixture.transfers
            size = int(t[self._transfer]) if self._transfer < t.size else DEFAULT_TRANSFER
            self._transfer += 1
            end = min(self._pos + size, self._pos + len(buff), len(bulk))
            if self._faults:  # stop at the next fault (it fires on the next read)
                end = min(end, self._faults[0].at_byte)
        # Wait for the data's time (with a speed) without holding the lock: control requests
        # from other threads go on meanwhile. Only this thread moves the stream on.
        try:
            self._wait_for(end, timeout_ms)
        except usb.core.USBTimeoutError:
            with self._lock:
                self._transfer -= 1  # this transfer comes again on the next read
            raise
        with self._lock:
            n = end - self._pos
            buff[:n] = array.array("B", bulk[self._pos : end])
            self._pos = end
            self._release_served()
            return n

    def _release_served(self) -> None:
        """Unmap the pages of bulk.bin already served: a camera's data is no part of the
        memory of the process that records it, and a replay should measure as one."""
        bulk = self.fixture.bulk
        done = self._pos - self._pos % RELEASE_BYTES
        if isinstance(bulk, mmap.mmap) and done > self._released:
            bulk.madvise(mmap.MADV_DONTNEED, self._released, done - self._released)
            self._released = done
