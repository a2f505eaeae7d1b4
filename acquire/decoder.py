"""The DAVIS346 stream decoder: bytes from bulk endpoint 0x82 -> events, frames, IMU, triggers.

The stream is 16-bit little-endian words (docs/davis346-protocol.md section 3). The word loop
is compiled with numba: the hot path (timestamps, DVS rows and columns) is inline in it, and
each rare word goes to a compiled helper of its own (the APS readout, the IMU samples, the
special events). The state lives in arrays that carry over from one transfer to the next, so
a transfer may end anywhere (even inside a word: the odd byte is kept for the next one).
Unknown or malformed words are counted in ``counters`` and skipped, never fatal.

Times are made host-continuous: device timestamps (with their wraps) plus an offset that a
timestamp reset advances, so that the output never goes back in time. A word that would make
time go backwards (corruption) is counted and does not move the clock; so is a wrap word that
jumps further than a running camera's clock can between two words (a few such bytes from a
flaky cable would otherwise make a session span hours or years), which is taken as one wrap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from evcap.events import Events
from evcap.streams import LIBCAER_TO_CAMERA, Frames, ImuSamples, TriggerKind, Triggers

STANDARD_GRAVITY = 9.80665
# The most wraps (32.768 ms each) one wrap word may carry: a running DAVIS346 sends words all
# the time (noise events, the IMU at 1 kHz, frames), so a second without any is not plausible
MAX_WRAPS_PER_WORD = 30

# The decoder's state: one int64 array S that carries over from one call to the next, its slots
# grouped by owner. One array, not one per owner: numba reference-counts each array a helper
# takes (about 10 ns per array and call here, where it fails to prune the counts), so the
# frequent helpers take S alone.
# The clock and the latched DVS row; the word loop keeps them in locals while it runs and
# brings them up to date for the helpers:
_NOW = 0  # host-continuous time of the last timestamp
_WRAP = 1  # device time of the last wrap (a multiple of 0x8000 since the last reset)
_BASE = 2  # host time of the last timestamp reset
_LAST_ROW = 3  # the latched DVS row
# The APS state machine (_aps_sample, _aps_column, _aps_frame, _aps_roi_byte):
_APS_IGNORE = 4  # drop APS words until a frame start (after data start or a timestamp reset)
_APS_ROI_STEP = 5  # which of the 4 ROI values comes next
_APS_ROI_HIGH = 6  # the high byte of the ROI value being read
_APS_ROI = 7  # 7..10: start column, start row, end column, end row, as sent
_APS_ROI_KNOWN = 11  # a valid ROI has arrived (the frame's place below is set)
_APS_FRAME_ACTIVE = 12
_APS_READ_TYPE = 13  # 0 reset read, 1 signal read
_APS_COLUMN = 14  # 14, 15: columns done, per read type
_APS_ROW = 16  # 16, 17: samples in the current column, per read type
_APS_FRAME_T = 18  # frame start time
_APS_EXPOSURE_START = 19  # -1 until its special arrives
_APS_EXPOSURE_END = 20
_APS_GLOBAL_SHUTTER = 21
_APS_FRAME_W, _APS_FRAME_H, _APS_FRAME_X, _APS_FRAME_Y = 22, 23, 24, 25  # ROI in the image
# IMU sample assembly (_imu_start, _imu_byte, _imu_end):
_IMU_IGNORE = 26  # drop IMU words until an IMU start (after data start or a timestamp reset)
_IMU_ACTIVE = 27  # between IMU start and IMU end
_IMU_COUNT = 28  # the next byte's index in the sample (14: complete)
_IMU_CONFIG = 29  # the sample's configuration byte; -1 until it arrives
_IMU_BYTES = 30  # 30..43: the 14 bytes of the sample being read
_STATE_SIZE = 44

# Indices into the counters array; COUNTER_NAMES describes them.
COUNTER_NAMES = (
    "words",
    "events",
    "dvs_out_of_range",
    "unknown_words",
    "aps_samples_skipped",
    "frames",
    "frames_bad",
    "imu_samples",
    "imu_bad",
    "timestamp_resets",
    "time_went_backwards",
    "odd_bytes",
    "timestamp_jumps",
)
(
    _C_WORDS,
    _C_EVENTS,
    _C_DVS_RANGE,
    _C_UNKNOWN,
    _C_APS_SKIPPED,
    _C_FRAMES,
    _C_FRAMES_BAD,
    _C_IMU,
    _C_IMU_BAD,
    _C_RESETS,
    _C_BACKWARDS,
    _C_ODD,
    _C_JUMPS,
) = range(len(COUNTER_NAMES))

# Indices into the geometry array G.
_G_DVS_COLS, _G_DVS_ROWS, _G_DVS_INVERT, _G_APS_WIDTH, _G_APS_HEIGHT = 0, 1, 2, 3, 4
_G_APS_FLIPX, _G_APS_FLIPY, _G_APS_INVERT = 5, 6, 7

# Wire codes of the special events (code 0) that become triggers.
_SPECIAL_TRIGGERS = {
    1: TriggerKind.TIMESTAMP_RESET,
    2: TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE,
    3: TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE,
    4: TriggerKind.EXTERNAL_SIGNAL_PULSE,
    8: TriggerKind.APS_FRAME_START,
    9: TriggerKind.APS_FRAME_START,
    10: TriggerKind.APS_FRAME_END,
    14: TriggerKind.APS_EXPOSURE_START,
    15: TriggerKind.APS_EXPOSURE_END,
    16: TriggerKind.EXTERNAL_GENERATOR_FALLING_EDGE,
    17: TriggerKind.EXTERNAL_GENERATOR_RISING_EDGE,
}
_TRIGGER_OF_SPECIAL = np.full(32, -1, np.int64)
for _code, _kind in _SPECIAL_TRIGGERS.items():
    _TRIGGER_OF_SPECIAL[_code] = int(_kind)


# -- the rare words (docs/davis346-protocol.md sections 3.1 to 3.4) ---------------------------


@numba.njit(cache=True, nogil=True)
def _timestamp_wrap(data, S, C):
    """A wrap word (code 7): ``data`` counts wraps of the 15-bit timestamp."""
    if data > MAX_WRAPS_PER_WORD:
        C[_C_JUMPS] += 1
        data = 1
    S[_WRAP] += 0x8000 * data
    t = S[_WRAP] + S[_BASE]
    if t >= S[_NOW]:
        S[_NOW] = t
    else:
        C[_C_BACKWARDS] += 1


@numba.njit(cache=True, nogil=True)
def _special_trigger(data, S, C, tr_t, tr_k, n_tr):
    """The trigger of a special event that has one; a timestamp reset also restarts the device
    time (host time goes on) and drops APS and IMU words until their next start. Returns the
    new number of triggers."""
    aps_only = data == 10 or data == 14 or data == 15
    if aps_only and S[_APS_IGNORE]:
        return n_tr
    if data == 1:
        S[_BASE] = S[_NOW]
        S[_WRAP] = 0
        S[_APS_IGNORE] = 1
        S[_APS_FRAME_ACTIVE] = 0
        S[_IMU_IGNORE] = 1
        S[_IMU_ACTIVE] = 0
        C[_C_RESETS] += 1
    tr_t[n_tr] = S[_NOW]
    tr_k[n_tr] = _TRIGGER_OF_SPECIAL[data]
    return n_tr + 1


@numba.njit(cache=True, nogil=True)
def _aps_frame(data, S, G, C, frame_buf):
    """Frame start (8 global, 9 rolling shutter), frame end (10), exposure start and end (14,
    15). Returns True when the frame just ended is complete in ``frame_buf``."""
    if data == 8 or data == 9:
        S[_APS_IGNORE] = 0
        S[_APS_FRAME_ACTIVE] = 1
        S[_APS_GLOBAL_SHUTTER] = 1 if data == 8 else 0
        S[_APS_COLUMN] = 0
        S[_APS_COLUMN + 1] = 0
        S[_APS_ROW] = 0
        S[_APS_ROW + 1] = 0
        S[_APS_READ_TYPE] = 0
        S[_APS_ROI_STEP] = 0
        S[_APS_FRAME_T] = S[_NOW]
        S[_APS_EXPOSURE_START] = -1
        S[_APS_EXPOSURE_END] = -1
        frame_buf[:] = 0
    elif data == 10:  # complete when every column of both reads came
        if S[_APS_FRAME_ACTIVE]:
            S[_APS_FRAME_ACTIVE] = 0
            wire_cols = S[_APS_FRAME_H] if G[_G_APS_INVERT] else S[_APS_FRAME_W]
            if (
                S[_APS_ROI_KNOWN]
                and S[_APS_COLUMN] == wire_cols
                and S[_APS_COLUMN + 1] == wire_cols
            ):
                C[_C_FRAMES] += 1
                return True
            C[_C_FRAMES_BAD] += 1
    elif data == 14 and not S[_APS_IGNORE]:
        S[_APS_EXPOSURE_START] = S[_NOW]
    elif data == 15 and not S[_APS_IGNORE]:
        S[_APS_EXPOSURE_END] = S[_NOW]
    return False


@numba.njit(cache=True, nogil=True)
def _aps_column(data, S):
    """Column start (11 reset read, 12 signal read) or column end (13)."""
    if data == 13:
        S[_APS_COLUMN + S[_APS_READ_TYPE]] += 1
    else:
        read_type = data - 11
        S[_APS_READ_TYPE] = read_type
        S[_APS_ROW + read_type] = 0


@numba.njit(cache=True, nogil=True)
def _aps_roi_byte(sub, byte, S, G, C):
    """A byte of the frame's ROI (misc8 sub 1 high, sub 2 low): start column, start row, end
    column, end row (inclusive, in image coordinates)."""
    if sub == 1:
        S[_APS_ROI_HIGH] = byte
        return
    step = S[_APS_ROI_STEP]
    if step >= 4:
        C[_C_UNKNOWN] += 1
        return
    S[_APS_ROI + step] = (S[_APS_ROI_HIGH] << 8) | byte
    S[_APS_ROI_STEP] = step + 1
    if step < 3:
        return
    sx, sy, ex, ey = S[_APS_ROI], S[_APS_ROI + 1], S[_APS_ROI + 2], S[_APS_ROI + 3]
    # In image coordinates (after invertXY), as libcaer checks it.
    if sx <= ex < G[_G_APS_WIDTH] and sy <= ey < G[_G_APS_HEIGHT]:
        S[_APS_FRAME_X] = sx
        S[_APS_FRAME_Y] = sy
        S[_APS_FRAME_W] = ex + 1 - sx
        S[_APS_FRAME_H] = ey + 1 - sy
        S[_APS_ROI_KNOWN] = 1
    else:
        C[_C_UNKNOWN] += 1


@numba.njit(cache=True, nogil=True)
def _aps_sample(data, S, G, C, reset_buf, frame_buf):
    """An ADC sample (code 4) of the current column: a reset read is kept, a signal read
    makes the pixel's value from it (correlated double sampling)."""
    if S[_APS_IGNORE] or not S[_APS_ROI_KNOWN] or not S[_APS_FRAME_ACTIVE]:
        C[_C_APS_SKIPPED] += 1
        return
    read_type = S[_APS_READ_TYPE]
    col = S[_APS_COLUMN + read_type]
    row = S[_APS_ROW + read_type]
    S[_APS_ROW + read_type] = row + 1
    width = S[_APS_FRAME_W]
    invert = G[_G_APS_INVERT]
    wire_cols = S[_APS_FRAME_H] if invert else width
    wire_rows = width if invert else S[_APS_FRAME_H]
    if col >= wire_cols or row >= wire_rows:
        C[_C_APS_SKIPPED] += 1
        return
    x = wire_cols - 1 - col if G[_G_APS_FLIPX] else col
    y = wire_rows - 1 - row if G[_G_APS_FLIPY] else row
    if invert:
        x, y = y, x
    idx = y * width + x
    value = data & 0x3FF
    if read_type == 0:
        reset_buf[idx] = value
        return
    reset = reset_buf[idx]
    if reset < 384 or value == 0:  # a saturated pixel: white, as libcaer makes it
        frame_buf[idx] = 1023
    else:
        frame_buf[idx] = min(max(reset - value, 0), 1023)


