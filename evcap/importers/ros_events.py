"""Event messages of ROS bags decoded into arrays: dvs_msgs/EventArray and the encodings of
event_camera_msgs/EventPacket.

dvs_msgs (rpg_dvs_ros) serializes every event as a struct; it is read straight from the
serialized bytes with numpy, in ROS 1's packed layout or in CDR's aligned one. EventPacket
carries raw bytes in one of the encodings of ros-event-camera/event_camera_codecs; each is
decoded here as that library defines it:

- ``evt3``: Prophesee's EVT 3.0, 16-bit words with a 4-bit code. Times are the sensor's clock
  (microseconds since it started; 12-bit TIME_HIGH words roll over every 2^24 us), not an
  absolute time: the message's ``time_base`` is not used. The decoder's state (time, row,
  vector base) runs on from one packet to the next, and nothing is decoded before the first
  TIME_HIGH followed by a TIME_LOW.
- ``libcaer_cmp``: 16-bit words like evt3's, by column: event time = ``time_base`` (ns since
  the epoch) + the 24-bit microsecond offset the packet's TIME_HIGH/TIME_LOW words give.
- ``libcaer``: libcaer's 8-byte polarity events; time = ``time_base`` + the 31-bit microsecond
  timestamp, plus 2^31 us for each wrap inside the packet (the driver puts the wraps before the
  packet into ``time_base``).

All decoders return times in nanoseconds.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from evcap.errors import InputError

ENCODINGS = ("evt3", "libcaer_cmp", "libcaer")
"""EventPacket encodings evcap decodes."""


@dataclass
class DecodedEvents:
    """Events of one message; ``t_ns`` in nanoseconds (absolute, or the sensor's clock for
    evt3)."""

    x: np.ndarray  # uint16
    y: np.ndarray  # uint16
    t_ns: np.ndarray  # int64
    p: np.ndarray  # uint8

    def __len__(self) -> int:
        return int(self.t_ns.size)


def _empty() -> DecodedEvents:
    z = np.zeros(0, np.uint16)
    return DecodedEvents(z, z, np.zeros(0, np.int64), np.zeros(0, np.uint8))


# -- dvs_msgs/EventArray ---------------------------------------------------------------------

# ROS 1: fields packed, 13 bytes per event (time = uint32 sec, uint32 nsec).
_ROS1_EVENT = np.dtype(
    {"names": ["x", "y", "sec", "nsec", "p"], "formats": ["<u2", "<u2", "<u4", "<u4", "u1"]}
)


def _cdr_event(endian: str, first: bool) -> np.dtype:
    """CDR aligns each field to its size from the message start: the first event of the array
    starts 4-aligned (after the count) and is 14 bytes; every later one starts at 2 mod 4,
    so its time is padded by 2 bytes and its stride is 16."""
    offsets = [0, 2, 4, 8, 12] if first else [0, 2, 6, 10, 14]
    return np.dtype(
        {
            "names": ["x", "y", "sec", "nsec", "p"],
            "formats": [endian + "u2", endian + "u2", endian + "i4", endian + "u4", "u1"],
            "offsets": offsets,
            "itemsize": offsets[-1] + 1,
        }
    )


def _from_struct(events: np.ndarray) -> DecodedEvents:
    t = events["sec"].astype(np.int64) * 1_000_000_000 + events["nsec"].astype(np.int64)
    return DecodedEvents(
        events["x"].astype(np.uint16),
        events["y"].astype(np.uint16),
        t,
        (events["p"] != 0).astype(np.uint8),
    )


def dvs_event_array(raw: bytes | memoryview, cdr: bool) -> tuple[int, int, DecodedEvents]:
    """(width, height, events) of one serialized dvs_msgs/EventArray (ROS 1 or CDR)."""
    raw = memoryview(raw)
    if not cdr:
        # header: seq, stamp (sec, nsec), frame_id (length + bytes)
        (n_frame,) = struct.unpack_from("<I", raw, 12)
        pos = 16 + n_frame
        height, width, n = struct.unpack_from("<III", raw, pos)
        pos += 12
        if pos + n * _ROS1_EVENT.itemsize != len(raw):
            raise InputError(f"a dvs_msgs/EventArray of {len(raw)} bytes does not hold {n} events")
        return width, height, _from_struct(np.frombuffer(raw, _ROS1_EVENT, n, pos))
    endian = "<" if raw[1] == 1 else ">"
    body = raw[4:]  # after the encapsulation header; CDR aligns from here
    # header: stamp (sec, nanosec), frame_id (length with its NUL + bytes)
    (n_frame,) = struct.unpack_from(endian + "I", body, 8)
    pos = (12 + n_frame + 3) & ~3
    height, width, n = struct.unpack_from(endian + "III", body, pos)
    pos += 12
    if n == 0:
        return width, height, _empty()
    end = pos + 13 if n == 1 else pos + 16 * n - 3
    if not end <= len(body) <= end + 3:
        raise InputError(f"a dvs_msgs/EventArray of {len(raw)} bytes does not hold {n} events")
    rest_type = _cdr_event(endian, False)
    first = np.frombuffer(body, _cdr_event(endian, True), 1, pos).astype(rest_type)
    rest = np.ndarray((n - 1,), rest_type, body, pos + 14, (16,)) if n > 1 else first[:0]
    return width, height, _from_struct(np.concatenate([first, rest]))


# -- helpers for the word encodings -----------------------------------------------------------


def _last(where: np.ndarray, values: np.ndarray, query: np.ndarray, before: int) -> np.ndarray:
    """For each word position in ``query``, the value of the last word at ``where`` (sorted
    positions, one value each) at or before it; ``before`` where there is none."""
    return np.concatenate([[before], values])[np.searchsorted(where, query, "right")]


def _vector_bases(
    base_at: np.ndarray,
    base_values: np.ndarray,
    emit_at: np.ndarray,
    advance: np.ndarray,
    before: int,
) -> tuple[np.ndarray, int]:
    """The vector base at each emitting word, and after the last word: the last base word's
    value (``before`` where none yet), moved on by the advances (8 or 12 pixels) of the
    vector words since."""
    done = np.concatenate([[0], np.cumsum(advance)])  # advance before each emitting word
    starts = np.concatenate([[before], base_values])
    done_at_base = np.concatenate([[0], done[np.searchsorted(emit_at, base_at)]])
    k = np.searchsorted(base_at, emit_at, "right")
    return starts[k] + done[:-1] - done_at_base[k], int(starts[-1] + done[-1] - done_at_base[-1])


def _expand(
    first: np.ndarray, mask: np.ndarray, other: np.ndarray, t: np.ndarray, p: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Events of words that each hold up to 16: one at ``first + i`` for each bit i set in
    ``mask``, in word order then bit order; ``other`` is the coordinate the word shares."""
    if np.all(mask == 1):
        return first, other, t, p
    bits = np.unpackbits(
        mask.astype("<u2").view(np.uint8).reshape(-1, 2), axis=1, bitorder="little"
    )
    rows, cols = np.nonzero(bits)
    return first[rows] + cols, other[rows], t[rows], p[rows]


