"""The batch's steps, each on one recording's folder OUTDIR/NAME and as the single commands do
them: the calibration applied, the poses, both stages of the reconstruction, the report.

The recording is copied to OUTDIR/NAME/session.h5 first (what the steps write goes there; the
original is only read). A step that ends is marked in OUTDIR/NAME/batch.json with its time and
what it made; a marked step whose outputs are there is not run again, and a step that runs again
unmarks those after it (their outputs were made from what it replaces).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path

from evcap.batch.manifest import Group, Recording

STEPS = ("calibrate", "poses", "reconstruct", "report")
STATE = "batch.json"
# the reconstruction's figures the summary shows (metrics.json's names)
FIGURES = (
    "object_psnr_cc",
    "object_psnr_constant",
    "normal_mae_deg",
    "depth_rel_err",
    "base_color_psnr_cc",
    "relit_object_psnr_cc",
)


@dataclass(frozen=True)
class Job:
    """One recording's work: where, and with which settings."""

    recording: Recording
    out: Path  # OUTDIR
    preset: str = "fast"
    device: str = "cpu"
    seed: int = 0
    cpus: int = 1  # threads each step may use (what its Ray task asks for)

    @property
    def folder(self) -> Path:
        return self.out / self.recording.name

    @property
    def session(self) -> Path:
        return self.folder / "session.h5"

    @property
    def reconstruction(self) -> Path:
        return self.folder / "reconstruction"


@dataclass
class StepResult:
    name: str  # the step's, or "calibration of GROUP"
    status: str  # "done", "done before", "failed", "not run", "stopped"
    seconds: float = 0.0
    summary: str = ""
    error: str = ""  # one line
    figures: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status in ("done", "done before")


def group_calibration(out: Path, group: Group) -> Path:
    """The group's calibration recording as calibrated: OUTDIR/calibration/NAME/session.h5."""
    return out / "calibration" / group.name / "session.h5"


def calibrate_group(out: Path, group: Group, cpus: int = 1) -> StepResult:
    """Calibrate the group's calibration recording (a copy of it) once; one that holds its
    /calibration already is taken as it is."""
    from evcap.calib.board import DEFAULT_BOARD, parse_board
    from evcap.calib.calibrate import calibrate, write_calibration
    from evcap.records import Calibration
    from evcap.session import Session

    name = f"calibration of {group.name}"
    target = group_calibration(out, group)
    state = _read_state(target.parent)
    if "calibrate" in state and target.exists():
        return StepResult(name, "done before", **_kept(state["calibrate"]))

    def work() -> str:
        _copy_session(group.calibration, target)
        with Session.open(target) as s:
            if Calibration.present(s):
                return f"{group.calibration.name}'s own /calibration, as it is"
        board = parse_board(group.board) if group.board else DEFAULT_BOARD
        cal = calibrate(target, board=board)
        write_calibration([target], cal)
        return cal.summary().replace("\n", "; ")

    return _run(name, target.parent, "calibrate", work, cpus)


def run_step(step: str, job: Job, before: StepResult | None = None) -> StepResult:
    """Run ``step`` on the job's recording unless it is done; ``before``: the result of what it
    waits for (the previous step, or the group's calibration), which must have gone well."""
    if before is not None and not before.ok:
        why = before.error if before.status == "not run" else f"{before.name} {before.status}"
        return StepResult(step, "not run", error=why)
    state = _read_state(job.folder)
    if step in state and _outputs_there(step, job):
        return StepResult(step, "done before", **_kept(state[step]))
    work = {
        "calibrate": _apply_calibration,
        "poses": _poses,
        "reconstruct": _reconstruct,
        "report": _report,
    }[step]
    return _run(step, job.folder, step, lambda: work(job), job.cpus)


def _run(name: str, folder: Path, key: str, work, cpus: int) -> StepResult:
    """Run ``work`` (returns its one-line summary, or a (summary, figures) pair) and mark it
    done in ``folder``'s state; an error becomes the result's one-line message."""
    _use_threads(cpus)
    started = time.perf_counter()
    try:
        made = work()
    except KeyboardInterrupt:
        return StepResult(name, "stopped", time.perf_counter() - started, error="interrupted")
    except Exception as e:  # any failure is this recording's; the others go on
        return StepResult(name, "failed", time.perf_counter() - started, error=one_line(e))
    summary, figures = made if isinstance(made, tuple) else (made, {})
    if summary is None:  # the work was interrupted and kept what it had (reconstruct)
        return StepResult(name, "stopped", time.perf_counter() - started, error="interrupted")
    result = StepResult(name, "done", time.perf_counter() - started, summary, figures=figures)
    state = _read_state(folder)
    if key in STEPS:  # what comes after was made from what this step replaced
        for later in STEPS[STEPS.index(key) + 1 :]:
            state.pop(later, None)
    state[key] = {"seconds": result.seconds, "summary": summary, "figures": figures}
    _write_state(folder, state)
    return result


