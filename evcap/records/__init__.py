"""The records the steps exchange through a session and a reconstruction folder, each the one
reader and writer of its group or files: /calibration, /poses, /gt, and OUT/ (the
reconstruction folder, with its metrics.json)."""

from evcap.records.calibration import Calibration, read_intrinsics
from evcap.records.poses import Poses
from evcap.records.reconstruction_folder import ReconstructionFolder
from evcap.records.result import Figures, ReconstructionResult
from evcap.records.truth import GroundTruth, TruthViews

__all__ = [
    "Calibration",
    "Figures",
    "GroundTruth",
    "Poses",
    "ReconstructionFolder",
    "ReconstructionResult",
    "TruthViews",
    "read_intrinsics",
]
