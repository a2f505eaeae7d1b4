"""`evcap batch`: every recording of a manifest through the steps, on a Ray cluster or, without
Ray, one after the other in this process; the same outputs either way.

On Ray each step of each recording is a task that asks for the cores it uses (and a GPU for the
reconstruction with ``device="cuda"``) and waits for the step before it (the first, for its
group's calibration), so Ray packs the recordings onto the cluster's nodes. Without an address
Ray starts on this machine with ``workers`` cores; with one it joins that cluster, whose nodes
need evcap installed and the manifest's paths and OUTDIR at the same place (a shared disk).
"""

from __future__ import annotations

import importlib.util
import logging
import time
from collections.abc import Callable
from pathlib import Path

from evcap.batch.manifest import Manifest
from evcap.batch.steps import Job, calibrate_group, run_step
from evcap.batch.summary import RecordingRow, write_summary
from evcap.errors import InputError
from evcap.pipeline import STEPS, StepResult, one_line
from evcap.recon.options import ReconstructOptions

# how long the tasks may take to stop and save what they have after Ctrl-C
DEFAULT_OPTIONS = ReconstructOptions()
STOP_WAIT_S = 60.0


class BatchInterrupted(KeyboardInterrupt):
    """Ctrl-C: the finished steps are kept; the same command goes on from them."""


def ray_installed() -> bool:
    return importlib.util.find_spec("ray") is not None


def run_batch(
    manifest: Manifest,
    out: str | Path,
    *,
    steps: tuple[str, ...] = STEPS,
    options: ReconstructOptions = DEFAULT_OPTIONS,
    cpus: int = 1,
    address: str | None = None,
    workers: int | None = None,
    use_ray: bool | None = None,
    say: Callable[[str], None] = lambda line: None,
    progress: Callable[[int, int, str], None] | None = None,
) -> list[RecordingRow]:
    """Run the manifest into ``out``; returns a row per recording (also written to
    out/summary.json, summary.csv and index.html). ``options``: the reconstructions' (every
    recording's the same); ``use_ray``: None uses Ray when it is
    installed; ``cpus``: the cores of each step's task; ``workers``: the cores of a Ray started
    here (default: all of them)."""
    unknown = [s for s in steps if s not in STEPS]
    if unknown or not steps:
        raise InputError(f"unknown step(s) {unknown}; the steps are {', '.join(STEPS)}")
    if cpus < 1 or (workers is not None and workers < 1):
        raise InputError("--cpus and --workers must be at least 1")
    if use_ray is None:
        use_ray = ray_installed() or address is not None
    if use_ray and not ray_installed():
        raise InputError(
            "Ray is not installed: pip install 'evcap[cluster]' (or run without --address, "
            "one recording after the other)"
        )
    out = Path(out).resolve()
    steps = tuple(s for s in STEPS if s in steps)  # always in their order
    jobs = [Job(r, out, options, cpus) for r in manifest.recordings]
    total = len(manifest.groups) * ("calibrate" in steps) + sum(
        len(_steps_of(job, steps)) for job in jobs
    )
    done = 0

    def tick(what: str) -> None:
        nonlocal done
        done += 1
        if progress:
            progress(done, total, what)

    about = {
        "manifest": str(manifest.path),
        "steps": ", ".join(steps),
        "preset": options.preset,
        "device": options.device,
        "seed": options.seed,
        "settings": ", ".join(f"{k}={v}" for k, v in options.settings) or "the preset's",
        "cores per task": cpus,
        "ran on": ("Ray at " + address if address else "Ray on this machine")
        if use_ray
        else "this process, one recording after the other",
    }
    rows = [RecordingRow(j.recording.name, str(j.recording.path)) for j in jobs]
    calibrations: dict[str, StepResult] = {}
    started = time.perf_counter()
    try:
        runner = _run_on_ray if use_ray else _run_here
        runner(jobs, steps, manifest, rows, calibrations, address, workers, say, tick)
    except KeyboardInterrupt:
        _finish(out, rows, calibrations, about, started)
        raise BatchInterrupted(
            f"stopped; finished steps are kept in {out}: run the same command to go on"
        ) from None
    _finish(out, rows, calibrations, about, started)
    return rows


def _steps_of(job: Job, steps: tuple[str, ...]) -> tuple[str, ...]:
    """The steps this recording takes: no calibration to apply where its group has none."""
    return tuple(s for s in steps if s != "calibrate" or job.recording.group.calibration)


def _finish(out: Path, rows, calibrations: dict[str, StepResult], about: dict, started) -> None:
    about = {
        **about,
        "wall seconds": round(time.perf_counter() - started, 1),
        "calibrations": [
            {"name": r.name, "status": r.status, "summary": r.summary, "error": r.error}
            for r in calibrations.values()
        ],
    }
    write_summary(out, rows, about)