def _apply_calibration(job: Job) -> str:
    from evcap.records import Calibration
    from evcap.session import Session

    group = job.recording.group
    if group.calibration is None:
        raise ValueError("its group names no calibration recording")
    _copy_session(job.recording.path, job.session)
    with Session.open(group_calibration(job.out, group)) as s:
        cal = Calibration.read(s)
    with Session.open(job.session) as s:
        size = (s.sensor.width, s.sensor.height)
    if size != (cal.width, cal.height):
        raise ValueError(
            f"its sensor is {size[0]} x {size[1]}; the calibration "
            f"({group.calibration.name}) is for {cal.width} x {cal.height}"
        )
    cal.write(job.session, replace=True)
    return f"the calibration of {group.calibration.name} applied"


def _poses(job: Job) -> str:
    from evcap.poses.estimate import estimate_poses, write_poses

    _copy_session(job.recording.path, job.session)
    result = estimate_poses(job.session, threads=job.cpus)
    write_poses(job.session, result)
    return result.summary()


def _reconstruct(job: Job) -> tuple[str | None, dict]:
    from evcap.recon.reconstruct import reconstruct

    _copy_session(job.recording.path, job.session)
    m = reconstruct(
        job.session,
        job.reconstruction,
        preset=job.preset,
        device=job.device,
        seed=job.seed,
        overwrite=True,
    )
    if m.interrupted:  # its state is saved: the next run goes on from it
        return None, {}
    found = {k: v for k, v in asdict(m.figures).items() if k in FIGURES and v is not None}
    summary = f"{m.gaussians:,} Gaussians, {m.iterations} + {m.material_iterations} steps"
    return summary, found


def _report(job: Job) -> str:
    from evcap.report.html import write_report

    page = write_report(job.reconstruction, job.session)
    shutil.copyfile(page, job.folder / "report.html")
    return f"report.html ({page.stat().st_size / 1e6:.1f} MB)"


def _outputs_there(step: str, job: Job) -> bool:
    if not job.session.exists():
        return False
    if step == "reconstruct":
        return (job.reconstruction / "metrics.json").exists()
    if step == "report":
        return (job.folder / "report.html").exists()
    from evcap.records import Calibration, Poses
    from evcap.session import Session

    with Session.open(job.session, validate=False) as s:
        return Calibration.present(s) if step == "calibrate" else Poses.present(s)


def _copy_session(source: Path, target: Path) -> None:
    """``source``, checked as a session (a corrupt recording fails here, named), copied to
    ``target`` once; the copy takes its name only when it is whole."""
    from evcap.session import Session

    if target.exists():
        return
    Session.open(source).close()
    target.parent.mkdir(parents=True, exist_ok=True)
    part = target.with_name(target.name + ".part")
    shutil.copyfile(source, part)
    part.replace(target)


def _use_threads(cpus: int) -> None:
    """The step's libraries keep to the cores its task was given."""
    import numba
    import torch

    torch.set_num_threads(cpus)
    numba.set_num_threads(min(cpus, numba.config.NUMBA_NUM_THREADS))
    os.environ["OMP_NUM_THREADS"] = str(cpus)


def one_line(e: BaseException) -> str:
    """The error in one line, without terminal colors."""
    text = " ".join(re.sub(r"\x1b\[[0-9;]*m", "", str(e)).split()) or type(e).__name__
    frames = traceback.extract_tb(e.__traceback__)
    if frames and not isinstance(e, OSError | ValueError | RuntimeError):  # not ours: where
        text = f"{type(e).__name__}: {text} ({Path(frames[-1].filename).name}:{frames[-1].lineno})"
    return text


def _kept(mark: dict) -> dict:
    return {k: mark.get(k, d) for k, d in (("seconds", 0.0), ("summary", ""), ("figures", {}))}


def _read_state(folder: Path) -> dict:
    try:
        return json.loads((folder / STATE).read_text())
    except (OSError, ValueError):  # none yet, or damaged: the steps run again
        return {}


def _write_state(folder: Path, state: dict) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    write_whole(folder / STATE, json.dumps(state, indent=1))


def write_whole(path: Path, text: str) -> None:
    """``text`` into ``path``, which takes its name only when written whole."""
    part = path.with_name(path.name + ".part")
    part.write_text(text, encoding="utf-8")
    part.replace(path)
