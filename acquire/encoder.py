"""Encode events, frames, IMU samples and triggers into the DAVIS346's USB stream format.

The inverse of evcap.acquire.decoder, written from the protocol description
(docs/davis346-protocol.md section 3), not from the decoder: it makes the hardware-replay fixtures
(hw-fixtures/) and the streams of the round-trip tests and benchmarks.

Times are host-continuous microseconds, as the decoder gives them. A timestamp reset
(TriggerKind.TIMESTAMP_RESET) restarts the device clock at 0; the encoder then writes the
following times relative to the reset, as a camera would.
"""

from __future__ import annotations

import numba
import numpy as np

from evcap.acquire.decoder import MAX_WRAPS_PER_WORD, STANDARD_GRAVITY, Geometry, imu_signs
from evcap.errors import InputError
from evcap.events import Events
from evcap.streams import Frames, ImuSamples, TriggerKind, Triggers

WRAP = 0x8000
DEFAULT_IMU_CONFIG = 0x80 | 0x40 | 0x20 | 1 << 2 | 1  # all sensors on, +-4 g, +-500 deg/s

_SPECIAL = {
    "timestamp_reset": 1,
    "imu_start": 5,
    "imu_end": 7,
    "frame_start_gs": 8,
    "frame_start_rs": 9,
    "frame_end": 10,
    "reset_column": 11,
    "signal_column": 12,
    "column_end": 13,
    "exposure_start": 14,
    "exposure_end": 15,
}
_TRIGGER_SPECIAL = {
    TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE: 2,
    TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE: 3,
    TriggerKind.EXTERNAL_SIGNAL_PULSE: 4,
    TriggerKind.EXTERNAL_GENERATOR_FALLING_EDGE: 16,
    TriggerKind.EXTERNAL_GENERATOR_RISING_EDGE: 17,
}


@numba.njit(cache=True)
def _encode_events(x, y, t, p, state, out):
    """DVS words for events (device times), after the words already in ``out``.

    state = [now, wrap, last_y, n_out]: the device clock, the wrap base, the latched row and
    the number of words written."""
    now, wrap, last_y, n = state[0], state[1], state[2], state[3]
    for i in range(t.shape[0]):
        ti = t[i]
        if ti != now:
            k = (ti - wrap) // 0x8000
            while k > 0:
                step = min(k, MAX_WRAPS_PER_WORD)
                out[n] = 0x7000 | step
                n += 1
                wrap += 0x8000 * step
                k -= step
                now = wrap
            if ti != now:
                out[n] = 0x8000 | (ti - wrap)
                n += 1
                now = ti
        if y[i] != last_y:
            out[n] = 0x1000 | y[i]
            n += 1
            last_y = y[i]
        out[n] = (0x3000 if p[i] else 0x2000) | x[i]
        n += 1
    state[0], state[1], state[2], state[3] = now, wrap, last_y, n