@numba.njit(cache=True, nogil=True)
def _imu_start(S):
    """IMU start (special 5): a new sample begins."""
    S[_IMU_IGNORE] = 0
    S[_IMU_ACTIVE] = 1
    S[_IMU_COUNT] = 0
    S[_IMU_CONFIG] = -1
    for i in range(14):
        S[_IMU_BYTES + i] = 0


@numba.njit(cache=True, nogil=True)
def _imu_byte(sub, byte, S):
    """The sample's configuration (misc8 sub 3) or its next data byte (sub 0); the bytes of
    sensors that are off are not sent, so the index skips them. Returns False for a word out of
    place, which the caller counts (so that this frequent helper takes S alone)."""
    cfg = S[_IMU_CONFIG]
    if sub == 3:
        if not S[_IMU_ACTIVE]:
            return False
        S[_IMU_CONFIG] = byte
        S[_IMU_COUNT] = 0 if byte & 0x80 else (6 if byte & 0x20 else (8 if byte & 0x40 else 14))
        return True
    k = S[_IMU_COUNT]
    if S[_IMU_IGNORE] or not S[_IMU_ACTIVE] or cfg < 0 or k >= 14:
        return False
    S[_IMU_BYTES + k] = byte
    k += 1
    if k == 6 and not cfg & 0x20:  # no temperature: on to the gyro, or the end
        k = 8 if cfg & 0x40 else 14
    if k == 8 and not cfg & 0x40:  # no gyro
        k = 14
    S[_IMU_COUNT] = k
    return True