def _decoded(
    x: np.ndarray, y: np.ndarray, t_ns: np.ndarray, p: np.ndarray, width: int, height: int
) -> DecodedEvents:
    """Events within the sensor (the codecs drop the others)."""
    keep = (x < width) & (y < height)
    return DecodedEvents(
        x[keep].astype(np.uint16),
        y[keep].astype(np.uint16),
        t_ns[keep].astype(np.int64),
        p[keep].astype(np.uint8),
    )


def _words(data: np.ndarray, known: tuple[int, ...], encoding: str) -> tuple[np.ndarray, ...]:
    """Codes and 12-bit values of 16-bit words; a code the encoding does not define is an
    error."""
    words = np.frombuffer(data, "<u2", len(data) // 2)
    codes = words >> 12
    unknown = np.setdiff1d(np.flatnonzero(np.bincount(codes, minlength=16)), known)
    if unknown.size:
        raise InputError(
            f"{encoding} word with code {int(unknown[0])}, which the encoding does not define "
            f"(known: {', '.join(map(str, known))})"
        )
    return codes, (words & 0xFFF).astype(np.int64)


# -- evt3 -------------------------------------------------------------------------------------

_E3_ADDR_Y, _E3_ADDR_X, _E3_VECT_BASE_X, _E3_VECT_12, _E3_VECT_8 = 0, 2, 3, 4, 5
_E3_TIME_LOW, _E3_TIME_HIGH = 6, 8
# CONTINUED_4 (7), padding (9), EXT_TRIGGER (10), OTHERS (14), CONTINUED_12 (15) carry no
# CD events and are skipped.
_E3_CODES = (0, 2, 3, 4, 5, 6, 7, 8, 9, 10, 14, 15)
_E3_ROLLOVER_SLACK = 10  # a TIME_HIGH this much below the last is jitter, not a rollover


class Evt3Decoder:
    """EVT 3.0 packets, one after the other; times are the sensor's (ns since it started)."""

    absolute = False

    def __init__(self) -> None:
        self.valid = False  # a TIME_HIGH and then a TIME_LOW were seen
        self._high12 = 0  # the last TIME_HIGH's 12 bits
        self._rollovers = 0
        self._high = 0  # (rollovers << 24) | (high12 << 12)
        self._low = 0
        self._y = 0
        self._base_x = 0
        self._polarity = 0

    def _highs(self, values: np.ndarray) -> np.ndarray:
        """Full time-high values of successive TIME_HIGH words, counting rollovers."""
        if values.size == 0:
            return values
        previous = np.concatenate([[self._high12], values[:-1]])
        rolled = (values < previous) & (previous - values > _E3_ROLLOVER_SLACK)
        rollovers = self._rollovers + np.cumsum(rolled)
        self._high12, self._rollovers = int(values[-1]), int(rollovers[-1])
        full = (rollovers << 24) | (values << 12)
        self._high = int(full[-1])
        return full

    def _find_valid_time(self, codes: np.ndarray, values: np.ndarray) -> int:
        """Index just past the TIME_LOW that makes the time valid (a TIME_HIGH before it in
        the same packet), or len(codes); only time words count until then."""
        highs = np.flatnonzero(codes == _E3_TIME_HIGH)
        lows = np.flatnonzero(codes == _E3_TIME_LOW)
        end = codes.size
        if highs.size and lows[lows > highs[0]].size:
            end = int(lows[lows > highs[0]][0]) + 1
            self.valid = True
        self._highs(values[highs[highs < end]])
        if lows[lows < end].size:
            self._low = int(values[lows[lows < end][-1]])
        return end

    def decode(self, data: np.ndarray, time_base: int, width: int, height: int) -> DecodedEvents:
        if not self.valid:
            words = np.frombuffer(data, "<u2", len(data) // 2).astype(np.int64)
            start = self._find_valid_time(words >> 12, words & 0xFFF)
            data = data[2 * start :]
        codes, values = _words(data, _E3_CODES, "evt3")
        if codes.size == 0:
            return _empty()
        at = {c: np.flatnonzero(codes == c) for c in (0, 2, 3, 4, 5, 6, 8)}
        emit_at = np.flatnonzero(
            (codes == _E3_ADDR_X) | (codes == _E3_VECT_12) | (codes == _E3_VECT_8)
        )
        emit_codes, emit_values = codes[emit_at], values[emit_at]
        high_before = self._high
        highs = self._highs(values[at[_E3_TIME_HIGH]])
        t_us = _last(at[_E3_TIME_HIGH], highs, emit_at, high_before)
        lows = values[at[_E3_TIME_LOW]]
        t_us = t_us + _last(at[_E3_TIME_LOW], lows, emit_at, self._low)
        rows = values[at[_E3_ADDR_Y]] & 0x7FF
        y = _last(at[_E3_ADDR_Y], rows, emit_at, self._y)
        bases = values[at[_E3_VECT_BASE_X]]
        is_x, is_8 = emit_codes == _E3_ADDR_X, emit_codes == _E3_VECT_8
        advance = np.where(is_x, 0, np.where(is_8, 8, 12))
        base_x, self._base_x = _vector_bases(
            at[_E3_VECT_BASE_X], bases & 0x7FF, emit_at, advance, self._base_x
        )
        polarity = _last(at[_E3_VECT_BASE_X], bases >> 11, emit_at, self._polarity)
        first = np.where(is_x, emit_values & 0x7FF, base_x)
        mask = np.where(is_x, 1, np.where(is_8, emit_values & 0xFF, emit_values))
        p = np.where(is_x, emit_values >> 11, polarity)
        x, y, t_us, p = _expand(first, mask, y, t_us, p)
        if lows.size:
            self._low = int(lows[-1])
        if rows.size:
            self._y = int(rows[-1])
        if bases.size:
            self._polarity = int(bases[-1] >> 11)
        return _decoded(x, y, t_us * 1000, p, width, height)


# -- libcaer_cmp ------------------------------------------------------------------------------

_LC_TIME_HIGH, _LC_TIME_LOW, _LC_ADDR_X, _LC_ADDR_Y, _LC_VECT_BASE_Y, _LC_VECT_8 = range(6)
# VECT_12 (6) is defined but never written by the driver, and not decoded by the codec.
_LC_CODES = (0, 1, 2, 3, 4, 5)


class LibcaerCmpDecoder:
    """libcaer_cmp packets: times restart from ``time_base`` in each packet; the column and
    the vector base run on from one packet to the next."""

    absolute = True

    def __init__(self) -> None:
        self._x = 0
        self._base_y = 0
        self._polarity = 0

    def decode(self, data: np.ndarray, time_base: int, width: int, height: int) -> DecodedEvents:
        codes, values = _words(data, _LC_CODES, "libcaer_cmp")
        if codes.size == 0:
            return _empty()
        at = {c: np.flatnonzero(codes == c) for c in _LC_CODES}
        emit_at = np.flatnonzero((codes == _LC_ADDR_Y) | (codes == _LC_VECT_8))
        emit_codes, emit_values = codes[emit_at], values[emit_at]
        offset_us = _last(at[_LC_TIME_HIGH], values[at[_LC_TIME_HIGH]] << 12, emit_at, 0)
        offset_us = offset_us + _last(at[_LC_TIME_LOW], values[at[_LC_TIME_LOW]], emit_at, 0)
        columns = values[at[_LC_ADDR_X]] & 0x7FF
        x = _last(at[_LC_ADDR_X], columns, emit_at, self._x)
        bases = values[at[_LC_VECT_BASE_Y]]
        is_y = emit_codes == _LC_ADDR_Y
        advance = np.where(is_y, 0, 8)
        base_y, self._base_y = _vector_bases(
            at[_LC_VECT_BASE_Y], bases & 0x7FF, emit_at, advance, self._base_y
        )
        polarity = _last(at[_LC_VECT_BASE_Y], bases >> 11, emit_at, self._polarity)
        first = np.where(is_y, emit_values & 0x7FF, base_y)
        mask = np.where(is_y, 1, emit_values & 0xFF)
        p = np.where(is_y, emit_values >> 11, polarity)
        y, x, offset_us, p = _expand(first, mask, x, offset_us, p)
        if columns.size:
            self._x = int(columns[-1])
        if bases.size:
            self._polarity = int(bases[-1] >> 11)
        return _decoded(x, y, time_base + offset_us * 1000, p, width, height)


# -- libcaer ----------------------------------------------------------------------------------

_LIBCAER_EVENT = np.dtype([("data", "<u4"), ("t", "<i4")])
_LIBCAER_WRAP_NS = (1 << 31) * 1000


class LibcaerDecoder:
    """libcaer's polarity events (x: bits 17-31, y: bits 2-16, polarity: bit 1)."""

    absolute = True

    def decode(self, data: np.ndarray, time_base: int, width: int, height: int) -> DecodedEvents:
        if len(data) % _LIBCAER_EVENT.itemsize:
            raise InputError(f"a libcaer packet of {len(data)} bytes does not hold whole events")
        events = np.frombuffer(data, _LIBCAER_EVENT)
        if events.size == 0:
            return _empty()
        t = events["t"].astype(np.int64)
        wraps = np.cumsum(t < np.concatenate([[0], t[:-1]]))
        word = events["data"]
        return DecodedEvents(
            ((word >> 17) & 0x7FFF).astype(np.uint16),
            ((word >> 2) & 0x7FFF).astype(np.uint16),
            time_base + wraps * _LIBCAER_WRAP_NS + t * 1000,
            ((word >> 1) & 1).astype(np.uint8),
        )


PacketDecoder = Evt3Decoder | LibcaerCmpDecoder | LibcaerDecoder


def packet_decoder(encoding: str) -> PacketDecoder:
    """A fresh decoder for EventPacket messages in ``encoding``."""
    decoders = {"evt3": Evt3Decoder, "libcaer_cmp": LibcaerCmpDecoder, "libcaer": LibcaerDecoder}
    if encoding not in decoders:
        raise InputError(
            f"event_camera_msgs/msg/EventPacket encoding {encoding!r} is not known; evcap "
            f"decodes {', '.join(ENCODINGS)}"
        )
    return decoders[encoding]()
