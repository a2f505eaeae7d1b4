"""Import AEDAT 4 files (iniVation DV) into a session.

Packets are decoded by the ``aedat`` package (neuromorphicsystems/aedat: a small, numpy-only
Rust decoder of AEDAT 4's LZ4/Zstd-compressed FlatBuffer packets). Before decoding, the file's
framing (header, packet headers, data table) is walked here, so that a truncated or foreign
file gives an error that says where it breaks instead of a decoder message.
"""

from __future__ import annotations

import os
import re
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from evcap.errors import ForeignFormatError, InputError, InputNotFoundError
from evcap.events import Events, check_color_filter
from evcap.importers.common import ImportSummary, check_output, partial_output
from evcap.session import SensorInfo, SessionWriter
from evcap.streams import LIBCAER_TO_CAMERA, Frames, ImuSamples, Triggers

MAGIC = b"#!AER-DAT4.0\r\n"
STANDARD_GRAVITY = 9.80665  # m/s^2 per g
_COMPRESSIONS = {0: "none", 1: "LZ4", 2: "LZ4 (high)", 3: "Zstd", 4: "Zstd (high)"}
_LZ4_MAGIC = 0x184D2204
_EVENT_BATCH = 1 << 18


@dataclass
class Aedat4Layout:
    """The framing of an AEDAT 4 file, read without decoding any packet."""

    compression: str
    data_table_position: int  # -1 when the recorder did not write a data table
    info_xml: str
    packets: list[tuple[int, int, int]] = field(default_factory=list)  # (offset, stream, size)


def _fb_field(buf: bytes, table: int, index: int) -> int | None:
    """Absolute position of field ``index`` of the FlatBuffer table at ``table``, or None."""
    vtable = table - struct.unpack_from("<i", buf, table)[0]
    vsize = struct.unpack_from("<H", buf, vtable)[0]
    slot = 4 + 2 * index
    if slot + 2 > vsize:
        return None
    offset = struct.unpack_from("<H", buf, vtable + slot)[0]
    return table + offset if offset else None


def _parse_io_header(buf: bytes) -> tuple[int, int, str]:
    """(compression, data table position, info XML) from the IOHeader FlatBuffer."""
    table = struct.unpack_from("<I", buf, 0)[0]
    pos = _fb_field(buf, table, 0)
    compression = struct.unpack_from("<i", buf, pos)[0] if pos is not None else 0
    pos = _fb_field(buf, table, 1)
    data_table = struct.unpack_from("<q", buf, pos)[0] if pos is not None else -1
    pos = _fb_field(buf, table, 2)
    info = ""
    if pos is not None:
        start = pos + struct.unpack_from("<I", buf, pos)[0]
        length = struct.unpack_from("<I", buf, start)[0]
        info = buf[start + 4 : start + 4 + length].decode("utf-8", "replace")
    return compression, data_table, info


def _lz4_frame_end(f, start: int, size: int) -> int | None:
    """Byte just past the LZ4 frame at ``start``, or None if the file ends inside it."""
    f.seek(start)
    head = f.read(7)
    if len(head) < 7 or struct.unpack_from("<I", head)[0] != _LZ4_MAGIC:
        return None
    flags = head[4]
    pos = start + 6 + (8 if flags & 0x08 else 0) + (4 if flags & 0x01 else 0) + 1
    block_checksum = 4 if flags & 0x10 else 0
    while True:
        f.seek(pos)
        word = f.read(4)
        if len(word) < 4:
            return None
        n = struct.unpack("<I", word)[0]
        pos += 4
        if n == 0:
            pos += 4 if flags & 0x04 else 0
            return pos if pos <= size else None
        pos += (n & 0x7FFFFFFF) + block_checksum
        if pos > size:
            return None