@numba.njit(cache=True, nogil=True)
def _imu_end(S, C, imu_raw, imu_t, imu_cfg, n_imu):
    """IMU end (special 7): a complete sample is written out. Returns the new number of
    samples."""
    if S[_IMU_ACTIVE] and S[_IMU_COUNT] == 14 and S[_IMU_CONFIG] & 0xE0:
        for i in range(14):
            imu_raw[n_imu, i] = S[_IMU_BYTES + i]
        imu_t[n_imu] = S[_NOW]
        imu_cfg[n_imu] = S[_IMU_CONFIG]
        n_imu += 1
        C[_C_IMU] += 1
    else:
        C[_C_IMU_BAD] += 1
    S[_IMU_ACTIVE] = 0
    return n_imu


# -- the word loop ------------------------------------------------------------------------------


@numba.njit(cache=True, nogil=True)
def _decode_words(words, pos, S, C, G, buffers, events, n_ev, triggers, n_tr, imu, n_imu):
    """Decode words[pos:]; stop early (returning frame_ready=1) when a frame completes.

    S, C and buffers = (reset reads, frame being read) carry over between calls. The outputs
    are filled from n_ev, n_tr, n_imu on: events = (x, y, t, p), triggers = (t, kind),
    imu = (raw bytes, t, configuration)."""
    reset_buf, frame_buf = buffers
    ev_x, ev_y, ev_t, ev_p = events
    tr_t, tr_k = triggers
    imu_raw, imu_t, imu_cfg = imu
    n = words.shape[0]
    dvs_cols = G[_G_DVS_COLS]
    dvs_rows = G[_G_DVS_ROWS]
    dvs_invert = G[_G_DVS_INVERT]
    now = S[_NOW]
    last_row = S[_LAST_ROW]
    time_base = S[_WRAP] + S[_BASE]
    while pos < n:
        w = np.int64(words[pos])
        pos += 1
        if w & 0x8000:  # timestamp
            t = time_base + (w & 0x7FFF)
            if t >= now:
                now = t
            else:
                C[_C_BACKWARDS] += 1
            continue
        code = (w >> 12) & 7
        data = w & 0x0FFF
        if code == 2 or code == 3:  # DVS column: one event
            if data < dvs_cols:
                if dvs_invert:
                    ev_x[n_ev] = last_row
                    ev_y[n_ev] = data
                else:
                    ev_x[n_ev] = data
                    ev_y[n_ev] = last_row
                ev_t[n_ev] = now
                ev_p[n_ev] = code & 1
                n_ev += 1
            else:
                C[_C_DVS_RANGE] += 1
            continue
        if code == 1:  # DVS row
            if data < dvs_rows:
                last_row = data
            else:
                C[_C_DVS_RANGE] += 1
            continue
        if code == 4:  # APS sample: the most frequent of the rare words; it needs no clock
            _aps_sample(data, S, G, C, reset_buf, frame_buf)
            continue
        S[_NOW] = now
        S[_LAST_ROW] = last_row
        if code == 7:
            _timestamp_wrap(data, S, C)
        elif code == 5:  # misc8: IMU configuration and bytes, APS ROI bytes
            sub = (data >> 8) & 0xF
            if sub == 0 or sub == 3:
                if not _imu_byte(sub, data & 0xFF, S):
                    C[_C_IMU_BAD] += 1
            elif sub == 1 or sub == 2:
                _aps_roi_byte(sub, data & 0xFF, S, G, C)
            else:
                C[_C_UNKNOWN] += 1
        elif code == 6:  # misc10: sub 0 carries the measured exposure (used for autoexposure)
            if (data >> 10) & 3:
                C[_C_UNKNOWN] += 1
        else:  # code 0: special event
            is_trigger = data < 32 and _TRIGGER_OF_SPECIAL[data] >= 0
            if is_trigger:
                n_tr = _special_trigger(data, S, C, tr_t, tr_k, n_tr)
            if data == 5:
                _imu_start(S)
            elif data == 7:
                n_imu = _imu_end(S, C, imu_raw, imu_t, imu_cfg, n_imu)
            elif 11 <= data <= 13:
                _aps_column(data, S)
            elif 8 <= data <= 15:
                if _aps_frame(data, S, G, C, frame_buf):
                    return pos, n_ev, n_tr, n_imu, 1
            elif not is_trigger:
                C[_C_UNKNOWN] += 1
        now = S[_NOW]
        time_base = S[_WRAP] + S[_BASE]
    S[_NOW] = now
    S[_LAST_ROW] = last_row
    return pos, n_ev, n_tr, n_imu, 0


