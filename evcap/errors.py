"""The exception hierarchy: one root, subclasses that are also the matching built-ins.

Callers can catch ``EvcapError`` for anything evcap raises on purpose, or the built-in they
already handle (``ValueError``, ``OSError``, ``FileNotFoundError``). The CLI turns an
``InputError`` into a one-line message and exit status 2.
"""

from __future__ import annotations


class EvcapError(Exception):
    """Root of every error evcap raises on purpose."""


class InputError(EvcapError, ValueError):
    """The input given by the user is wrong: a bad file, a bad option, bad data."""


class InputNotFoundError(InputError, FileNotFoundError):
    """An input file does not exist."""


class OutputExistsError(InputError, FileExistsError):
    """An output file already exists and overwriting was not asked for."""


class SessionFormatError(InputError):
    """A session file is not valid: wrong schema, missing datasets, corrupt or truncated."""


class CalibrationError(InputError):
    """A calibration the recording cannot give (no board seen, too little data)."""


class PosesError(InputError):
    """Poses the recording cannot give (structure from motion failed)."""


class ForeignFormatError(InputError):
    """A file to import is not in the expected format, or is corrupt or truncated."""


class SessionWriteError(EvcapError, OSError):
    """Writing a session failed (disk full, I/O error); what was flushed before is kept."""


class DiskFullError(SessionWriteError):
    """The disk ran (almost) full; the recording was stopped and its session closed."""


class DeviceError(EvcapError, OSError):
    """The camera cannot be used: not found, no permission, wrong firmware, USB failure."""


class DeviceNotFoundError(DeviceError):
    """No camera matches."""


class DevicePermissionError(DeviceError, PermissionError):
    """The camera is there but this user may not open it (udev rule missing)."""


class FirmwareError(DeviceError):
    """The camera's firmware or FPGA logic version is not the one evcap speaks."""


class DeviceLostError(DeviceError):
    """The camera vanished (unplugged) while in use."""


class NumericalError(EvcapError, FloatingPointError):
    """An optimisation stopped making finite numbers (NaN or infinity)."""
