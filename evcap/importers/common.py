"""What the importers share: the summary they return and the sensors they know by name."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class ImportSummary:
    """What an import wrote."""

    events: int = 0
    frames: int = 0
    imu: int = 0
    triggers: int = 0
    source: str = ""  # the container and sensor, as the source states them


# the sensors the sources name, with their pixel arrays (width, height)
SENSOR_SIZES = {
    "DVS128": (128, 128),
    "DAVIS240C": (240, 180),
    "DAVIS346": (346, 260),
}