@dataclass(frozen=True)
class Geometry:
    """What the decoder needs to know about the camera (read from its registers at open)."""

    dvs_columns: int = 346
    dvs_rows: int = 260
    dvs_invert_xy: bool = False
    aps_columns: int = 346
    aps_rows: int = 260
    aps_flip_x: bool = False
    aps_flip_y: bool = False
    aps_invert_xy: bool = False
    imu_type: int = 1  # 1 MPU-6050/6150, 2 MPU-9250
    imu_flip: tuple[bool, bool, bool] = (False, False, False)  # negate x, y, z
    color_filter: str = "MONO"

    @property
    def width(self) -> int:
        return self.dvs_rows if self.dvs_invert_xy else self.dvs_columns

    @property
    def height(self) -> int:
        return self.dvs_columns if self.dvs_invert_xy else self.dvs_rows

    @property
    def aps_width(self) -> int:
        """Width of the frames (after invertXY)."""
        return self.aps_rows if self.aps_invert_xy else self.aps_columns

    @property
    def aps_height(self) -> int:
        return self.aps_columns if self.aps_invert_xy else self.aps_rows


@dataclass
class Decoded:
    """What one call of StreamDecoder.decode produced."""

    events: Events
    frames: Frames
    imu: ImuSamples
    triggers: Triggers


