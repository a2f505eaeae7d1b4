"""The bytes of a session's compressed chunks: HDF5's shuffle filter, then its deflate filter.

The session writer compresses chunks itself (in worker threads) and hands HDF5 the finished
bytes, so that the file holds standard shuffle + deflate chunks that any HDF5 reader opens
without plugins. The deflate streams are made by ISA-L (Intel's igzip, through ``isal``), which
makes ordinary zlib streams 5 to 6 times faster than zlib on shuffled event fields, and smaller
(docs/session-format.md has the measurements). ``compress_reference`` makes the same chunks
with Python's zlib: the slow, obviously right path the fast one is tested against.
"""

from __future__ import annotations

import zlib

import numpy as np
from isal import isal_zlib

LEVEL = 1
"""ISA-L's level (0..3): 1 compresses shuffled event fields as well as 2 and 3, at full speed."""
REFERENCE_LEVEL = 1
"""zlib's level in the reference path (what sessions were written with before ISA-L)."""


def shuffled(a: np.ndarray) -> np.ndarray:
    """The bytes of ``a`` as HDF5's shuffle filter arranges them: byte planes, the lowest
    byte of every element first (a 1-byte type is left as it is)."""
    a = np.ascontiguousarray(a)
    if a.itemsize == 1:
        return a.reshape(-1).view(np.uint8)
    return np.ascontiguousarray(a.reshape(-1).view(np.uint8).reshape(-1, a.itemsize).T)


def compress(a: np.ndarray) -> bytes:
    """One chunk's bytes on disk: ``a`` shuffled and deflated (ISA-L; releases the GIL)."""
    return isal_zlib.compress(shuffled(a), LEVEL)


def compress_reference(a: np.ndarray) -> bytes:
    """The same chunk through Python's zlib (run-length strategy, as evcap wrote before)."""
    deflate = zlib.compressobj(REFERENCE_LEVEL, zlib.DEFLATED, 15, 8, zlib.Z_RLE)
    return deflate.compress(shuffled(a)) + deflate.flush()


def decompress(data: bytes, dtype: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    """A chunk's values back from its bytes on disk (what HDF5's filters do when reading)."""
    dtype = np.dtype(dtype)
    planes = np.frombuffer(zlib.decompress(data), np.uint8)
    if dtype.itemsize == 1:
        return planes.view(dtype).reshape(shape)
    return np.ascontiguousarray(planes.reshape(dtype.itemsize, -1).T).view(dtype).reshape(shape)