def read_layout(path: str | os.PathLike) -> Aedat4Layout:
    """Walk the framing of an AEDAT 4 file; raise ForeignFormatError if it is not one, or is
    truncated or corrupt."""
    path = Path(path)
    if not path.exists():
        raise InputNotFoundError(f"{path}: no such file")
    if path.is_dir():
        raise ForeignFormatError(f"{path} is a folder, not an AEDAT 4 file")
    size = path.stat().st_size
    with open(path, "rb") as f:
        magic = f.read(len(MAGIC))
        if magic != MAGIC:
            if magic.startswith(b"#!AER-DAT"):
                version = magic[9:12].decode("ascii", "replace")
                raise ForeignFormatError(
                    f"{path} is AEDAT {version}; evcap imports AEDAT 4.0 (convert it with DV)"
                )
            raise ForeignFormatError(f"{path} is not an AEDAT 4 file (no '#!AER-DAT4.0' header)")
        word = f.read(4)
        header_size = struct.unpack("<I", word)[0] if len(word) == 4 else size
        header = f.read(header_size)
        if len(header) < header_size:
            raise ForeignFormatError(f"{path} is truncated: it ends inside its header")
        try:
            compression, data_table, info = _parse_io_header(header)
        except (struct.error, IndexError):
            raise ForeignFormatError(f"{path}: the AEDAT 4 header is corrupt") from None
        if compression not in _COMPRESSIONS or data_table < -1 or data_table > size:
            if data_table > size:
                raise ForeignFormatError(
                    f"{path} is truncated: {size} bytes, but its data table starts at byte "
                    f"{data_table}"
                )
            raise ForeignFormatError(f"{path}: the AEDAT 4 header is corrupt")
        layout = Aedat4Layout(_COMPRESSIONS[compression], data_table, info)
        end = data_table if data_table >= 0 else size
        pos = len(MAGIC) + 4 + header_size
        while pos < end:
            f.seek(pos)
            word = f.read(8)
            if len(word) < 8 or pos + 8 > end:
                raise ForeignFormatError(
                    f"{path} is truncated or corrupt: a packet header at byte {pos} is cut off"
                )
            stream, length = struct.unpack("<ii", word)
            if length < 0 or stream < 0 or pos + 8 + length > end:
                raise ForeignFormatError(
                    f"{path} is truncated or corrupt: the packet at byte {pos} claims {length} "
                    f"bytes, but the {'data table' if data_table >= 0 else 'file'} starts at "
                    f"byte {end}"
                )
            layout.packets.append((pos, stream, length))
            pos += 8 + length
        if data_table >= 0 and layout.compression.startswith("LZ4"):
            table_end = _lz4_frame_end(f, data_table, size)
            if table_end is None:
                raise ForeignFormatError(
                    f"{path} is truncated: it ends inside its data table (at byte {size})"
                )
    return layout


def _sensor_from_info(
    info_xml: str, width: int, height: int, color_filter: str, t_offset: int
) -> SensorInfo:
    """Model and serial from DV's "source" attribute, e.g. "DAVIS346_00000002"."""
    m = re.search(r'<attr key="source" type="string">([^<]*)</attr>', info_xml)
    source = m.group(1) if m else "unknown"
    model, _, serial = source.rpartition("_")
    if not model:
        model, serial = source, ""
    if color_filter != "MONO" and not model.startswith("Color-"):
        model = f"Color-{model}"
    return SensorInfo(model, width, height, color_filter, serial, t_offset)


def _mosaic(pixels: np.ndarray, fmt: str, color_filter: str) -> np.ndarray:
    """An AEDAT 4 frame as the sensor's raw values (uint16, 0..1023).

    DV writes 8-bit frames: the 10-bit value >> 2. Color frames (RGB/RGBA) were demosaiced
    from the sensor's mosaic; each pixel keeps the channel its filter passes."""
    if fmt == "L":
        gray = pixels if pixels.ndim == 2 else pixels[..., 0]
        return gray.astype(np.uint16) << 2
    if fmt in ("RGB", "RGBA"):
        if color_filter == "MONO":
            raise ForeignFormatError("color frames in a file imported as MONO; pass --color-filter")
        from evcap.events import pixel_channels

        h, w = pixels.shape[:2]
        yy, xx = np.mgrid[0:h, 0:w]
        channel = pixel_channels(xx.ravel(), yy.ravel(), color_filter).reshape(h, w)
        raw = np.take_along_axis(pixels[..., :3], channel[..., None].astype(np.intp), axis=2)
        return raw[..., 0].astype(np.uint16) << 2
    raise ForeignFormatError(f"frames in format {fmt!r} are not supported (L, RGB, RGBA are)")


def _first_timestamp(decoder_factory: Callable, stream_types: dict[int, str]) -> int:
    """The earliest timestamp of the file: the first element of each stream's first packet."""
    firsts: dict[int, int] = {}
    for packet in decoder_factory():
        sid = packet["stream_id"]
        if sid in firsts:
            if len(firsts) == len(stream_types):
                break
            continue
        if "events" in packet and len(packet["events"]):
            firsts[sid] = int(packet["events"]["t"][0])
        elif "frame" in packet:
            firsts[sid] = int(packet["frame"]["exposure_begin_t"])
        elif "imus" in packet and len(packet["imus"]):
            firsts[sid] = int(packet["imus"]["t"][0])
        elif "triggers" in packet and len(packet["triggers"]):
            firsts[sid] = int(packet["triggers"]["t"][0])
        if len(firsts) == len(stream_types):
            break
    return min(firsts.values()) if firsts else 0


