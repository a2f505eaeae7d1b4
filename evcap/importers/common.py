"""What the importers share: the summary they return, the sensors they know by name, and how
they write their output."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path

from evcap.atomic_write import atomic_path
from evcap.errors import OutputExistsError


@dataclass
class ImportSummary:
    """What an import wrote."""

    events: int = 0
    frames: int = 0
    imu: int = 0
    triggers: int = 0
    source: str = ""  # the container and sensor, as the source states them
    notes: list[str] = field(default_factory=list)  # for the user: where a value came from
    warnings: list[str] = field(default_factory=list)  # for the user to check


# the sensors the sources name, with their pixel arrays (width, height)
SENSOR_SIZES = {
    "DVS128": (128, 128),
    "DAVIS240C": (240, 180),
    "DAVIS346": (346, 260),
}


def check_output(dst: Path, overwrite: bool) -> None:
    if dst.exists() and not overwrite:
        raise OutputExistsError(f"{dst} exists; choose another name or pass --force")


def partial_output(dst: Path) -> contextlib.AbstractContextManager[Path]:
    """A path beside ``dst`` to write the session to, renamed to ``dst`` when the block ends
    without an error: a failed import leaves nothing under ``dst``."""
    return atomic_path(dst)
