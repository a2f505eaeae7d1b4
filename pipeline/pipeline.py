"""One recording's way through the steps, as `evcap demo` and `evcap batch` run it: the steps of
a workspace (calibrate, poses, reconstruct, report) in order, one state file, and one rule for
what a rerun redoes.

Each step that ends is marked in the workspace's state file with its time, what it made and its
figures. A marked step whose outputs are there is not run again; a step that runs again unmarks
those after it (their outputs were made from what it replaces). The state also holds the
settings the workspace was made with; another run with other settings is refused.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal, get_args

from evcap.atomic_write import atomic_path, write_text_atomic
from evcap.errors import InputError
from evcap.pipeline import steps as work  # each step's work, wired once
from evcap.pipeline.steps import Progress, no_progress
from evcap.pipeline.workspace import Settings, Workspace

Step = Literal["calibrate", "poses", "reconstruct", "report"]
STEPS: tuple[Step, ...] = get_args(Step)
Status = Literal["done", "done before", "failed", "not run", "stopped"]
# how a user names the held options (a batch's board is its manifest's)
FLAGS = {"preset": "--preset", "device": "--device", "seed": "--seed", "relight": "--relight"}
FLAGS |= {"backend": "--backend", "ablate": "--without", "stage": "--stage"}

# what a step's work returns: its one-line summary (None: it was stopped and kept what it had),
# or the summary and its figures
Made = str | None | tuple[str | None, dict[str, float]]


class PipelineInterrupted(KeyboardInterrupt):
    """A step was stopped (Ctrl-C); what the steps before it made is kept."""


@dataclass
class StepResult:
    name: str  # the step's, or what the caller calls it
    status: Status
    seconds: float = 0.0
    summary: str = ""
    error: str = ""  # one line
    figures: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status in ("done", "done before")


@dataclass
class StepDefinition:
    """A step of a pipeline: what it does and whether what it made is there."""

    name: str
    work: Callable[[], Made]
    made: Callable[[], bool]


class Pipeline:
    """The steps of one workspace, in order. ``hint``: how to start the workspace over, said
    when its state cannot be gone on with."""

    def __init__(
        self,
        workspace: Workspace,
        settings: Settings | None = None,
        *,
        say: Callable[[str], None] = lambda line: None,
        progress: Progress | None = None,
        hint: str = "delete it to start over",
    ) -> None:
        self.workspace, self.say, self.hint = workspace, say, hint
        self.settings = settings or Settings()
        self.progress = progress or no_progress
        self.steps: list[StepDefinition] = [
            StepDefinition("calibrate", self._calibrate, lambda: workspace.holds("calibration")),
            StepDefinition("poses", self._poses, lambda: workspace.holds("poses")),
            StepDefinition("reconstruct", self._reconstruct, workspace.reconstruction.finished),
            StepDefinition("report", self._report, workspace.report.exists),
        ]

    def add(self, step: StepDefinition, *, before: str | None = None) -> None:
        """Another step (the demo's), before the named one or at the end."""
        at = len(self.steps) if before is None else self.names().index(before)
        self.steps.insert(at, step)

    def names(self) -> list[str]:
        return [s.name for s in self.steps]

    # -- running -------------------------------------------------------------------------------

    def run(self, names: list[str] | None = None) -> list[StepResult]:
        """Run (or go on with) the named steps, all by default, in order, saying how each went;
        a step's error is raised, Ctrl-C as PipelineInterrupted."""
        chosen = [s for s in self.steps if names is None or s.name in names]
        if not self.workspace.state.exists():  # the folder is this pipeline's from now on
            self._write_state({})
        results = []
        for i, step in enumerate(chosen, 1):
            head = f"[{i}/{len(chosen)}] {step.name}"
            if self._done_before(step) is None:
                self.say(f"{head} ...")
            result = self.attempt(step.name)
            if result.status == "stopped":
                raise PipelineInterrupted(
                    f"stopped during '{step.name}'; run the same command again to go on from there"
                )
            took = f"{result.seconds:.1f} s"
            if result.status == "done before":
                took = f"done before ({took})"
            self.say(f"{head}: {took}: {result.summary}")
            results.append(result)
        return results

    def run_step(self, name: str, before: StepResult | None = None) -> StepResult:
        """Run one step unless it is done, as `evcap batch` does: never raises, an error is
        the result's one line. ``before``: the result of what it waits for, which must have
        gone well."""
        if before is not None and not before.ok:
            why = before.error if before.status == "not run" else f"{before.name} {before.status}"
            return StepResult(name, "not run", error=why)
        started = time.perf_counter()
        try:
            return self.attempt(name)
        except KeyboardInterrupt:
            return StepResult(name, "stopped", time.perf_counter() - started, error="interrupted")
        except Exception as e:  # any failure is this recording's; the others go on
            return StepResult(name, "failed", time.perf_counter() - started, error=one_line(e))

    def attempt(self, name: str) -> StepResult:
        """Run the step unless it is done; its errors are raised."""
        step = self.steps[self.names().index(name)]
        kept = self._done_before(step)
        if kept is not None:
            return kept
        if self.settings.cpus is not None:
            use_threads(self.settings.cpus)
        started = time.perf_counter()
        try:
            made = step.work()
        except KeyboardInterrupt:
            made = None
        summary, figures = made if isinstance(made, tuple) else (made, {})
        seconds = time.perf_counter() - started
        if summary is None:  # stopped; what it saved goes on next time
            return StepResult(name, "stopped", seconds, error="interrupted")
        state = self._read_state()
        later = self.names()[self.names().index(name) + 1 :]
        done = {k: v for k, v in state["done"].items() if k not in later}
        done[name] = {"seconds": seconds, "summary": summary, "figures": figures}
        self._write_state(done)
        return StepResult(name, "done", seconds, summary, figures=figures)

    def _done_before(self, step: StepDefinition) -> StepResult | None:
        mark = self._read_state()["done"].get(step.name)
        if mark is None or not step.made():
            return None
        kept = {k: mark.get(k, d) for k, d in (("seconds", 0.0), ("summary", ""), ("figures", {}))}
        return StepResult(step.name, "done before", **kept)

    # -- the state file ------------------------------------------------------------------------

    def _read_state(self) -> dict:
        path = self.workspace.state
        if not path.exists():
            return {"settings": self.settings.held(), "done": {}}
        try:
            state = json.loads(path.read_text())
            done, held = dict(state["done"]), dict(state["settings"])
        except (ValueError, KeyError, TypeError):
            raise InputError(f"{path} is damaged; {self.hint}") from None
        if held != self.settings.held():
            other = _differences(held, self.settings.held())
            raise InputError(
                f"{self.workspace.root} holds a run made with {other}; choose another output "
                f"folder, or {self.hint}"
            )
        return {"settings": held, "done": done}

    def _write_state(self, done: dict) -> None:
        state = {"settings": self.settings.held(), "done": done}
        write_text_atomic(self.workspace.state, json.dumps(state, indent=1))

    # -- the steps -----------------------------------------------------------------------------

    def _calibrate(self) -> str:
        """Measure the calibration recording's calibration (unless it holds one) and write it
        to the session."""
        from evcap.calib.board import parse_board
        from evcap.records import Calibration
        from evcap.session import Session

        ws = self.workspace
        if ws.calibration is None:
            raise InputError("no calibration recording to apply")
        ws.copy_source()
        with Session.open(ws.calibration) as s:
            kept = Calibration.read(s) if Calibration.present(s) else None
        if kept is None:
            board = parse_board(self.settings.board) if self.settings.board else None
            cal = work.calibrate_step(
                ws.calibration, board=board, also=[ws.session], progress=self.progress
            )
            return cal.summary().replace("\n", "; ")
        if ws.calibration == ws.session:
            return f"{(ws.source or ws.session).name}'s own /calibration, as it is"
        with Session.open(ws.session) as s:
            size = (s.sensor.width, s.sensor.height)
        if size != (kept.width, kept.height):
            raise InputError(
                f"its sensor is {size[0]} x {size[1]}; the calibration "
                f"({ws.calibration.name}) is for {kept.width} x {kept.height}"
            )
        kept.write(ws.session, replace=True)
        return f"the calibration of {ws.calibration.name} applied"

    def _poses(self) -> str:
        self.workspace.copy_source()
        result = work.poses_step(
            self.workspace.session, threads=self.settings.cpus or 1, progress=self.progress
        )
        return result.summary()

    def _reconstruct(self) -> tuple[str | None, dict[str, float]]:
        from evcap.records import Poses

        ws, settings = self.workspace, self.settings
        ws.copy_source()
        # a rerun goes on where the state fits, else starts over (the state file says what
        # is done)
        options = replace(settings.reconstruct, resume="go on or start over")
        if options.relight is not None:
            options = replace(options, relight=str(ws.root / options.relight))
        m = work.reconstruct_step(
            ws.session, ws.reconstruction.root, options, say=self.say, progress=self.progress
        )
        if m.interrupted:  # its state is saved: the next run goes on from it
            return None, {}
        refined = ""
        if ws.reconstruction.poses.exists():
            notes = Poses.read_file(ws.reconstruction.poses).notes
            refined = f", poses refined (by {notes['refinement_median_deg']:.2f} deg, median)"
        summary = (
            f"{m.gaussians:,} Gaussians; stage I {m.iterations} steps{refined}; stage II "
            f"{m.material_iterations} steps"
        )
        shown = m.figures.shown()
        if shown:
            summary += f". Held-out views: {figures_line(shown)}"
        return summary, shown

    def _report(self) -> str:
        page = work.report_step(self.workspace.reconstruction.root, self.workspace.session)
        with atomic_path(self.workspace.report) as partial:
            shutil.copyfile(page, partial)
        return f"{self.workspace.report} ({page.stat().st_size / 1e6:.1f} MB, self-contained)"


def _by_name(held: dict) -> dict[str, object]:
    """Held settings by the names a user gives them (--preset, stage1.iterations, board); a
    state an earlier evcap wrote held preset, device, seed and relight beside the board."""
    options = held.get("reconstruct", {k: v for k, v in held.items() if k in FLAGS})
    out: dict[str, object] = {FLAGS.get(k, k): v for k, v in options.items() if k != "settings"}
    out |= options.get("settings", {})
    return out | {k: v for k, v in held.items() if k != "reconstruct" and k not in FLAGS}


def _differences(then: dict, now: dict) -> str:
    """What a held state was made with, where it differs from now: its options, and the
    settings given by name now that it was not made with."""
    then, now = _by_name(then), _by_name(now)
    named = [k for k in now if k not in then and "." in k]
    differ = [k for k in then if then[k] != now.get(k)] + named
    return ", ".join(f"{k} {then.get(k, 'not given')}" for k in differ)


def figures_line(figures: dict[str, float]) -> str:
    """Figures (by name) as one line: each one's readable name, value and unit."""
    from evcap.records import Figures

    parts = []
    for key, value in figures.items():
        name, unit, _ = Figures.describe(key)
        if key.endswith("_err") and not unit:  # a share
            shown = f"{100 * value:.1f} %"
        elif unit in ("dB", "deg"):
            shown = f"{value:.1f} {unit}"
        else:
            shown = f"{value:.3g}{' ' + unit if unit else ''}"
        parts.append(f"{name}: {shown}")
    return "; ".join(parts)


def use_threads(cpus: int) -> None:
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
