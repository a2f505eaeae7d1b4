"""The DAVIS346 over pyusb: discovery, version checks, registers, configuration, start and stop.

A device is named by a string: ``usb`` (the first camera), ``usb:SERIAL`` or ``replay:PATH``
(a hardware-replay fixture, see evcap.acquire.replay). The same code drives both: the replay
backend is just another pyusb backend.
"""

from __future__ import annotations

import errno
import time
from dataclasses import dataclass, field
from pathlib import Path

import usb.core
import usb.util

from evcap.acquire import protocol as P
from evcap.acquire.decoder import Geometry
from evcap.acquire.reader import BulkReader
from evcap.acquire.transfers import BulkStream, LibusbBulkStream, SyncBulkStream
from evcap.errors import (
    DeviceError,
    DeviceLostError,
    DeviceNotFoundError,
    DevicePermissionError,
    FirmwareError,
    InputError,
)

MAX_SENSOR_SIDE = 1024  # pixels: the largest DAVIS (DAVIS640) is 640 x 480
UDEV_RULE = (
    "# iniVation cameras (DAVIS346): allow users of the plugdev group, and the logged-in user\n"
    'SUBSYSTEM=="usb", ATTR{idVendor}=="152a", ATTR{idProduct}=="84[0-1]?", '
    'MODE="0660", GROUP="plugdev", TAG+="uaccess"\n'
)
UDEV_PATH = "/etc/udev/rules.d/65-inivation.rules"
UDEV_HINT = (
    f"install the udev rule (evcap devices --udev | sudo tee {UDEV_PATH} && "
    "sudo udevadm control --reload-rules && sudo udevadm trigger), then replug the camera"
)
NO_LIBUSB_HINT = (
    "no libusb library was found for pyusb: `pip install libusb-package` (it "
    "bundles libusb) or install your system's libusb-1.0 (Debian/Ubuntu: "
    "sudo apt install libusb-1.0-0)"
)


def libusb_backend():
    """pyusb's libusb1 backend: the system's libusb, else the one libusb-package bundles."""
    import usb.backend.libusb1

    backend = usb.backend.libusb1.get_backend()
    if backend is None:
        try:
            import libusb_package
        except ImportError:
            libusb_package = None
        if libusb_package is not None:
            backend = libusb_package.get_libusb1_backend()
    if backend is None:
        raise DeviceError(NO_LIBUSB_HINT)
    return backend


@dataclass(frozen=True)
class DeviceSpec:
    kind: str  # "usb" or "replay"
    serial: str | None = None  # usb: which camera
    path: Path | None = None  # replay: the fixture folder
    speed: float | None = None  # replay: multiple of real time (None: as fast as read)

    @classmethod
    def parse(cls, text: str, *, speed: float | None = None) -> DeviceSpec:
        """``speed``: for a replay device, serve it at this multiple of real time."""
        if text == "usb":
            return cls("usb")
        if text.startswith("usb:") and len(text) > 4:
            return cls("usb", serial=text[4:])
        if text.startswith("replay:") and len(text) > 7:
            path = Path(text[7:])
            if not path.is_dir():
                raise InputError(f"replay fixture {path} is not a folder")
            return cls("replay", path=path, speed=speed)
        raise InputError(f"device {text!r}: expected usb, usb:SERIAL or replay:PATH")

    def backend(self):
        if self.kind == "replay":
            from evcap.acquire.replay import ReplayBackend

            return ReplayBackend(self.path, speed=self.speed)
        return libusb_backend()


@dataclass(frozen=True)
class DeviceInfo:
    """What the camera says about itself (read at open)."""

    serial: str
    product: str
    firmware: int
    logic: int
    logic_patch: int
    chip_id: int
    color_filter: str
    is_master: bool
    clocks: P.Clocks
    geometry: Geometry
    capabilities: dict = field(default_factory=dict)

    @property
    def chip(self) -> str:
        return P.CHIP_IDS.get(self.chip_id, f"unknown chip {self.chip_id}")

    @property
    def model(self) -> str:
        return "DAVIS346" if self.color_filter == "MONO" else "Color-DAVIS346"

    def as_attrs(self) -> dict:
        """Session root attributes."""
        return {
            "firmware_version": self.firmware,
            "logic_version": self.logic,
            "logic_patch": self.logic_patch,
            "chip_id": self.chip_id,
            "chip": self.chip,
            "is_timestamp_master": self.is_master,
            "product": self.product,
            "clock_logic_mhz": self.clocks.logic,
            "clock_adc_mhz": self.clocks.adc,
            "clock_usb_mhz": self.clocks.usb,
        }


