"""The reconstruction's compiled CPU kernels, made ahead in a second process.

numba compiles each kernel at its first call and caches it beside the code: on a fresh install
that is about 100 s of one core, once. `evcap demo` starts this process first, so that the
kernels compile on one core while the other replays, calibrates and poses the captures; the
reconstruction then finds them in the cache. The process reconstructs a few steps of both
stages of the demo's own scene on the truth's poses, in a temporary folder: the kernels
compiled are the reconstruction's own, for the same kinds of arrays.

    python -m evcap.app.compile_ahead FIXTURES PRESET
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import IO

from evcap.recon.config import Preset


class KernelsAhead:
    """The compiling process, once started (its output discarded, its errors kept in a
    temporary file, not a pipe that could fill and stall it): started by the demo's first
    step, waited for before the reconstruction, ended if the demo ends first."""

    def __init__(self) -> None:
        self.process: subprocess.Popen | None = None
        self.errors: IO[bytes] | None = None
        self.started = 0.0

    def start(self, fixtures: Path, preset: Preset) -> str:
        self.started = time.perf_counter()
        # open while the process runs: read and closed when it is waited for or ended
        self.errors = tempfile.TemporaryFile()  # noqa: SIM115
        command = [sys.executable, "-m", "evcap.app.compile_ahead", str(fixtures), preset]
        self.process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=self.errors)
        return "started"

    def finish(self) -> str:
        """Wait for it; what it did, in a line. A failure is said, not raised: the
        reconstruction then compiles what it needs itself."""
        if self.process is None or self.errors is None:  # the demo went on from an earlier run
            return "not compiled ahead in this run; the reconstruction compiles what it lacks"
        self.process.wait()
        waited = time.perf_counter() - self.started
        self.errors.seek(0)
        lines = self.errors.read().decode(errors="replace").strip().splitlines()
        self.errors.close()
        if self.process.returncode != 0:
            why = lines[-1] if lines else f"exit status {self.process.returncode}"
            return f"not compiled ahead ({why}); the reconstruction compiles them itself"
        return f"compiled in the background, done {waited:.0f} s after the demo started"

    def stop(self) -> None:
        """End it if it still runs."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()
        if self.errors is not None:
            self.errors.close()


def compile_kernels(fixtures: Path, preset: Preset) -> None:
    """Record the demo's scene, give it the truth's poses and a calibration of the kinds
    `evcap calibrate` writes (its values do not matter here: the kernels are compiled for the
    kinds of arrays, not their values) and run both stages of the preset for a few steps,
    refining the poses as on estimated ones."""
    import numpy as np

    from evcap.app.demo import SCENE, record_fixture
    from evcap.recon.options import ReconstructOptions
    from evcap.recon.reconstruct import reconstruct
    from evcap.records import Calibration, GroundTruth
    from evcap.session import Session
    from evcap.sim.truth import copy_truth

    with tempfile.TemporaryDirectory() as tmp:
        session = Path(tmp) / "scene.h5"
        record_fixture(fixtures / SCENE, session)
        copy_truth(fixtures / SCENE / "truth.h5", session, poses=True, replace=True)
        with Session.open(session) as s:
            K, (w, h) = GroundTruth.read(s).K, (s.sensor.width, s.sensor.height)
        ones = np.ones((h, w), np.float32)
        Calibration(
            w,
            h,
            "compile ahead: a stand-in",
            K=K,
            distortion_model="radtan",
            dist=np.array([-0.4, 0.3, 0.0, 0.0, 0.0]),
            threshold_on=0.2 * ones,
            threshold_off=0.2 * ones,
            threshold_confidence=ones,
            hot_pixels=np.zeros((h, w), bool),
            event_rate_hz=ones,
        ).write(session)
        steps = {"stage1.iterations": 3, "stage2.iterations": 2, "stage1.poses.refine": "on"}
        options = ReconstructOptions(preset=preset, settings=steps)
        reconstruct(session, Path(tmp) / "reconstruction", options)


if __name__ == "__main__":
    compile_kernels(Path(sys.argv[1]), sys.argv[2])  # type: ignore[arg-type]