def imu_signs(flip: tuple[bool, bool, bool]) -> np.ndarray:
    """The sign of each axis from the IMU's registers to the camera's axes: the device's
    orientation flips, then libcaer's axes into the camera's (evcap.streams.LIBCAER_TO_CAMERA)."""
    return np.where(np.asarray(flip), -1.0, 1.0) * LIBCAER_TO_CAMERA


def imu_physical(
    raw: np.ndarray, cfg: np.ndarray, imu_type: int, flip: tuple[bool, bool, bool]
) -> tuple[np.ndarray, ...]:
    """(accel m/s^2, gyro rad/s, temperature degC) from the 14 raw bytes of each sample;
    NaN where the sample's configuration says the sensor was off."""
    high, low = raw[:, 0::2].astype(np.uint16), raw[:, 1::2].astype(np.uint16)
    values = (high << 8 | low).view(np.int16).astype(np.float64)  # big-endian int16 pairs
    accel_fs = (cfg >> 2) & 3
    gyro_fs = cfg & 3
    accel = values[:, 0:3] * (4.0 * 2.0**accel_fs / 65536.0)[:, None] * STANDARD_GRAVITY
    gyro = np.deg2rad(values[:, 4:7] * (500.0 * 2.0**gyro_fs / 65536.0)[:, None])
    if imu_type == 2:
        temperature = values[:, 3] / 333.87 + 21.0
    else:
        temperature = values[:, 3] / 340.0 + 35.0
    sign = imu_signs(flip)
    accel, gyro = accel * sign, gyro * sign
    accel[(cfg & 0x80) == 0] = np.nan
    temperature[(cfg & 0x20) == 0] = np.nan
    gyro[(cfg & 0x40) == 0] = np.nan
    return accel, gyro, temperature