def _run_here(jobs, steps, manifest, rows, calibrations, address, workers, say, tick) -> None:
    for group in manifest.groups if "calibrate" in steps else ():
        calibrations[group.name] = result = calibrate_group(jobs[0].out, group, jobs[0].cpus)
        _said(say, result)
        tick(result.name)
        if result.status == "stopped":
            raise KeyboardInterrupt
    for job, row in zip(jobs, rows, strict=True):
        before = calibrations.get(job.recording.group.name)
        for step in _steps_of(job, steps):
            result = run_step(step, job, before if step == "calibrate" else _last(row))
            row.steps[step] = result
            _said(say, result, job.recording.name)
            tick(f"{job.recording.name}: {step}")
            if result.status == "stopped":
                raise KeyboardInterrupt


def _last(row: RecordingRow) -> StepResult | None:
    return list(row.steps.values())[-1] if row.steps else None


def _run_on_ray(jobs, steps, manifest, rows, calibrations, address, workers, say, tick) -> None:
    import ray

    started_here = not ray.is_initialized()
    if started_here:
        if address:
            ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
        else:
            ray.init(
                num_cpus=workers,
                include_dashboard=False,
                log_to_driver=False,
                logging_level=logging.WARNING,
            )
    try:
        _submit_and_wait(ray, jobs, steps, manifest, rows, calibrations, say, tick)
    finally:
        if started_here:
            ray.shutdown()


def _submit_and_wait(ray, jobs, steps, manifest, rows, calibrations, say, tick) -> None:
    cpus = jobs[0].cpus if jobs else 1
    gpu = 1 if jobs and jobs[0].options.device == "cuda" else 0
    calibrate_task = ray.remote(calibrate_group)
    step_task = ray.remote(run_step)
    # a failed step is a result, not an exception: nothing for Ray to retry
    needs = {"num_cpus": cpus, "max_retries": 0}
    pending = {}  # ObjectRef -> (row or None, step or group)
    group_refs = {}
    for group in manifest.groups if "calibrate" in steps else ():
        ref = calibrate_task.options(**needs).remote(jobs[0].out, group, cpus)
        group_refs[group.name] = ref
        pending[ref] = (None, group.name)
    for job, row in zip(jobs, rows, strict=True):
        previous = group_refs.get(job.recording.group.name)
        for step in _steps_of(job, steps):
            gpus = gpu if step == "reconstruct" else 0
            # the ref as an argument: Ray runs the step once the one before it has ended
            ref = step_task.options(**needs, num_gpus=gpus).remote(step, job, previous)
            pending[ref] = (row, step)
            previous = ref
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                row, what = pending.pop(ref)
                result = _result(ray, ref, what)
                if row is None:
                    calibrations[what] = result
                    _said(say, result)
                else:
                    row.steps[what] = result
                    _said(say, result, row.name)
                tick(what if row is None else f"{row.name}: {what}")
    except KeyboardInterrupt:
        for ref in pending:  # a running step gets Ctrl-C and keeps what it can
            ray.cancel(ref)
        _collect_stopped(ray, pending, rows, calibrations)
        raise


def _collect_stopped(ray, pending, rows, calibrations) -> None:
    """The results of the steps cancelled after Ctrl-C, as far as they come in time."""
    deadline = time.monotonic() + STOP_WAIT_S
    while pending and time.monotonic() < deadline:
        ready, _ = ray.wait(list(pending), num_returns=1, timeout=deadline - time.monotonic())
        for ref in ready:
            row, what = pending.pop(ref)
            (calibrations if row is None else row.steps)[what] = _result(ray, ref, what)


def _result(ray, ref, what: str) -> StepResult:
    """The task's result; a cancelled task as a stopped step, one whose worker raised or died
    as a failed step with a one-line error."""
    try:
        return ray.get(ref)
    except (ray.exceptions.TaskCancelledError, KeyboardInterrupt):
        return StepResult(what, "stopped", error="interrupted")
    except ray.exceptions.RayTaskError as e:
        cause = getattr(e, "cause", None)
        if isinstance(cause, KeyboardInterrupt):
            return StepResult(what, "stopped", error="interrupted")
        return StepResult(what, "failed", error=one_line(cause if cause is not None else e))
    except ray.exceptions.RayError as e:  # its worker or node lost
        return StepResult(what, "failed", error=f"{type(e).__name__}: {one_line(e)}")


def _said(say, result: StepResult, name: str = "") -> None:
    where = f"{name}: {result.name}" if name else result.name
    detail = result.error if result.error else result.summary
    say(f"{where}: {result.status} ({result.seconds:.1f} s){': ' + detail if detail else ''}")
