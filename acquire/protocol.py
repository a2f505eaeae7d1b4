"""The DAVIS346 host protocol: USB identity, vendor requests, register map, bias codes, and the
default configuration and start/stop sequences (docs/davis346-protocol.md sections 1 and 2, from
libcaer 3.3.9 and 3.3.15, jAER and neuromorphic-drivers).

Everything here is data and pure functions; evcap.acquire.device sends it over USB.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

VENDOR_ID = 0x152A
PRODUCT_ID = 0x841A  # DAVIS FX3 (the DAVIS346 is an FX3 device)
DATA_ENDPOINT = 0x82  # bulk IN: the event stream
DEBUG_ENDPOINT = 0x81  # interrupt IN: FX3 debug messages
INTERFACE = 0
CONFIGURATION = 1

MIN_FIRMWARE = 6  # low byte of bcdDevice
REQUIRED_LOGIC = 18  # SYSINFO LOGIC_VERSION
MIN_LOGIC_PATCH = 1  # SYSINFO LOGIC_PATCH

REQUEST_CONFIG = 0xBF  # one register: wValue = module, wIndex = param, 4 bytes big-endian
REQUEST_CONFIG_MULTIPLE = 0xC2  # wValue = N entries of [module u8][param u8][value u32 BE]
MULTIPLE_MAX_ENTRIES = 682  # 6 * 682 <= 4096 bytes per request, as jAER splits them
VENDOR_OUT = 0x40
VENDOR_IN = 0xC0


class Module(IntEnum):
    MUX = 0
    DVS = 1
    APS = 2
    IMU = 3
    EXTINPUT = 4
    BIAS = 5  # params < 128: biases; params >= 128: the chip's shift register
    SYSINFO = 6
    USB = 9


# (module, param) of the registers the driver uses by name.
MUX_RUN = (Module.MUX, 0)
MUX_TIMESTAMP_RUN = (Module.MUX, 1)
MUX_TIMESTAMP_RESET = (Module.MUX, 2)
MUX_RUN_CHIP = (Module.MUX, 3)
MUX_DROP_EXTINPUT_ON_STALL = (Module.MUX, 4)
MUX_DROP_DVS_ON_STALL = (Module.MUX, 5)
MUX_HAS_STATISTICS = (Module.MUX, 80)
MUX_STAT_EXTINPUT_DROPPED = (Module.MUX, 81)  # 64-bit: 81 high, 82 low
MUX_STAT_DVS_DROPPED = (Module.MUX, 83)  # 64-bit: 83 high, 84 low
DVS_SIZE_COLUMNS = (Module.DVS, 0)
DVS_SIZE_ROWS = (Module.DVS, 1)
DVS_ORIENTATION = (Module.DVS, 2)
DVS_RUN = (Module.DVS, 3)
DVS_HAS_PIXEL_FILTER = (Module.DVS, 10)
DVS_HAS_BA_FILTER = (Module.DVS, 30)
DVS_HAS_ROI_FILTER = (Module.DVS, 40)
DVS_HAS_SKIP_FILTER = (Module.DVS, 50)
DVS_HAS_POLARITY_FILTER = (Module.DVS, 60)
DVS_HAS_STATISTICS = (Module.DVS, 80)
DVS_STAT_EVENTS_DROPPED = (Module.DVS, 85)  # 64-bit
APS_SIZE_COLUMNS = (Module.APS, 0)
APS_SIZE_ROWS = (Module.APS, 1)
APS_ORIENTATION = (Module.APS, 2)
APS_COLOR_FILTER = (Module.APS, 3)
APS_RUN = (Module.APS, 4)
APS_HAS_GLOBAL_SHUTTER = (Module.APS, 6)
APS_EXPOSURE = (Module.APS, 12)
APS_FRAME_INTERVAL = (Module.APS, 13)
IMU_TYPE = (Module.IMU, 0)
IMU_ORIENTATION = (Module.IMU, 1)
IMU_RUN_ACCEL = (Module.IMU, 2)
IMU_RUN_GYRO = (Module.IMU, 3)
IMU_RUN_TEMPERATURE = (Module.IMU, 4)
IMU_ACCEL_FULL_SCALE = (Module.IMU, 7)
IMU_GYRO_FULL_SCALE = (Module.IMU, 10)
EXTINPUT_RUN_DETECTOR = (Module.EXTINPUT, 0)
EXTINPUT_HAS_GENERATOR = (Module.EXTINPUT, 10)
SYSINFO_LOGIC_VERSION = (Module.SYSINFO, 0)
SYSINFO_CHIP_ID = (Module.SYSINFO, 1)
SYSINFO_IS_MASTER = (Module.SYSINFO, 2)
SYSINFO_LOGIC_CLOCK = (Module.SYSINFO, 3)
SYSINFO_ADC_CLOCK = (Module.SYSINFO, 4)
SYSINFO_USB_CLOCK = (Module.SYSINFO, 5)
SYSINFO_CLOCK_DEVIATION = (Module.SYSINFO, 6)
SYSINFO_LOGIC_PATCH = (Module.SYSINFO, 7)
USB_RUN = (Module.USB, 0)
USB_EARLY_PACKET_DELAY = (Module.USB, 1)

CHIP_IDS = {4: "DAVIS346A", 5: "DAVIS346B", 9: "DAVIS346C (BSI)"}
COLOR_FILTER_CODES = {
    0: "MONO",
    1: "RGBG",
    2: "GRGB",
    3: "GBGR",
    4: "BGRG",
    5: "RGBW",
    6: "GRWB",
    7: "WBGR",
    8: "BWRG",
}
IMU_TYPES = {0: "none", 1: "InvenSense MPU-6050/6150", 2: "InvenSense MPU-9250"}

# What a DAVIS346 (logic 18) reports from its read-only registers. The replay backend answers
# these for registers a fixture does not list. The clock values are UNCONFIRMED on hardware
# (jAER's fallbacks: logic 90 MHz, ADC 30 MHz; libcaer's old FX3 USB clock: 80 MHz).
DAVIS346_READ_ONLY = {
    SYSINFO_LOGIC_VERSION: 18,
    SYSINFO_CHIP_ID: 5,
    SYSINFO_IS_MASTER: 1,
    SYSINFO_LOGIC_CLOCK: 90,
    SYSINFO_ADC_CLOCK: 30,
    SYSINFO_USB_CLOCK: 80,
    SYSINFO_CLOCK_DEVIATION: 1000,
    SYSINFO_LOGIC_PATCH: 1,
    MUX_HAS_STATISTICS: 1,
    DVS_SIZE_COLUMNS: 346,
    DVS_SIZE_ROWS: 260,
    DVS_ORIENTATION: 0,
    DVS_HAS_PIXEL_FILTER: 1,
    DVS_HAS_BA_FILTER: 1,
    DVS_HAS_ROI_FILTER: 1,
    DVS_HAS_SKIP_FILTER: 1,
    DVS_HAS_POLARITY_FILTER: 1,
    DVS_HAS_STATISTICS: 1,
    APS_SIZE_COLUMNS: 346,
    APS_SIZE_ROWS: 260,
    APS_ORIENTATION: 0,
    APS_COLOR_FILTER: 0,
    APS_HAS_GLOBAL_SHUTTER: 1,
    IMU_TYPE: 1,
    IMU_ORIENTATION: 0,
    EXTINPUT_HAS_GENERATOR: 1,
}


# -- bias encodings (the 16-bit codes written to module 5) ----------------------------------

COARSE_CURRENTS_PA = (11.0, 94.0, 756.0, 6054.0, 48437.0, 387500.0, 3.1e6, 24.8e6)


def vdac_code(voltage: int, current: int) -> int:
    """VDAC bias: voltage 0..63 (1/64 of 3.3 V), current 0..7."""
    _check_range("VDAC voltage", voltage, 63)
    _check_range("VDAC current", current, 7)
    return voltage | current << 6


def coarse_fine_code(
    coarse: int,
    fine: int,
    *,
    n_type: bool,
    enabled: bool = True,
    cascode: bool = False,
    low_current: bool = False,
) -> int:
    """Coarse-fine bias: coarse 0..7, fine 0..255; current about C[coarse] * fine / 255."""
    _check_range("coarse", coarse, 7)
    _check_range("fine", fine, 255)
    flags = enabled | n_type << 1 | (not cascode) << 2 | (not low_current) << 3
    return flags | fine << 4 | coarse << 12


def shifted_source_code(ref: int, reg: int, *, mode: int = 0, voltage_level: int = 0) -> int:
    """Shifted-source bias: ref and reg 0..63; mode 0 shifted source, 1 Hi-Z, 2 tied to rail;
    voltage level 0 split gate, 1 single diode, 2 double diode."""
    _check_range("ref", ref, 63)
    _check_range("reg", reg, 63)
    _check_range("mode", mode, 2)
    _check_range("voltage_level", voltage_level, 2)
    return mode | voltage_level << 2 | ref << 4 | reg << 10


def _check_range(name: str, value: int, top: int) -> None:
    from evcap.errors import InputError

    if not isinstance(value, int) or not 0 <= value <= top:
        raise InputError(f"bias {name} must be an integer in 0..{top}, got {value!r}")


@dataclass(frozen=True)
class Bias:
    """A named DAVIS346 bias and how it is encoded."""

    param: int  # module 5 parameter address
    kind: str  # "vdac", "coarse_fine" or "shifted_source"
    n_type: bool = True  # coarse-fine: N-type (else P-type)
    default: dict | None = None  # the vendor default, as keyword arguments of the encoder

    def code(self, **setting: int | bool) -> int:
        if self.kind == "vdac":
            return vdac_code(**setting)
        if self.kind == "shifted_source":
            return shifted_source_code(**setting)
        return coarse_fine_code(n_type=self.n_type, **setting)


def _cf(param: int, coarse: int, fine: int, n_type: bool = True, **flags: bool) -> Bias:
    return Bias(param, "coarse_fine", n_type, {"coarse": coarse, "fine": fine, **flags})


# libcaer's default DAVIS346 biases (docs/davis346-protocol.md section 2.5), in the order they are
# sent.
BIASES: dict[str, Bias] = {
    "ApsOverflowLevel": Bias(0, "vdac", default={"voltage": 27, "current": 6}),
    "ApsCas": Bias(1, "vdac", default={"voltage": 21, "current": 6}),
    "AdcRefHigh": Bias(2, "vdac", default={"voltage": 32, "current": 7}),
    "AdcRefLow": Bias(3, "vdac", default={"voltage": 1, "current": 7}),
    "AdcTestVoltage": Bias(4, "vdac", default={"voltage": 21, "current": 7}),
    "LocalBufBn": _cf(8, 5, 164),
    "PadFollBn": _cf(9, 7, 215, enabled=False),
    "DiffBn": _cf(10, 4, 39),
    "OnBn": _cf(11, 5, 255),
    "OffBn": _cf(12, 4, 1),
    "PixInvBn": _cf(13, 6, 144),
    "PrBp": _cf(14, 2, 58, n_type=False),
    "PrSFBp": _cf(15, 1, 16, n_type=False),
    "RefrBp": _cf(16, 4, 25, n_type=False),
    "ReadoutBufBp": _cf(17, 6, 20, n_type=False),
    "APSROSFBn": _cf(18, 6, 219),
    "ADCCompBp": _cf(19, 5, 20, n_type=False),
    "ColSelLowBn": _cf(20, 0, 1),
    "DACBufBp": _cf(21, 6, 60, n_type=False),
    "LcolTimeoutBn": _cf(22, 5, 49),
    "AEPdBn": _cf(23, 6, 91),
    "AEPuXBp": _cf(24, 4, 80, n_type=False),
    "AEPuYBp": _cf(25, 7, 152, n_type=False),
    "IFRefrBn": _cf(26, 5, 255),
    "IFThrBn": _cf(27, 5, 255),
    "BiasBuffer": _cf(34, 5, 254),
    "SSP": Bias(35, "shifted_source", default={"ref": 1, "reg": 33}),
    "SSN": Bias(36, "shifted_source", default={"ref": 1, "reg": 33}),
}


def describe_bias(name: str, code: int) -> str:
    """A bias code in words, e.g. "N 5/255" (coarse/fine), "VDAC 21/6", "SS 1/33"."""
    kind = BIASES[name].kind
    if kind == "vdac":
        return f"VDAC {code & 63}/{code >> 6 & 7}"
    if kind == "shifted_source":
        return f"SS {code >> 4 & 63}/{code >> 10 & 63}"
    sex = "N" if code & 2 else "P"
    extra = (
        ("" if code & 1 else " off")
        + ("" if code & 4 else " cascode")
        + ("" if code & 8 else " low")
    )
    return f"{sex} {code >> 12 & 7}/{code >> 4 & 0xFF}{extra}"


def parse_bias(name: str, text: str, current: int) -> int:
    """A new code for bias ``name`` from what a user typed: two numbers (coarse fine,
    voltage current, or ref reg; a coarse-fine bias keeps its other flags), or a raw code."""
    from evcap.errors import InputError

    if name not in BIASES:
        raise InputError(f"unknown bias {name!r}")
    parts = text.replace(",", " ").replace("/", " ").split()
    try:
        numbers = [int(p, 0) for p in parts]
    except ValueError:
        raise InputError(f"{text!r}: expected two numbers (e.g. 5 255) or a code") from None
    if len(numbers) == 1:
        if not 0 <= numbers[0] <= 0xFFFF:
            raise InputError(f"bias code {numbers[0]} is not a 16-bit value")
        return numbers[0]
    if len(numbers) != 2:
        raise InputError(f"{text!r}: expected two numbers (e.g. 5 255) or a code")
    a, b = numbers
    bias = BIASES[name]
    if bias.kind == "vdac":
        return vdac_code(a, b)
    if bias.kind == "shifted_source":
        return shifted_source_code(a, b, mode=current & 3, voltage_level=current >> 2 & 3)
    return (current & 0xF) | coarse_fine_code(a, b, n_type=bias.n_type) & ~0xF


def default_bias_codes() -> dict[str, int]:
    return {name: bias.code(**bias.default) for name, bias in BIASES.items()}


# -- the chip shift register (module 5, params >= 128), in the order libcaer sends it ---------

CHIP_DEFAULTS = [
    (128, 0),
    (129, 0),
    (130, 0),
    (131, 0),
    (132, 0),
    (133, 0),
    (134, 0),
    (135, 0),
    (136, 1),
    (137, 0),
    (138, 1),
    (140, 0),
    (141, 0),
    (143, 1),
    (144, 0),
]
CHIP_GLOBAL_SHUTTER = 142


@dataclass(frozen=True)
class Clocks:
    """The device's clocks in MHz (SYSINFO value times CLOCK_DEVIATION / 1000)."""

    logic: float
    adc: float
    usb: float