def import_aedat4(
    src: str | os.PathLike,
    dst: str | os.PathLike,
    *,
    color_filter: str | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> ImportSummary:
    """Convert the AEDAT 4 file ``src`` into the session ``dst``.

    Timestamps become microseconds since the earliest timestamp in the file (t_offset_us).
    ``color_filter`` is the sensor's (e.g. "RGBG"); by default MONO, or RGBG when the file has
    color frames. The session is written to a temporary name and renamed when complete, so a
    failed import leaves nothing under ``dst``. ``progress(done, total)`` counts packet bytes.
    """
    import aedat

    src, dst = Path(src), Path(dst)
    check_output(dst, overwrite)
    if color_filter is not None:
        check_color_filter(color_filter)
    layout = read_layout(src)

    def decoder():
        try:
            return aedat.Decoder(str(src))
        except RuntimeError as e:
            raise ForeignFormatError(f"{src}: cannot read the AEDAT 4 file: {e}") from None

    streams = {sid: info for sid, info in decoder().id_to_stream().items()}
    types = {sid: info["type"] for sid, info in streams.items()}
    sized = [info for info in streams.values() if "width" in info]
    if not sized:
        raise ForeignFormatError(f"{src} has no event or frame stream: nothing to import")
    width, height = int(sized[0]["width"]), int(sized[0]["height"])
    if color_filter is None:
        color_filter = "MONO"
        for packet in decoder():
            if "frame" in packet:
                color_filter = "RGBG" if packet["frame"]["format"] != "L" else "MONO"
                break
    t_offset = _first_timestamp(decoder, types)
    sensor = _sensor_from_info(layout.info_xml, width, height, color_filter, t_offset)

    summary = ImportSummary(source=f"AEDAT 4, {sensor.sensor}")
    total = sum(size + 8 for _, _, size in layout.packets)
    done = 0
    attrs = {
        "source_file": src.name,
        "source_format": "AEDAT 4.0",
        "source_compression": layout.compression,
    }
    # DV writes 8-bit frames: 8 significant bits of the sensor's 10.
    with (
        partial_output(dst) as tmp,
        SessionWriter(tmp, sensor, attrs=attrs, overwrite=True, frame_bits=8) as writer,
    ):
        batch: list[np.ndarray] = []
        batch_n = 0
        try:
            for index, packet in enumerate(decoder()):
                if "events" in packet:
                    batch.append(packet["events"])
                    batch_n += packet["events"].size
                    if batch_n >= _EVENT_BATCH:
                        summary.events += _append_events(writer, batch, sensor)
                        batch, batch_n = [], 0
                elif "frame" in packet:
                    writer.append_frames(_frame(packet["frame"], sensor))
                    summary.frames += 1
                elif "imus" in packet:
                    imu = packet["imus"]
                    # DV stores libcaer's axes
                    accel = np.stack([imu[f"accelerometer_{a}"] for a in "xyz"], axis=1)
                    accel = accel * LIBCAER_TO_CAMERA
                    gyro = np.stack([imu[f"gyroscope_{a}"] for a in "xyz"], axis=1)
                    gyro = gyro * LIBCAER_TO_CAMERA
                    writer.append_imu(
                        ImuSamples(
                            imu["t"].astype(np.int64) - t_offset,
                            accel * STANDARD_GRAVITY,
                            np.deg2rad(gyro),
                            imu["temperature"],
                        )
                    )
                    summary.imu += imu.size
                elif "triggers" in packet:
                    trig = packet["triggers"]
                    writer.append_triggers(
                        Triggers(trig["t"].astype(np.int64) - t_offset, trig["source"])
                    )
                    summary.triggers += trig.size
                if index < len(layout.packets):
                    done += layout.packets[index][2] + 8
                if progress:
                    progress(done, total)
            if batch:
                summary.events += _append_events(writer, batch, sensor)
        except RuntimeError as e:
            raise ForeignFormatError(f"{src} is corrupt: {e}") from None
        except InputError as e:
            if isinstance(e, ForeignFormatError):
                raise
            raise ForeignFormatError(f"{src}: {e}") from None
    return summary


def _append_events(writer: SessionWriter, batch: list[np.ndarray], sensor: SensorInfo) -> int:
    """Append a batch of aedat event packets (absolute times) to the session."""
    ev = np.concatenate(batch)
    writer.append_events(
        Events(
            ev["x"],
            ev["y"],
            ev["t"].astype(np.int64) - sensor.t_offset_us,
            ev["p"].view(np.uint8),
            sensor.width,
            sensor.height,
            sensor.color_filter,
        )
    )
    return int(ev.size)


def _frame(frame: dict, sensor: SensorInfo) -> Frames:
    """One aedat frame as a full-sensor Frames (pixels outside its ROI are 0)."""
    full = np.zeros((sensor.height, sensor.width), np.uint16)
    raw = _mosaic(frame["pixels"], frame["format"], sensor.color_filter)
    x0, y0 = int(frame["offset_x"]), int(frame["offset_y"])
    if x0 < 0 or y0 < 0 or x0 + raw.shape[1] > sensor.width or y0 + raw.shape[0] > sensor.height:
        raise ForeignFormatError(
            f"a frame's ROI lies outside the {sensor.width} x {sensor.height} sensor"
        )
    full[y0 : y0 + raw.shape[0], x0 : x0 + raw.shape[1]] = raw
    begin = int(frame["exposure_begin_t"])
    return Frames(full[None], [begin - sensor.t_offset_us], [int(frame["exposure_end_t"]) - begin])