def _string(dev: usb.core.Device, index: int) -> str:
    """A string descriptor, "" when there is none or it cannot be read."""
    if not index:
        return ""
    try:
        return usb.util.get_string(dev, index) or ""
    except (usb.core.USBError, ValueError):
        return ""


def find(spec: DeviceSpec, backend=None) -> list[usb.core.Device]:
    """The DAVIS346 cameras (VID 0x152A, PID 0x841A) the spec names, unopened."""
    backend = backend or spec.backend()
    try:
        devices = list(
            usb.core.find(
                find_all=True, idVendor=P.VENDOR_ID, idProduct=P.PRODUCT_ID, backend=backend
            )
        )
    except usb.core.NoBackendError:
        raise DeviceError(NO_LIBUSB_HINT) from None
    if spec.serial is not None:
        devices = [d for d in devices if _string(d, d.iSerialNumber)[:8] == spec.serial[:8]]
    return devices


class Davis346:
    """An open DAVIS346. Use ``Davis346.open(spec)``; close it (or use it as a context
    manager) to stop the camera and release the interface."""

    def __init__(self, dev: usb.core.Device, spec: DeviceSpec) -> None:
        self._dev = dev
        self.spec = spec
        self.backend = dev._ctx.backend
        self.streaming = False
        self.reader: BulkReader | None = None
        self._reader_stuck = False
        self.clock_started_us = 0  # host time (Unix us) when the device clock started
        try:
            # Set the configuration only if it differs (setting it again can reset the device).
            try:
                active = dev.get_active_configuration().bConfigurationValue
            except usb.core.USBError:
                active = None
            if active != P.CONFIGURATION:
                dev.set_configuration(P.CONFIGURATION)
            usb.util.claim_interface(dev, P.INTERFACE)
        except usb.core.USBError as e:
            usb.util.dispose_resources(dev)
            raise self._usb_error(e, "open") from None
        try:
            self.info = self._read_info()
        except BaseException:
            self._release()
            raise

    @classmethod
    def open(cls, spec: str | DeviceSpec) -> Davis346:
        spec = DeviceSpec.parse(spec) if isinstance(spec, str) else spec
        devices = find(spec)
        if not devices:
            which = f" with serial {spec.serial}" if spec.serial else ""
            raise DeviceNotFoundError(
                f"no DAVIS346{which} found on USB: check the cable (a USB 3 port), and run "
                "`evcap devices`; on Linux the camera also needs the udev rule "
                "(evcap devices --udev)"
            )
        return cls(devices[0], spec)

    def _usb_error(self, e: usb.core.USBError, doing: str) -> DeviceError:
        if e.errno == errno.EACCES:
            return DevicePermissionError(f"no permission to open the camera: {UDEV_HINT}")
        if e.errno in (errno.ENODEV, errno.ENOENT):
            return DeviceLostError(f"the camera was disconnected ({doing})")
        if e.errno == errno.EBUSY:
            return DeviceError("the camera is in use by another program (close DV or jAER)")
        return DeviceError(f"USB error during {doing}: {e}")

    # -- registers -------------------------------------------------------------------------------

    def read_register(self, module: int, param: int) -> int:
        try:
            data = self._dev.ctrl_transfer(P.VENDOR_IN, P.REQUEST_CONFIG, module, param, 4, 1000)
        except usb.core.USBError as e:
            raise self._usb_error(e, f"reading register {module}.{param}") from None
        if len(data) != 4:
            raise DeviceError(f"short read of register {module}.{param}")
        return int.from_bytes(bytes(data), "big")

    def write_register(self, module: int, param: int, value: int) -> None:
        try:
            n = self._dev.ctrl_transfer(
                P.VENDOR_OUT, P.REQUEST_CONFIG, module, param, value.to_bytes(4, "big"), 1000
            )
        except usb.core.USBError as e:
            raise self._usb_error(e, f"writing register {module}.{param}") from None
        if n != 4:
            raise DeviceError(f"short write of register {module}.{param}")

    def write_registers(self, writes: list[tuple[int, int, int]]) -> None:
        """Several writes in as few requests as the protocol allows (682 entries each)."""
        for i in range(0, len(writes), P.MULTIPLE_MAX_ENTRIES):
            part = writes[i : i + P.MULTIPLE_MAX_ENTRIES]
            data = P.pack_multiple(part)
            try:
                n = self._dev.ctrl_transfer(
                    P.VENDOR_OUT, P.REQUEST_CONFIG_MULTIPLE, len(part), 0, data, 1000
                )
            except usb.core.USBError as e:
                raise self._usb_error(e, "writing registers") from None
            if n != len(data):
                raise DeviceError(f"short write of {len(part)} registers")

    def reset_timestamps(self) -> None:
        """Restart the device clock at 0 (and, on a timestamp master, its slaves')."""
        self.write_registers([(*P.MUX_TIMESTAMP_RESET, 1), (*P.MUX_TIMESTAMP_RESET, 0)])

    def read_counter64(self, module: int, param: int) -> int:
        """A 64-bit statistics counter (high word at param, low at param + 1)."""
        for _ in range(3):
            high = self.read_register(module, param)
            low = self.read_register(module, param + 1)
            if self.read_register(module, param) == high:
                return high << 32 | low
        return high << 32 | low

    def _reg(self, address: tuple[int, int]) -> int:
        return self.read_register(*address)

    # -- open-time checks and information -------------------------------------------------------

    def _read_info(self) -> DeviceInfo:
        dev = self._dev
        firmware = dev.bcdDevice & 0xFF
        if firmware < P.MIN_FIRMWARE:
            raise FirmwareError(
                f"the camera's firmware is version {firmware}; evcap needs {P.MIN_FIRMWARE} or "
                "later: update it with iniVation's DV software (Help > Update firmware)"
            )
        logic = self._reg(P.SYSINFO_LOGIC_VERSION)
        patch = self._reg(P.SYSINFO_LOGIC_PATCH)
        if logic != P.REQUIRED_LOGIC or patch < P.MIN_LOGIC_PATCH:
            raise FirmwareError(
                f"the camera's FPGA logic is version {logic} (patch {patch}); evcap speaks "
                f"logic {P.REQUIRED_LOGIC} (patch {P.MIN_LOGIC_PATCH} or later): update it with "
                "iniVation's DV software"
            )
        deviation = self._reg(P.SYSINFO_CLOCK_DEVIATION) / 1000.0 or 1.0
        clocks = P.Clocks(
            self._reg(P.SYSINFO_LOGIC_CLOCK) * deviation,
            self._reg(P.SYSINFO_ADC_CLOCK) * deviation,
            self._reg(P.SYSINFO_USB_CLOCK) * deviation,
        )
        code = self._reg(P.APS_COLOR_FILTER)
        color_filter = P.COLOR_FILTER_CODES.get(code)
        if color_filter not in ("MONO", "RGBG", "GRGB", "GBGR", "BGRG"):
            raise DeviceError(
                f"the camera reports color filter code {code}, which evcap does "
                "not support (RGBW filters)"
            )
        dvs_o, aps_o, imu_o = (
            self._reg(P.DVS_ORIENTATION),
            self._reg(P.APS_ORIENTATION),
            self._reg(P.IMU_ORIENTATION),
        )
        geometry = Geometry(
            dvs_columns=self._reg(P.DVS_SIZE_COLUMNS),
            dvs_rows=self._reg(P.DVS_SIZE_ROWS),
            dvs_invert_xy=bool(dvs_o & 4),
            aps_columns=self._reg(P.APS_SIZE_COLUMNS),
            aps_rows=self._reg(P.APS_SIZE_ROWS),
            aps_flip_x=bool(aps_o & 2),
            aps_flip_y=bool(aps_o & 1),
            aps_invert_xy=bool(aps_o & 4),
            imu_type=self._reg(P.IMU_TYPE),
            imu_flip=(bool(imu_o & 4), bool(imu_o & 2), bool(imu_o & 1)),
            color_filter=color_filter,
        )
        for what, size, least in (
            ("DVS", (geometry.dvs_columns, geometry.dvs_rows), 1),
            ("APS", (geometry.aps_columns, geometry.aps_rows), 0),
        ):
            if not all(least <= n <= MAX_SENSOR_SIDE for n in size):
                raise DeviceError(
                    f"the camera reports {size[0]} x {size[1]} pixels for its {what} array, "
                    "which no DAVIS has: unplug it and plug it in again; if it persists, its "
                    "logic needs reflashing (iniVation's flashy)"
                )
        capabilities = {name: self._reg(addr) for name, addr in P.DEVICE_CAPABILITIES.items()}
        capabilities["mux_statistics"] = self._reg(P.MUX_HAS_STATISTICS)
        capabilities["dvs_statistics"] = self._reg(P.DVS_HAS_STATISTICS)
        return DeviceInfo(
            serial=_string(dev, dev.iSerialNumber),
            product=_string(dev, dev.iProduct),
            firmware=firmware,
            logic=logic,
            logic_patch=patch,
            chip_id=self._reg(P.SYSINFO_CHIP_ID),
            color_filter=color_filter,
            is_master=bool(self._reg(P.SYSINFO_IS_MASTER)),
            clocks=clocks,
            geometry=geometry,
            capabilities=capabilities,
        )

    # -- configuration, start and stop -------------------------------------------------------------

    def configure(self, biases: dict[str, int], settings: P.Settings) -> None:
        """Send the full configuration (biases, chip, FPGA modules), as libcaer's default config."""
        # One write per register, in libcaer's order (it sends its default config this way).
        g = self.info.geometry
        for module, param, value in P.default_config(
            self.info.capabilities,
            self.info.clocks,
            biases,
            settings,
            dvs_size=(g.dvs_columns, g.dvs_rows),
            aps_size=(g.aps_width, g.aps_height),
        ):
            self.write_register(module, param, value)

    def set_bias(self, name: str, code: int) -> None:
        """Change one bias now (the camera may be running)."""
        if name not in P.BIASES:
            raise InputError(f"unknown bias {name!r}")
        self.write_register(P.Module.BIAS, P.BIASES[name].param, code)

    def start(
        self, *, aps: bool = True, imu: bool = True, transfers: int = 8, transfer_size: int = 8192
    ) -> BulkReader:
        """The start sequence (docs/davis346-protocol.md section 2.7); returns the running
        reader."""
        for address in P.STOP_SEQUENCE:
            self.write_register(*address, 0)
        time.sleep(0.01)  # let the FPGA buffers drain
        try:
            self._dev.clear_halt(P.DATA_ENDPOINT)
        except usb.core.USBError as e:
            raise self._usb_error(e, "clearing the endpoint") from None
        self.reader = BulkReader(self._bulk_stream(transfer_size, transfers), transfers)
        self.reader.start()
        self.streaming = True  # from here on, stop() undoes what was started
        try:
            self._run(aps, imu)
        except BaseException:
            self.stop()
            raise
        return self.reader

    def _run(self, aps: bool, imu: bool) -> None:
        self.write_register(*P.MUX_RUN_CHIP, 1)
        self._sleep(0.2)  # biases settle
        self.write_register(*P.USB_RUN, 1)
        self.write_register(*P.MUX_TIMESTAMP_RUN, 1)
        self.clock_started_us = time.time_ns() // 1000  # the device clock starts now
        self.write_register(*P.MUX_RUN, 1)
        self._sleep(0.05)
        skip = set()
        if not aps:
            skip.add(P.APS_RUN)
        if not imu:
            skip |= {P.IMU_RUN_ACCEL, P.IMU_RUN_GYRO, P.IMU_RUN_TEMPERATURE}
        for address in P.RUN_SEQUENCE:
            if address not in skip:
                self.write_register(*address, 1)

    def _sleep(self, seconds: float) -> None:
        if self.spec.kind == "usb":  # the replay camera needs no settling
            time.sleep(seconds)

    def _bulk_stream(self, size: int, count: int) -> BulkStream:
        from usb.backend import libusb1

        if isinstance(self.backend, libusb1._LibUSB):
            return LibusbBulkStream(self._dev, P.DATA_ENDPOINT, size, count)
        return SyncBulkStream(self._dev, P.DATA_ENDPOINT, size)

    def stop(self) -> None:
        """The stop sequence; then the reader takes in what is still in flight and ends."""
        if not self.streaming:
            return
        self.streaming = False
        try:
            for address in P.STOP_SEQUENCE:
                self.write_register(*address, 0)
            self._sleep(0.01)  # the device flushes its last short packet
        except DeviceError:
            pass  # a lost camera cannot be stopped; the reader has ended already
        if self.reader is not None and not self.reader.stop():
            self._reader_stuck = True  # its transfers may still be in flight: keep them

    def dropped_counters(self) -> dict[str, int]:
        """The device-side dropped-event counters (statistics registers)."""
        out = {}
        if self.info.capabilities.get("mux_statistics"):
            out["mux_dvs_dropped"] = self.read_counter64(*P.MUX_STAT_DVS_DROPPED)
            out["mux_extinput_dropped"] = self.read_counter64(*P.MUX_STAT_EXTINPUT_DROPPED)
        if self.info.capabilities.get("dvs_statistics"):
            out["dvs_dropped"] = self.read_counter64(*P.DVS_STAT_EVENTS_DROPPED)
        return out

    @property
    def stream_exhausted(self) -> bool:
        """A replay camera that has sent all of its fixture (a real camera never is)."""
        return bool(getattr(self.backend, "exhausted", False))

    def close(self) -> None:
        try:
            self.stop()
        finally:
            self._release()

    def _release(self) -> None:
        if self._reader_stuck:
            return
        try:
            usb.util.release_interface(self._dev, P.INTERFACE)
        except usb.core.USBError:
            pass  # a vanished camera has nothing to release
        usb.util.dispose_resources(self._dev)

    def __enter__(self) -> Davis346:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
