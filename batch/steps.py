"""The batch's work on one recording: the pipeline (evcap.pipeline) in the recording's
workspace OUTDIR/NAME, the recording copied in as OUTDIR/NAME/session.h5 (the original is only
read), and each group's calibration recording calibrated once, in OUTDIR/calibration/GROUP/.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from evcap.batch.manifest import Group, Recording
from evcap.pipeline import Pipeline, Settings, Step, StepResult, Workspace
from evcap.recon.options import ReconstructOptions

START_OVER = "delete it to start the recording over"


@dataclass(frozen=True)
class Job:
    """One recording's work: where, and with which settings."""

    recording: Recording
    out: Path  # OUTDIR
    options: ReconstructOptions = ReconstructOptions()  # the reconstruction's
    cpus: int = 1  # threads each step may use (what its Ray task asks for)

    @property
    def workspace(self) -> Workspace:
        group = self.recording.group
        calibration = group_workspace(self.out, group).session if group.calibration else None
        return Workspace(
            self.out / self.recording.name, source=self.recording.path, calibration=calibration
        )

    @property
    def settings(self) -> Settings:
        return Settings(reconstruct=self.options, cpus=self.cpus)


def group_workspace(out: Path, group: Group) -> Workspace:
    """The group's calibration recording as calibrated: OUTDIR/calibration/NAME/session.h5,
    its own calibration recording."""
    root = out / "calibration" / group.name
    return Workspace(root, source=group.calibration, calibration=root / "session.h5")


def calibrate_group(out: Path, group: Group, cpus: int = 1) -> StepResult:
    """Calibrate the group's calibration recording (a copy of it) once; one that holds its
    /calibration already is taken as it is."""
    pipeline = Pipeline(
        group_workspace(out, group), Settings(board=group.board, cpus=cpus), hint=START_OVER
    )
    result = pipeline.run_step("calibrate")
    result.name = f"calibration of {group.name}"
    return result


def run_step(step: Step, job: Job, before: StepResult | None = None) -> StepResult:
    """Run ``step`` on the job's recording unless it is done; ``before``: the result of what it
    waits for (the previous step, or the group's calibration), which must have gone well."""
    return Pipeline(job.workspace, job.settings, hint=START_OVER).run_step(step, before)