class StreamDecoder:
    """Decodes the bulk stream of one camera, one transfer (or many) at a time."""

    def __init__(self, geometry: Geometry) -> None:
        self.geometry = geometry
        g = geometry
        self._G = np.array(
            [
                g.dvs_columns,
                g.dvs_rows,
                int(g.dvs_invert_xy),
                g.aps_width,
                g.aps_height,
                int(g.aps_flip_x),
                int(g.aps_flip_y),
                int(g.aps_invert_xy),
            ],
            np.int64,
        )
        self._S = np.zeros(_STATE_SIZE, np.int64)
        self._S[_APS_IGNORE] = 1
        self._S[_IMU_IGNORE] = 1
        self._S[_IMU_CONFIG] = -1
        self._C = np.zeros(len(COUNTER_NAMES), np.int64)
        self._reset_buf = np.zeros(g.aps_columns * g.aps_rows, np.int64)
        self._frame_buf = np.zeros(g.aps_columns * g.aps_rows, np.uint16)
        self._odd = b""

    @property
    def counters(self) -> dict[str, int]:
        return {name: int(v) for name, v in zip(COUNTER_NAMES, self._C, strict=True)}

    @property
    def now_us(self) -> int:
        """The decoder's clock: the time of the last timestamp seen (host-continuous)."""
        return int(self._S[_NOW])

    @property
    def pending_since_us(self) -> int:
        """The earliest time data still to come can carry: the start of the frame being read
        (frames are stamped with their exposure start), or the clock."""
        S, now = self._S, self._S[_NOW]
        if S[_APS_FRAME_ACTIVE] and not S[_APS_IGNORE]:
            return int(min(self._exposure_start(), now))
        return int(now)

    def decode(self, data: bytes | bytearray | memoryview) -> Decoded:
        """Decode the next bytes of the stream."""
        if self._odd:
            data = self._odd + bytes(data)
            self._odd = b""
        n_bytes = len(data)
        if n_bytes % 2:
            self._odd = bytes(data[-1:])
            self._C[_C_ODD] += 1
            n_bytes -= 1
        words = np.frombuffer(data, dtype="<u2", count=n_bytes // 2)
        n = words.size
        self._C[_C_WORDS] += n
        ev_x = np.empty(n, np.uint16)
        ev_y = np.empty(n, np.uint16)
        ev_t = np.empty(n, np.int64)
        ev_p = np.empty(n, np.uint8)
        tr_t = np.empty(n, np.int64)
        tr_k = np.empty(n, np.uint8)
        # A sample takes at least 5 words (start, configuration, 2 bytes, end); the first
        # may have begun in an earlier call.
        n_imu_max = n // 5 + 1
        imu_raw = np.zeros((n_imu_max, 14), np.uint8)
        imu_t = np.empty(n_imu_max, np.int64)
        imu_cfg = np.empty(n_imu_max, np.int64)
        frames, frame_t, frame_exp = [], [], []
        pos = n_ev = n_tr = n_imu = 0
        while True:
            pos, n_ev, n_tr, n_imu, ready = _decode_words(
                words,
                pos,
                self._S,
                self._C,
                self._G,
                (self._reset_buf, self._frame_buf),
                (ev_x, ev_y, ev_t, ev_p),
                n_ev,
                (tr_t, tr_k),
                n_tr,
                (imu_raw, imu_t, imu_cfg),
                n_imu,
            )
            if not ready:
                break
            frames.append(self._completed_frame())
            start = self._exposure_start()
            end = self._S[_APS_EXPOSURE_END]
            end = end if end >= start else start
            frame_t.append(int(start))
            frame_exp.append(int(end - start))
        self._C[_C_EVENTS] += n_ev
        g = self.geometry
        events = Events._unchecked(
            ev_x[:n_ev], ev_y[:n_ev], ev_t[:n_ev], ev_p[:n_ev], g.width, g.height, g.color_filter
        )
        data3 = np.stack(frames) if frames else np.zeros((0, g.aps_height, g.aps_width), np.uint16)
        accel, gyro, temperature = imu_physical(
            imu_raw[:n_imu], imu_cfg[:n_imu], g.imu_type, g.imu_flip
        )
        return Decoded(
            events=events,
            frames=Frames(data3, np.asarray(frame_t, np.int64), np.asarray(frame_exp, np.int64)),
            imu=ImuSamples(imu_t[:n_imu], accel, gyro, temperature),
            triggers=Triggers(tr_t[:n_tr], tr_k[:n_tr]),
        )

    def _exposure_start(self) -> int:
        """The time of the frame being read (its exposure start, else its frame start)."""
        S = self._S
        start = S[_APS_EXPOSURE_START]
        return int(start if start >= 0 else S[_APS_FRAME_T])

    def _completed_frame(self) -> np.ndarray:
        """The frame just read, placed in a full-sensor image (pixels outside its ROI are 0)."""
        g, S = self.geometry, self._S
        full = np.zeros((g.aps_height, g.aps_width), np.uint16)
        w, h = int(S[_APS_FRAME_W]), int(S[_APS_FRAME_H])
        x, y = int(S[_APS_FRAME_X]), int(S[_APS_FRAME_Y])
        full[y : y + h, x : x + w] = self._frame_buf[: w * h].reshape(h, w)
        return full
