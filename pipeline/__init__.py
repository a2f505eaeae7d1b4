"""evcap.pipeline: one recording's way through the steps, the level that the application
(evcap.app: `evcap demo` and the single-step commands) and `evcap batch` (evcap.batch) both
stand on.

- workspace.py: a recording's folder (Workspace) and what the steps are run with (Settings).
- steps.py: each step's work, wired once and called by both the single-step commands and the
  Pipeline: calibrate_step, poses_step, reconstruct_step (the one call of
  evcap.recon.reconstruct.reconstruct), report_step.
- pipeline.py: the steps of a workspace in order (Pipeline), its one state file and the one rule
  for what a rerun redoes, and each step's result (StepResult).

It imports the spine (evcap's own modules) and the steps (calib, poses, recon, report), never
evcap.app or evcap.batch (the import-linter contracts in pyproject.toml check it). It stays light
when imported: a step's libraries are imported when the step runs, so `evcap --help` stays quick.
"""

from evcap.pipeline.pipeline import (
    STEPS,
    Made,
    Pipeline,
    PipelineInterrupted,
    Status,
    Step,
    StepDefinition,
    StepResult,
    figures_line,
    one_line,
    use_threads,
)
from evcap.pipeline.steps import (
    Progress,
    calibrate_step,
    no_progress,
    poses_step,
    reconstruct_step,
    report_step,
)
from evcap.pipeline.workspace import STATE, Settings, Workspace

__all__ = [
    "STATE",
    "STEPS",
    "Made",
    "Pipeline",
    "PipelineInterrupted",
    "Progress",
    "Settings",
    "Status",
    "Step",
    "StepDefinition",
    "StepResult",
    "Workspace",
    "calibrate_step",
    "figures_line",
    "no_progress",
    "one_line",
    "poses_step",
    "reconstruct_step",
    "report_step",
    "use_threads",
]
