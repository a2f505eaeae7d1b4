"""The DAVIS346 stream decoder: bytes from bulk endpoint 0x82 -> events, frames, IMU, triggers.

The stream is 16-bit little-endian words (davis346-usb.md section 3). The word loop is compiled
with numba; its state lives in arrays that carry over from one transfer to the next, so a
transfer may end anywhere (even inside a word: the odd byte is kept for the next one).
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
from evcap.streams import Frames, ImuSamples, TriggerKind, Triggers

STANDARD_GRAVITY = 9.80665
# The most wraps (32.768 ms each) one wrap word may carry: a running DAVIS346 sends words all
# the time (noise events, the IMU at 1 kHz, frames), so a second without any is not plausible
MAX_WRAPS_PER_WORD = 30

# Indices into the state array S.
_NOW, _WRAP, _BASE, _LASTY, _APS_IGNORE, _IMU_IGNORE = 0, 1, 2, 3, 4, 5
_ROI_STEP, _ROI_HIGH, _ROI_SX, _ROI_SY, _ROI_EX, _ROI_EY, _ROI_KNOWN = 6, 7, 8, 9, 10, 11, 12
_FRAME_ACTIVE, _READ_TYPE, _COL0, _COL1, _ROW0, _ROW1 = 13, 14, 15, 16, 17, 18
_FRAME_T, _EXP_START, _EXP_END, _GLOBAL_SHUTTER = 19, 20, 21, 22
_FSX, _FSY, _FPX, _FPY = 23, 24, 25, 26  # geometry of the frame being read
_IMU_ACTIVE, _IMU_COUNT, _IMU_CFG = 27, 28, 29
_STATE_SIZE = 32

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


@numba.njit(cache=True, nogil=True)
def _decode_words(words, pos, S, C, G, specials, events, n_ev, triggers, n_tr, imu, n_imu, aps):
    """Decode words[pos:]; stop early (returning frame_ready=1) when a frame completes.

    The outputs are filled from n_ev, n_tr, n_imu on: events = (x, y, t, p),
    triggers = (t, kind), imu = (sample being read, raw bytes, t, config); aps = (reset reads,
    frame being read) carries over between calls."""
    ev_x, ev_y, ev_t, ev_p = events
    tr_t, tr_k = triggers
    imu_cur, imu_raw, imu_t, imu_cfg = imu
    reset_buf, frame_buf = aps
    trig_of_special = specials
    n = words.shape[0]
    dvs_cols = G[_G_DVS_COLS]
    dvs_rows = G[_G_DVS_ROWS]
    dvs_invert = G[_G_DVS_INVERT]
    # The hot path (timestamps, rows, columns) keeps its state in locals; the rare words
    # work on S, which is brought up to date before them and read back after.
    now = S[_NOW]
    last_y = S[_LASTY]
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
                    ev_x[n_ev] = last_y
                    ev_y[n_ev] = data
                else:
                    ev_x[n_ev] = data
                    ev_y[n_ev] = last_y
                ev_t[n_ev] = now
                ev_p[n_ev] = code & 1
                n_ev += 1
            else:
                C[_C_DVS_RANGE] += 1
            continue
        if code == 1:  # DVS row
            if data < dvs_rows:
                last_y = data
            else:
                C[_C_DVS_RANGE] += 1
            continue
        S[_NOW] = now
        S[_LASTY] = last_y
        if code == 7:  # timestamp wrap: data counts wraps
            if data > MAX_WRAPS_PER_WORD:
                C[_C_JUMPS] += 1
                data = 1
            S[_WRAP] += 0x8000 * data
            t = S[_WRAP] + S[_BASE]
            if t >= S[_NOW]:
                S[_NOW] = t
            else:
                C[_C_BACKWARDS] += 1
        elif code == 4:  # APS ADC sample
            if S[_APS_IGNORE] or not S[_ROI_KNOWN] or not S[_FRAME_ACTIVE]:
                C[_C_APS_SKIPPED] += 1
                continue
            rt = S[_READ_TYPE]
            col = S[_COL0 + rt]
            row = S[_ROW0 + rt]
            S[_ROW0 + rt] = row + 1
            sx = S[_FSX]
            sy = S[_FSY]
            wire_cols = sy if G[_G_APS_INVERT] else sx
            wire_rows = sx if G[_G_APS_INVERT] else sy
            if col >= wire_cols or row >= wire_rows:
                C[_C_APS_SKIPPED] += 1
                continue
            x = wire_cols - 1 - col if G[_G_APS_FLIPX] else col
            y = wire_rows - 1 - row if G[_G_APS_FLIPY] else row
            if G[_G_APS_INVERT]:
                x, y = y, x
            idx = y * sx + x
            value = data & 0x3FF
            if rt == 0:
                reset_buf[idx] = value
            else:
                reset = reset_buf[idx]
                if reset < 384 or value == 0:
                    frame_buf[idx] = 1023
                else:
                    frame_buf[idx] = min(max(reset - value, 0), 1023)
        elif code == 5:  # misc8
            sub = (data >> 8) & 0xF
            byte = data & 0xFF
            if sub == 0:  # IMU data byte
                if S[_IMU_IGNORE] or not S[_IMU_ACTIVE] or S[_IMU_CFG] < 0 or S[_IMU_COUNT] >= 14:
                    C[_C_IMU_BAD] += 1
                    continue
                k = S[_IMU_COUNT]
                imu_cur[k] = byte
                k += 1
                cfg = S[_IMU_CFG]
                if k == 6 and not cfg & 0x20:  # no temperature: on to the gyro, or the end
                    k = 8 if cfg & 0x40 else 14
                if k == 8 and not cfg & 0x40:  # no gyro
                    k = 14
                S[_IMU_COUNT] = k
            elif sub == 1:  # APS ROI high byte
                S[_ROI_HIGH] = byte
            elif sub == 2:  # APS ROI low byte: one of start col, start row, end col, end row
                step = S[_ROI_STEP]
                if step < 4:
                    S[_ROI_SX + step] = (S[_ROI_HIGH] << 8) | byte
                    S[_ROI_STEP] = step + 1
                    if step == 3:
                        sx0, sy0, ex, ey = S[_ROI_SX], S[_ROI_SY], S[_ROI_EX], S[_ROI_EY]
                        # In image coordinates (after invertXY), as libcaer checks it.
                        if sx0 <= ex < G[_G_APS_WIDTH] and sy0 <= ey < G[_G_APS_HEIGHT]:
                            S[_FPX] = sx0
                            S[_FPY] = sy0
                            S[_FSX] = ex + 1 - sx0
                            S[_FSY] = ey + 1 - sy0
                            S[_ROI_KNOWN] = 1
                        else:
                            C[_C_UNKNOWN] += 1
                else:
                    C[_C_UNKNOWN] += 1
            elif sub == 3:  # IMU configuration
                if S[_IMU_ACTIVE]:
                    S[_IMU_CFG] = byte
                    S[_IMU_COUNT] = (
                        0 if byte & 0x80 else (6 if byte & 0x20 else (8 if byte & 0x40 else 14))
                    )
                else:
                    C[_C_IMU_BAD] += 1
            else:
                C[_C_UNKNOWN] += 1
        elif code == 6:  # misc10: sub 0 carries the measured exposure (used for autoexposure)
            if (data >> 10) & 3:
                C[_C_UNKNOWN] += 1
        else:  # code 0: special event
            aps_only = data == 10 or data == 14 or data == 15
            if data < 32 and trig_of_special[data] >= 0 and not (aps_only and S[_APS_IGNORE]):
                if data == 1:  # timestamp reset: device time restarts at 0
                    S[_BASE] = S[_NOW]
                    S[_WRAP] = 0
                    S[_APS_IGNORE] = 1
                    S[_IMU_IGNORE] = 1
                    S[_FRAME_ACTIVE] = 0
                    S[_IMU_ACTIVE] = 0
                    C[_C_RESETS] += 1
                tr_t[n_tr] = S[_NOW]
                tr_k[n_tr] = trig_of_special[data]
                n_tr += 1
            if data == 5:  # IMU start
                S[_IMU_IGNORE] = 0
                S[_IMU_ACTIVE] = 1
                S[_IMU_COUNT] = 0
                S[_IMU_CFG] = -1
                imu_cur[:] = 0
            elif data == 7:  # IMU end
                if S[_IMU_ACTIVE] and S[_IMU_COUNT] == 14 and S[_IMU_CFG] & 0xE0:
                    imu_raw[n_imu, :] = imu_cur
                    imu_t[n_imu] = S[_NOW]
                    imu_cfg[n_imu] = S[_IMU_CFG]
                    n_imu += 1
                    C[_C_IMU] += 1
                else:
                    C[_C_IMU_BAD] += 1
                S[_IMU_ACTIVE] = 0
            elif data == 8 or data == 9:  # frame start (global / rolling shutter)
                S[_APS_IGNORE] = 0
                S[_FRAME_ACTIVE] = 1
                S[_GLOBAL_SHUTTER] = 1 if data == 8 else 0
                S[_COL0] = 0
                S[_COL1] = 0
                S[_ROW0] = 0
                S[_ROW1] = 0
                S[_READ_TYPE] = 0
                S[_ROI_STEP] = 0
                S[_FRAME_T] = S[_NOW]
                S[_EXP_START] = -1
                S[_EXP_END] = -1
                frame_buf[:] = 0
            elif data == 10:  # frame end
                if S[_FRAME_ACTIVE]:
                    S[_FRAME_ACTIVE] = 0
                    wire_cols = S[_FSY] if G[_G_APS_INVERT] else S[_FSX]
                    if S[_ROI_KNOWN] and S[_COL0] == wire_cols and S[_COL1] == wire_cols:
                        C[_C_FRAMES] += 1
                        return pos, n_ev, n_tr, n_imu, 1
                    C[_C_FRAMES_BAD] += 1
            elif data == 11 or data == 12:  # column start: reset read / signal read
                rt = data - 11
                S[_READ_TYPE] = rt
                S[_ROW0 + rt] = 0
            elif data == 13:  # column end
                rt = S[_READ_TYPE]
                S[_COL0 + rt] += 1
            elif data == 14 and not S[_APS_IGNORE]:
                S[_EXP_START] = S[_NOW]
            elif data == 15 and not S[_APS_IGNORE]:
                S[_EXP_END] = S[_NOW]
            elif data < 32 and trig_of_special[data] >= 0:
                pass
            else:
                C[_C_UNKNOWN] += 1
        now = S[_NOW]
        time_base = S[_WRAP] + S[_BASE]
    S[_NOW] = now
    S[_LASTY] = last_y
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
    sign = np.where(np.asarray(flip), -1.0, 1.0)
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
        self._S[_IMU_CFG] = -1
        self._C = np.zeros(len(COUNTER_NAMES), np.int64)
        self._reset_buf = np.zeros(g.aps_columns * g.aps_rows, np.int64)
        self._frame_buf = np.zeros(g.aps_columns * g.aps_rows, np.uint16)
        self._imu_cur = np.zeros(14, np.uint8)  # the IMU sample being read
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
        S = self._S
        if S[_FRAME_ACTIVE] and not S[_APS_IGNORE]:
            start = S[_EXP_START] if S[_EXP_START] >= 0 else S[_FRAME_T]
            return int(min(start, S[_NOW]))
        return int(S[_NOW])

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
                _TRIGGER_OF_SPECIAL,
                (ev_x, ev_y, ev_t, ev_p),
                n_ev,
                (tr_t, tr_k),
                n_tr,
                (self._imu_cur, imu_raw, imu_t, imu_cfg),
                n_imu,
                (self._reset_buf, self._frame_buf),
            )
            if not ready:
                break
            frames.append(self._completed_frame())
            start = self._S[_EXP_START] if self._S[_EXP_START] >= 0 else self._S[_FRAME_T]
            end = self._S[_EXP_END] if self._S[_EXP_END] >= start else start
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

    def _completed_frame(self) -> np.ndarray:
        """The frame just read, placed in a full-sensor image (pixels outside its ROI are 0)."""
        g, S = self.geometry, self._S
        full = np.zeros((g.aps_height, g.aps_width), np.uint16)
        sx, sy, px, py = int(S[_FSX]), int(S[_FSY]), int(S[_FPX]), int(S[_FPY])
        full[py : py + sy, px : px + sx] = self._frame_buf[: sx * sy].reshape(sy, sx)
        return full
