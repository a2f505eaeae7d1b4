"""Each step's work, wired once: what `evcap calibrate`, `evcap poses`, `evcap reconstruct` and
`evcap report` run, and what the Pipeline runs in a workspace (pipeline.py). Each takes its
paths and options as arguments, says what it does through ``say`` and shows its progress
through ``progress`` (a description -> a context manager that gives update(done, total,
status)); it writes what it made (the session's group, the reconstruction folder, the page) and
returns it, and the caller says it in its own words. A step's libraries are imported when it
runs."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from evcap.errors import InputError

if TYPE_CHECKING:
    from evcap.calib.board import Board
    from evcap.calib.calibrate import CalibrationRun
    from evcap.poses.estimate import PosesResult
    from evcap.recon.options import ReconstructOptions
    from evcap.records import ReconstructionResult

# a description -> a context manager that gives update(done, total, status)
Progress = Callable[[str], contextlib.AbstractContextManager[Callable[..., None]]]
Say = Callable[[str], None]


@contextlib.contextmanager
def no_progress(description: str) -> Iterator[Callable[..., None]]:
    yield lambda *args: None


def _silent(line: str) -> None:
    """Say nothing."""


def calibrate_step(
    session: str | Path,
    *,
    board: Board | None = None,
    also: Iterable[str | Path] = (),
    skip: frozenset[str] = frozenset(),
    intrinsics: str | Path | None = None,
    camera: str | None = None,
    say: Say = _silent,
    progress: Progress = no_progress,
) -> CalibrationRun:
    """Measure the session's calibration (``board``: the ChArUco board filmed, default the
    printable one; ``skip``: parts kept as the session holds them; ``intrinsics``: another
    tool's calibration file to take them from instead, ``camera`` the one of a file holding
    several) and write it to its /calibration and to that of each session of ``also`` (the
    same camera and biases); every one of them, and the file, is checked first, before
    minutes of work."""
    from evcap.calib.board import DEFAULT_BOARD
    from evcap.calib.calibrate import calibrate, check_targets, write_calibration
    from evcap.importers.calibration_files import read_calibration_file

    if camera is not None and intrinsics is None:
        raise InputError("--camera picks a camera of an --intrinsics file: give the file")
    targets = list(dict.fromkeys(Path(p) for p in (session, *also)))
    check_targets(targets)
    known = None if intrinsics is None else read_calibration_file(intrinsics, camera)
    with progress("calibrating") as update:
        cal = calibrate(
            session,
            board=board or DEFAULT_BOARD,
            skip=skip,
            intrinsics=known,
            say=say,
            progress=update,
        )
    write_calibration(targets, cal)
    return cal


def poses_step(
    session: str | Path,
    *,
    say: Say = _silent,
    progress: Progress = no_progress,
    **options: Any,
) -> PosesResult:
    """Estimate the camera's path from the session's events and write it to the session's
    /poses. ``options``: evcap.poses.estimate.estimate_poses's (kind, weights, rate_hz,
    export_frames, gravity, gyro, aps, threads)."""
    from evcap.poses.estimate import estimate_poses, write_poses

    with progress("poses") as update:
        result = estimate_poses(session, say=say, progress=update, **options)
    write_poses(session, result)
    return result


def reconstruct_step(
    session: str | Path,
    out: str | Path,
    options: ReconstructOptions,
    *,
    say: Say = _silent,
    progress: Progress = no_progress,
) -> ReconstructionResult:
    """Reconstruct the session into the folder ``out`` as the options record says: the one
    call of evcap.recon.reconstruct.reconstruct, for `evcap reconstruct` and the Pipeline
    alike."""
    from evcap.recon.options import Feedback
    from evcap.recon.reconstruct import reconstruct

    with progress(f"reconstructing ({options.preset})") as update:
        return reconstruct(session, out, options, Feedback(say, update))


def report_step(out: str | Path, session: str | Path | None = None) -> Path:
    """Write the report of the reconstruction folder ``out`` and its session (default: the one
    it was made from): one self-contained page; returns its path (OUT/report.html)."""
    from evcap.report.html import write_report

    return write_report(out, session)