@dataclass(frozen=True)
class Settings:
    """Camera settings beyond the biases; defaults are libcaer's (docs/davis346-protocol.md
    section 2.6)."""

    aps_exposure_us: int = 4000  # APS exposure time
    aps_frame_interval_us: int = 40000  # time between APS frames (25 fps)
    aps_global_shutter: bool = True  # global shutter, where the chip has one
    imu_sample_rate_divider: int = 0  # IMU output rate = 1 kHz / (1 + divider)
    imu_accel_dlpf: int = 1  # accelerometer low-pass filter setting 0..7
    imu_accel_full_scale: int = 1  # 0 = 2 g, 1 = 4 g, 2 = 8 g, 3 = 16 g
    imu_gyro_dlpf: int = 1  # gyroscope low-pass filter setting (MPU-9250 only)
    imu_gyro_full_scale: int = 1  # 0 = 250, 1 = 500, 2 = 1000, 3 = 2000 deg/s
    dvs_background_filter_us: int = 2000  # background-activity filter time (0 = off)
    dvs_refractory_filter_us: int = 0  # the FPGA's refractory filter (0 = off)
    usb_early_packet_delay_us: int = 1000  # the device flushes short USB packets after this

    def __post_init__(self) -> None:
        from evcap.errors import InputError

        limits = {  # the ranges libcaer accepts
            "aps_exposure_us": (0, 4_194_303),
            "aps_frame_interval_us": (0, 8_388_607),
            "imu_sample_rate_divider": (0, 255),
            "imu_accel_dlpf": (0, 7),
            "imu_accel_full_scale": (0, 3),
            "imu_gyro_dlpf": (0, 7),
            "imu_gyro_full_scale": (0, 3),
            "dvs_background_filter_us": (0, 4095 * 250),
            "dvs_refractory_filter_us": (0, 4095 * 250),
            "usb_early_packet_delay_us": (125, 8191 * 125),
        }
        for name, (low, high) in limits.items():
            value = getattr(self, name)
            if not low <= value <= high:
                raise InputError(f"setting {name} = {value} is outside {low}..{high}")


