"""Compression of the session's event fields, compared, for bench/record_throughput.py.

Each row compresses the x, y, t and p chunks of a decoded stream on one core: the deflate
streams that evcap makes itself (its writer's worker threads, chunk_codec: shuffle, then
zlib or ISA-L), and, where hdf5plugin is installed, the filters of the field that it brings
(Blosc, Blosc2, LZ4, Zstd, Bitshuffle), through HDF5's own filter pipeline into an in-memory
file (with HDF5's built-in gzip as the yardstick of that path). Figures: M events/s on one
core, bytes per event on disk, and what a reader needs to open the file.
"""

from __future__ import annotations

import io
import time
import zlib
from collections.abc import Callable

import h5py
import numpy as np
from isal import isal_zlib

from evcap import chunk_codec
from evcap.events import Events

FIELDS = {"x": np.uint16, "y": np.uint16, "t": np.int64, "p": np.uint8}
ANY_READER = "any HDF5 reader"
PLUGIN_READER = "import hdf5plugin"


def _fields(events: Events, chunk: int) -> dict[str, list[np.ndarray]]:
    n = len(events) // chunk * chunk
    return {
        k: [getattr(events, k)[i : i + chunk].astype(dt) for i in range(0, n, chunk)]
        for k, dt in FIELDS.items()
    }


def _direct(compress: Callable[[np.ndarray], bytes], chunks: dict, rounds: int) -> tuple:
    best, size = float("inf"), 0
    for _ in range(rounds):
        begin = time.perf_counter()
        size = sum(len(compress(c)) for parts in chunks.values() for c in parts)
        best = min(best, time.perf_counter() - begin)
    return best, size


def _pipeline(options: dict, chunks: dict, rounds: int) -> tuple:
    best, size = float("inf"), 0
    for _ in range(rounds):
        with h5py.File(io.BytesIO(), "w") as f:
            begin = time.perf_counter()
            for name, parts in chunks.items():
                n = len(parts[0])
                d = f.create_dataset(
                    name, (n * len(parts),), parts[0].dtype, chunks=(n,), **options
                )
                for i, c in enumerate(parts):
                    d[i * n : (i + 1) * n] = c
            f.flush()
            best = min(best, time.perf_counter() - begin)
            size = sum(f[name].id.get_storage_size() for name in chunks)
    return best, size


def _zlib(level: int, strategy: int) -> Callable[[np.ndarray], bytes]:
    def compress(a: np.ndarray) -> bytes:
        z = zlib.compressobj(level, zlib.DEFLATED, 15, 8, strategy)
        return z.compress(chunk_codec.shuffled(a)) + z.flush()

    return compress


def _isal(level: int) -> Callable[[np.ndarray], bytes]:
    return lambda a: isal_zlib.compress(chunk_codec.shuffled(a), level)


def _plugin_rows() -> list[tuple[str, dict]]:
    try:
        import hdf5plugin as h
    except ImportError:
        return []
    b, b2 = h.Blosc, h.Blosc2
    return [
        ("Blosc LZ4 + shuffle", b("lz4", 5, b.SHUFFLE)),
        ("Blosc LZ4 + bitshuffle", b("lz4", 5, b.BITSHUFFLE)),
        ("Blosc Zstd 1 + shuffle (DSEC's filter)", b("zstd", 1, b.SHUFFLE)),
        ("Blosc Zstd 1 + bitshuffle", b("zstd", 1, b.BITSHUFFLE)),
        ("Blosc2 LZ4 + shuffle", b2("lz4", 5, b2.SHUFFLE)),
        ("Blosc2 Zstd 1 + bitshuffle", b2("zstd", 1, b2.BITSHUFFLE)),
        ("LZ4", h.LZ4()),
        ("Zstd 1", h.Zstd(1)),
        ("Bitshuffle + LZ4", h.Bitshuffle(cname="lz4")),
    ]


def compare(events: Events, rounds: int = 2) -> list[dict]:
    """The rows of the comparison (see the module's docstring) on ``events``."""
    chunk = 1 << 17
    chunks = _fields(events, chunk)
    n = sum(len(c) for c in chunks["t"])
    if n == 0:
        return []
    rows = []

    def row(name: str, timing: tuple, reader: str, chunk_events: int = chunk) -> None:
        seconds, size = timing
        rows.append(
            {
                "codec": name,
                "chunk_events": chunk_events,
                "Mev_per_s_one_core": n / seconds / 1e6,
                "bytes_per_event": size / n,
                "readers_need": reader,
            }
        )

    row(
        "zlib 1, run-length + shuffle (evcap before)",
        _direct(_zlib(1, zlib.Z_RLE), chunks, rounds),
        ANY_READER,
    )
    row("zlib 1 + shuffle", _direct(_zlib(1, zlib.Z_DEFAULT_STRATEGY), chunks, rounds), ANY_READER)
    for level in range(4):
        row(f"ISA-L {level} + shuffle", _direct(_isal(level), chunks, rounds), ANY_READER)
    for size in (1 << 15, 1 << 19):
        other = _fields(events, size)
        if other["t"]:
            m = sum(len(c) for c in other["t"])
            seconds, nbytes = _direct(chunk_codec.compress, other, rounds)
            row(
                f"ISA-L {chunk_codec.LEVEL} + shuffle",
                (seconds * n / m, nbytes * n / m),
                ANY_READER,
                size,
            )
    gzip = {"compression": "gzip", "compression_opts": 1, "shuffle": True}
    row("HDF5 pipeline: gzip 1 + shuffle", _pipeline(gzip, chunks, rounds), ANY_READER)
    for name, options in _plugin_rows():
        row(f"HDF5 pipeline: {name}", _pipeline(dict(options), chunks, rounds), PLUGIN_READER)
    return rows
