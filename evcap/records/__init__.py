"""The records the steps exchange through a session and a reconstruction folder, each the one
reader and writer of its group or file: /calibration, /poses, /gt and OUT/metrics.json."""

from evcap.records.calibration import Calibration, read_intrinsics
from evcap.records.poses import Poses
from evcap.records.result import Figures, ReconstructionResult
from evcap.records.truth import GroundTruth, TruthViews

__all__ = [
    "Calibration",
    "Figures",
    "GroundTruth",
    "Poses",
    "ReconstructionResult",
    "TruthViews",
    "read_intrinsics",
]