def default_config(
    has: dict[str, int],
    clocks: Clocks,
    biases: dict[str, int],
    settings: Settings,
    dvs_size: tuple[int, int] = (346, 260),
    aps_size: tuple[int, int] = (346, 260),
) -> list[tuple[int, int, int]]:
    """The (module, param, value) writes that configure the camera, in libcaer's order.

    ``has`` holds the capability registers read at open (filter presence, global shutter,
    IMU type, generator), keyed by the names of DEVICE_CAPABILITIES; the sizes are
    (columns, rows) of the DVS and of the APS image."""
    (dvs_cols, dvs_rows), (aps_cols, aps_rows) = dvs_size, aps_size
    w: list[tuple[int, int, int]] = []
    for name, bias in BIASES.items():
        w.append((Module.BIAS, bias.param, biases[name]))
    for param, value in CHIP_DEFAULTS:
        w.append((Module.BIAS, param, value))
    w += [(Module.MUX, 4, 1), (Module.MUX, 5, 1), (Module.DVS, 4, 0), (Module.DVS, 5, 0)]
    if has["dvs_pixel_filter"]:
        for k in range(8):
            # a slot is disabled by pointing it outside the array
            w += [(Module.DVS, 11 + 2 * k, dvs_rows), (Module.DVS, 12 + 2 * k, dvs_cols)]
    if has["dvs_ba_filter"]:
        ba, refr = settings.dvs_background_filter_us, settings.dvs_refractory_filter_us
        w += [
            (Module.DVS, 31, int(ba > 0)),
            (Module.DVS, 32, max(1, round(ba / 250))),
            (Module.DVS, 33, int(refr > 0)),
            (Module.DVS, 34, max(1, round(refr / 250))),
        ]
    if has["dvs_roi_filter"]:
        w += [
            (Module.DVS, 41, 0),
            (Module.DVS, 42, 0),
            (Module.DVS, 43, dvs_cols - 1),
            (Module.DVS, 44, dvs_rows - 1),
        ]
    if has["dvs_skip_filter"]:
        w += [(Module.DVS, 51, 0), (Module.DVS, 52, 5)]
    if has["dvs_polarity_filter"]:
        w += [(Module.DVS, 61, 0), (Module.DVS, 62, 0), (Module.DVS, 63, 0)]
    w.append((Module.APS, 5, 1))
    if has["aps_global_shutter"]:
        gs = int(settings.aps_global_shutter)
        w += [(Module.BIAS, CHIP_GLOBAL_SHUTTER, gs), (Module.APS, 7, gs)]
    w += [(Module.APS, 8, 0), (Module.APS, 9, 0)]
    w += [(Module.APS, 10, aps_cols - 1), (Module.APS, 11, aps_rows - 1)]
    w += [
        (Module.APS, 12, round(settings.aps_exposure_us * clocks.adc)),
        (Module.APS, 13, round(settings.aps_frame_interval_us * clocks.adc)),
    ]
    w += [
        (Module.IMU, 5, settings.imu_sample_rate_divider),
        (Module.IMU, 6, settings.imu_accel_dlpf),
        (Module.IMU, 7, settings.imu_accel_full_scale),
    ]
    if has["imu_type"] == 2:
        w.append((Module.IMU, 9, settings.imu_gyro_dlpf))
    w.append((Module.IMU, 10, settings.imu_gyro_full_scale))
    w += [
        (Module.EXTINPUT, 1, 0),
        (Module.EXTINPUT, 2, 0),
        (Module.EXTINPUT, 3, 1),
        (Module.EXTINPUT, 4, 1),
        (Module.EXTINPUT, 5, round(10 * clocks.logic)),
    ]
    if has["extinput_generator"]:
        w += [
            (Module.EXTINPUT, 11, 0),
            (Module.EXTINPUT, 12, 1),
            (Module.EXTINPUT, 13, round(10 * clocks.logic)),
            (Module.EXTINPUT, 14, round(5 * clocks.logic)),
            (Module.EXTINPUT, 15, 0),
            (Module.EXTINPUT, 16, 0),
        ]
    slices = max(1, round(settings.usb_early_packet_delay_us / 125))
    w.append((Module.USB, 1, round(slices * 125 * clocks.usb)))
    return w


