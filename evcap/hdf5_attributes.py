"""HDF5 attribute values both ways: what h5py is given to store, and the Python values read back.

The one place that converts them, so that every writer and reader of session and truth files
agrees on strings, numbers and arrays.
"""

from __future__ import annotations

from typing import Any

import h5py
import numpy as np


def to_hdf5(value: object) -> object:
    """``value`` as HDF5 stores it: numbers and strings as they are, anything else (lists,
    tuples, arrays) as a numpy array."""
    if isinstance(value, str | int | float | bool | np.integer | np.floating):
        return value
    return np.asarray(value)


def from_hdf5(value: object) -> object:
    """A stored attribute value as Python's: bytes decoded, numpy scalars as Python scalars;
    arrays as they are."""
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value


def read_attributes(obj: h5py.HLObject) -> dict[str, Any]:
    """All attributes of an HDF5 file, group or dataset, as Python values."""
    return {key: from_hdf5(value) for key, value in obj.attrs.items()}
