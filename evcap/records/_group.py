"""What the records share: finding their group in a session or in any HDF5 file (a truth
file), and reading its arrays with errors that name the file and the dataset."""

from __future__ import annotations

import h5py
import numpy as np

from evcap.errors import InputError
from evcap.session import Session

Source = Session | h5py.Group  # an open session, or an open HDF5 file or group


def find_group(source: Source, name: str) -> h5py.Group | None:
    """The group /``name`` of ``source``, or None when it has none."""
    if isinstance(source, Session):
        return source.group(name) if name in source.groups else None
    item = source.get(name)
    return item if isinstance(item, h5py.Group) else None


def path_of(source: Source) -> str:
    return str(source.path if isinstance(source, Session) else source.file.filename)


def where(source: Source, name: str) -> str:
    """ "FILE: /name", for errors."""
    return f"{path_of(source)}: /{name}"


def array(
    g: h5py.Group, name: str, place: str, dtype=np.float64, shape: tuple | None = None
) -> np.ndarray:
    """The dataset ``name`` of ``g`` as ``dtype``, checked numeric, finite and (``shape``:
    None for any length on that axis) of that shape."""
    try:
        a = np.asarray(g[name][()], dtype)
    except (TypeError, ValueError) as e:
        raise InputError(f"{place}/{name} holds values that are not numbers ({e})") from None
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise InputError(f"{place}/{name} holds NaN or infinite values")
    if shape is not None and (
        a.ndim != len(shape)
        or any(s is not None and s != n for s, n in zip(shape, a.shape, strict=True))
    ):
        expected = " x ".join("N" if s is None else str(s) for s in shape)
        raise InputError(f"{place}/{name} should be {expected}, is {' x '.join(map(str, a.shape))}")
    return a


def optional(g: h5py.Group, name: str, place: str, dtype=np.float64, shape=None):
    """``array`` where ``g`` has the dataset, else None."""
    return array(g, name, place, dtype, shape) if name in g else None