DEVICE_CAPABILITIES = {
    "dvs_pixel_filter": DVS_HAS_PIXEL_FILTER,
    "dvs_ba_filter": DVS_HAS_BA_FILTER,
    "dvs_roi_filter": DVS_HAS_ROI_FILTER,
    "dvs_skip_filter": DVS_HAS_SKIP_FILTER,
    "dvs_polarity_filter": DVS_HAS_POLARITY_FILTER,
    "aps_global_shutter": APS_HAS_GLOBAL_SHUTTER,
    "imu_type": IMU_TYPE,
    "extinput_generator": EXTINPUT_HAS_GENERATOR,
}

# The run flags, in the order libcaer clears them (stop) and sets them (start, last step).
STOP_SEQUENCE = [
    DVS_RUN,
    APS_RUN,
    IMU_RUN_ACCEL,
    IMU_RUN_GYRO,
    IMU_RUN_TEMPERATURE,
    EXTINPUT_RUN_DETECTOR,
    MUX_RUN,
    MUX_TIMESTAMP_RUN,
    USB_RUN,
    MUX_RUN_CHIP,
]
RUN_SEQUENCE = STOP_SEQUENCE[:6]  # DVS, APS, IMU (3), EXTINPUT: set after the MUX runs


def pack_multiple(writes: list[tuple[int, int, int]]) -> bytes:
    """The data of a REQUEST_CONFIG_MULTIPLE request."""
    return b"".join(bytes([m, p]) + v.to_bytes(4, "big") for m, p, v in writes)