class StreamEncoder:
    """Builds the byte stream of one camera. Call ``encode`` once per stream, or several times
    for consecutive pieces (the state carries over)."""

    def __init__(
        self,
        geometry: Geometry | None = None,
        *,
        global_shutter: bool = True,
        imu_config: int = DEFAULT_IMU_CONFIG,
    ) -> None:
        self.geometry = geometry or Geometry()
        self.global_shutter = global_shutter
        self.imu_config = imu_config
        self._state = np.array([0, 0, -1, 0], np.int64)  # now, wrap, last_y, n (per chunk)
        self._base = 0  # host time of the last timestamp reset

    # -- words -----------------------------------------------------------------------------

    def _advance(self, words: list[int], t_host: int) -> None:
        """Words that move the device clock to host time ``t_host``."""
        dev = t_host - self._base
        now, wrap = int(self._state[0]), int(self._state[1])
        if dev < now:
            raise InputError(f"encoder: time {t_host} goes back before {now + self._base}")
        if dev != now:
            k = (dev - wrap) // WRAP
            while k > 0:
                step = min(k, MAX_WRAPS_PER_WORD)
                words.append(0x7000 | step)
                wrap += WRAP * step
                k -= step
                now = wrap
            if dev != now:
                words.append(0x8000 | (dev - wrap))
                now = dev
        self._state[0], self._state[1] = now, wrap

    def _special(self, words: list[int], name_or_code: str | int) -> None:
        code = _SPECIAL[name_or_code] if isinstance(name_or_code, str) else name_or_code
        words.append(code)

    def _misc8(self, words: list[int], sub: int, byte: int) -> None:
        words.append(0x5000 | sub << 8 | byte)

    # -- sparse items ------------------------------------------------------------------------

    def _frame_head(self, words: list[int], roi: tuple[int, int, int, int]) -> None:
        self._special(words, "frame_start_gs" if self.global_shutter else "frame_start_rs")
        for value in roi:  # start col, start row, end col, end row: high byte, low byte
            self._misc8(words, 1, value >> 8)
            self._misc8(words, 2, value & 0xFF)
        self._special(words, "exposure_start")

    def _columns(self, words: list[int], values: np.ndarray, kind: str) -> None:
        """Reset or signal columns of a frame; ``values`` is the ROI image (rows x cols)."""
        g = self.geometry
        img = values.T if g.aps_invert_xy else values
        if g.aps_flip_y:
            img = img[::-1, :]
        if g.aps_flip_x:
            img = img[:, ::-1]
        for column in np.ascontiguousarray(img.T):  # the wire sends column after column
            self._special(words, kind)
            words.extend((0x4000 | column.astype(np.int64)).tolist())
            self._special(words, "column_end")

    def _imu_words(self, words: list[int], raw: np.ndarray, cfg: int) -> None:
        self._special(words, "imu_start")
        self._misc8(words, 3, cfg)
        present = [cfg & 0x80] * 3 + [cfg & 0x20] + [cfg & 0x40] * 3
        for value, on in zip(raw.tolist(), present, strict=True):
            if on:
                v = value & 0xFFFF
                self._misc8(words, 0, v >> 8)
                self._misc8(words, 0, v & 0xFF)
        self._special(words, "imu_end")

    def imu_raw(self, imu: ImuSamples) -> np.ndarray:
        """The int16 register values [N, 7] (AX AY AZ T GX GY GZ) that decode to ``imu``."""
        cfg = self.imu_config
        sign = imu_signs(self.geometry.imu_flip)
        accel_lsb = 4.0 * 2.0 ** ((cfg >> 2) & 3) / 65536.0 * STANDARD_GRAVITY
        gyro_lsb = np.deg2rad(500.0 * 2.0 ** (cfg & 3) / 65536.0)
        if self.geometry.imu_type == 2:
            temp = (imu.temperature.astype(np.float64) - 21.0) * 333.87
        else:
            temp = (imu.temperature.astype(np.float64) - 35.0) * 340.0
        raw = np.concatenate(
            [imu.accel * sign / accel_lsb, temp[:, None], imu.gyro * sign / gyro_lsb], axis=1
        )
        return np.clip(np.round(np.nan_to_num(raw)), -32768, 32767).astype(np.int16)

    # -- the whole stream --------------------------------------------------------------------

    def encode(
        self,
        events: Events | None = None,
        frames: Frames | None = None,
        imu: ImuSamples | None = None,
        triggers: Triggers | None = None,
        *,
        roi: tuple[int, int, int, int] | None = None,
        imu_raw: tuple[np.ndarray, np.ndarray] | None = None,
        frame_resets: np.ndarray | None = None,
    ) -> bytes:
        """The stream carrying these streams, merged in time order.

        ``roi`` (start col, start row, end col, end row; default the whole sensor) is the part
        of each frame that is sent. ``imu_raw`` = (t, values [N, 7] int16) gives IMU register
        values directly, instead of ``imu``'s physical values. ``frame_resets`` gives the reset
        reads of each frame (default: a level that makes the signal read reset - value)."""
        g = self.geometry
        roi = roi or (0, 0, g.aps_width - 1, g.aps_height - 1)
        items: list[tuple[int, int, int, object]] = []  # (time, order, kind, payload)
        if frames is not None:
            for i in range(len(frames)):
                t0 = int(frames.t[i])
                items.append((t0, 0, 0, i))
                items.append((t0 + int(frames.exposure_us[i]), 2, 1, i))
        if imu is not None or imu_raw is not None:
            t_imu = imu.t if imu is not None else imu_raw[0]
            raw = imu_raw[1] if imu_raw is not None else self.imu_raw(imu)
            for i in range(len(t_imu)):
                items.append((int(t_imu[i]), 1, 2, raw[i]))
        if triggers is not None:
            for t, kind in zip(triggers.t.tolist(), triggers.kind.tolist(), strict=True):
                if kind == TriggerKind.TIMESTAMP_RESET:
                    items.append((t, 3, 3, None))
                elif kind in _TRIGGER_SPECIAL:
                    items.append((t, 1, 4, _TRIGGER_SPECIAL[kind]))
                else:
                    raise InputError(
                        f"encoder: trigger kind {kind} comes from the APS readout; "
                        "give frames instead"
                    )
        items.sort(key=lambda item: (item[0], item[1]))
        ev_t = events.t if events is not None else np.zeros(0, np.int64)
        cut = np.searchsorted(ev_t, [it[0] for it in items], "right") if items else []
        chunks: list[np.ndarray] = []
        done = 0
        for (t, _, kind, payload), stop in zip(items, list(cut), strict=True):
            if stop > done:
                chunks.append(self._event_words(events, done, stop))
                done = stop
            words: list[int] = []
            self._advance(words, t)
            if kind == 0:
                sx, sy, ex, ey = roi
                self._frame_head(words, roi)
                values = frames.data[payload][sy : ey + 1, sx : ex + 1].astype(np.int64)
                if frame_resets is not None:
                    resets = frame_resets[payload][sy : ey + 1, sx : ex + 1].astype(np.int64)
                else:
                    resets = np.maximum(384, values + 1)
                self._pending_signal = np.where(values >= 1023, 0, resets - values)
                self._columns(words, resets, "reset_column")
            elif kind == 1:
                self._special(words, "exposure_end")
                self._columns(words, self._pending_signal, "signal_column")
                self._special(words, "frame_end")
            elif kind == 2:
                self._imu_words(words, payload, self.imu_config)
            elif kind == 3:
                self._special(words, "timestamp_reset")
                self._base = t
                self._state[0], self._state[1] = 0, 0
            else:
                self._special(words, payload)
            chunks.append(np.asarray(words, np.uint16))
        if len(ev_t) > done:
            chunks.append(self._event_words(events, done, len(ev_t)))
        return np.concatenate(chunks).astype("<u2").tobytes() if chunks else b""

    def _event_words(self, events: Events, start: int, stop: int) -> np.ndarray:
        t = events.t[start:stop] - self._base
        if t.size and int(t[0]) < int(self._state[0]):
            raise InputError("encoder: events go back in time")
        # At most: per event one row, one column, one timestamp and (for a long gap) wrap words
        # of up to MAX_WRAPS_PER_WORD wraps each.
        wraps = int((t[-1] - self._state[1]) // WRAP) if t.size else 0
        out = np.zeros(4 * t.size + wraps // MAX_WRAPS_PER_WORD + 2, np.uint16)
        state = self._state.copy()
        state[3] = 0
        x, y = events.x[start:stop], events.y[start:stop]
        if self.geometry.dvs_invert_xy:
            x, y = y, x
        _encode_events(x.astype(np.int64), y.astype(np.int64), t, events.p[start:stop], state, out)
        self._state[:3] = state[:3]
        return out[: state[3]]
