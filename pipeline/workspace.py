"""A recording's folder as the pipeline keeps it (Workspace), and what its steps are run with
(Settings)."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from evcap.atomic_write import atomic_path
from evcap.recon.options import ReconstructOptions

if TYPE_CHECKING:  # the records (numpy, h5py) wait for a step: `evcap --help` stays quick
    from evcap.records import ReconstructionFolder

STATE = "pipeline.json"  # the workspace's state file (pipeline.py reads and writes it)


@dataclass(frozen=True)
class Settings:
    """What the steps are run with; all but ``cpus`` (and the reconstruction's resume policy,
    the pipeline's own) are held in the state, and a workspace is only gone on with under the
    same."""

    # the reconstruction's options (its relight image relative to the workspace's folder
    # unless absolute)
    reconstruct: ReconstructOptions = ReconstructOptions()
    board: str | None = None  # the ChArUco board, when the calibration is measured (calib)
    cpus: int | None = None  # threads each step may use (None: as the libraries choose)

    def held(self) -> dict:
        return {"reconstruct": self.reconstruct.held(), "board": self.board}


@dataclass(frozen=True)
class Workspace:
    """A recording's folder: ROOT/SESSION (the session the steps write to: a copy of ``source``
    when one is given), ROOT/reconstruction/, ROOT/report.html, and the state file.
    ``calibration``: the recording whose calibration the calibrate step applies (measured
    first when it holds none); the session itself when it is its own."""

    root: Path
    session_name: str = "session.h5"
    source: Path | None = None
    calibration: Path | None = None

    @property
    def session(self) -> Path:
        return self.root / self.session_name

    @property
    def reconstruction(self) -> ReconstructionFolder:
        from evcap.records import ReconstructionFolder

        return ReconstructionFolder(self.root / "reconstruction")

    @property
    def report(self) -> Path:
        """The reconstruction's report, copied beside the session."""
        return self.root / self.reconstruction.report.name

    @property
    def state(self) -> Path:
        return self.root / STATE

    def holds(self, record: Literal["calibration", "poses"]) -> bool:
        """The session is there and holds that record's group."""
        from evcap.records import Calibration, Poses
        from evcap.session import Session

        if not self.session.exists():
            return False
        with Session.open(self.session, validate=False) as s:
            return (Calibration if record == "calibration" else Poses).present(s)

    def copy_source(self) -> None:
        """The source recording, checked as a session (a corrupt one fails here, named),
        copied to the session once; the copy takes its name only when it is whole."""
        from evcap.session import Session

        if self.source is None or self.session.exists():
            return
        Session.open(self.source).close()
        with atomic_path(self.session) as partial:
            shutil.copyfile(self.source, partial)
