"""Training steps a second, per stage, backend and device, and where a step's time goes.

Stage I runs with the preset's own schedule (its densification, the background learnt first)
and is stopped after ``--from + --steps`` steps, as Ctrl-C would stop it; steps a second are
taken over the last ``--steps``. Stage II then runs on that field for ``--material-steps``
(the first ``--material-from`` left out: each training view's stage-I render is made once
there). A second pass of each stage with the device waited for at every part's ends gives the
share of a step in each part (events, render, loss, backward, optimizer, densification).

``--baseline REF`` runs the same measurement on another commit of evcap (its tree exported
from git, imported in a fresh process in place of this one): today's code beside it.
``--full`` runs the whole of stage I through `evcap reconstruct` instead and scores it against
the session's truth (steps a minute over the whole run, object PSNR, normals, depth), for
the same comparison at the same figures.

    python bench/steps.py [SESSION.h5] [--scene single_object] [--preset fast]
        [--device cpu] [--backend cpu] [--resolution 1] [--from 450] [--steps 200]
        [--baseline 8aa6cd6]
"""

from __future__ import annotations

import argparse
import importlib.abc
import importlib.util
import inspect
import json
import subprocess
import sys
import tempfile
import time
import tomllib
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FIGURES = (
    "object_psnr",
    "object_psnr_gain",
    "object_psnr_constant",
    "normal_mae_deg",
    "depth_rel_err",
    "render_psnr",
    "render_psnr_gain",
)


def use_code(root: Path) -> None:
    """Import evcap from the checkout at ``root`` (its folders mapped into the namespace as
    its pyproject.toml maps them), ahead of the installed one."""
    folders = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    mapping = {name: root / folder for name, folder in folders["package-dir"].items()}

    class Finder(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name not in mapping:
                return None
            return importlib.util.spec_from_file_location(
                name, mapping[name] / "__init__.py", submodule_search_locations=[str(mapping[name])]
            )

    sys.meta_path.insert(0, Finder())


class Stop(KeyboardInterrupt):
    """Ends a training at a chosen step, as Ctrl-C does."""


class Clock:
    """The progress callback: the time at each step (the device waited for at the two ends of
    the measured span), and a stop after the last. On a GPU it also counts the times a step
    made the GPU wait for the host (PyTorch's sync debug mode), outside the steps that check
    for NaN and log (one in CHECK_EVERY)."""

    def __init__(self, first: int, last: int, device: str) -> None:
        self.first, self.last, self.device = first, last, device
        self.times: dict[int, float] = {}
        self.syncs = 0
        self.watched = 0
        self.caught: warnings.catch_warnings | None = None
        self.seen: list[warnings.WarningMessage] = []

    def __call__(self, step: int, total: int, text: str) -> None:
        self._close()
        if step in (self.first, self.last):
            _wait(self.device)
            self.times[step] = time.perf_counter()
        if step >= self.last:
            raise Stop
        self._open(step + 1)

    def _open(self, step: int) -> None:
        """Watch the coming step for waits, on a GPU, unless it is one that checks."""
        if self.device != "cuda" or step <= self.first or step % _check_every() == 0:
            return
        import torch

        self.caught = warnings.catch_warnings(record=True)
        self.seen = self.caught.__enter__()
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode(1)

    def _close(self) -> None:
        if self.caught is None:
            return
        import torch

        torch.cuda.set_sync_debug_mode(0)
        self.syncs += sum("synchroniz" in str(w.message) for w in self.seen)
        self.watched += 1
        self.caught.__exit__(None, None, None)
        self.caught = None

    def rate(self) -> float:
        return (self.last - self.first) / (self.times[self.last] - self.times[self.first])


def _check_every() -> int:
    """The steps between the trainers' checks for NaN (each waits for the device)."""
    stage = sys.modules[_trainers()[1].__module__]  # stage I's trainer's module
    return getattr(stage, "CHECK_EVERY", 1)  # before it had a name: every step


def _wait(device: str) -> None:
    import torch

    if device == "cuda":
        torch.cuda.synchronize()


def measure(args: argparse.Namespace) -> dict:
    """Steps a second of each stage (and each part's share, where this code can time them)."""
    import torch

    from evcap.session import Session

    load_training_data, train_radiance, train_material = _trainers()

    if args.threads:
        torch.set_num_threads(args.threads)
    timed = "timer" in inspect.signature(train_radiance).parameters
    config, mconfig = _configs(args)
    backend = args.backend or ("cpu" if args.device == "cpu" else "gsplat")
    out: dict = {"stage_1_from": args.start, "stage_1_steps": args.steps}
    with Session.open(args.session) as session:
        data = load_training_data(session, config, args.device)
        passes = [None]
        if timed and args.parts:
            from evcap.recon.step_timer import StepTimer

            passes.append(StepTimer(args.device))
        for timer in passes:
            clock = Clock(args.start, args.start + args.steps, args.device)
            extra = {"timer": timer} if timer is not None else {}
            fit = train_radiance(
                data,
                config,
                seed=args.seed,
                device=args.device,
                backend=backend,
                progress=clock,
                **extra,
            )
            if timer is None:
                field = fit.field
                out["stage_1_steps_per_s"] = clock.rate()
                out["gaussians"] = len(field.gaussians)
                if clock.watched:
                    out["stage_1_syncs_per_step"] = clock.syncs / clock.watched
            else:
                out.update({f"stage_1_share_{k}": v for k, v in timer.shares().items()})
        if not args.material_steps:
            return out
        for timer in passes:
            first = args.material_from
            clock = Clock(first, first + args.material_steps, args.device)
            extra = {"timer": timer} if timer is not None else {}
            train_material(
                field,
                data,
                session,
                config,
                mconfig,
                seed=args.seed,
                device=args.device,
                progress=clock,
                **extra,
            )
            if timer is None:
                out["stage_2_steps_per_s"] = clock.rate()
                if clock.watched:
                    out["stage_2_syncs_per_step"] = clock.syncs / clock.watched
            else:
                out.update({f"stage_2_share_{k}": v for k, v in timer.shares().items()})
    return out


def _trainers() -> tuple:
    """(load_training_data, train_radiance, train_material) where the code measured has them
    (a baseline from before recon/ was laid out by its parts has them in two modules)."""
    try:
        from evcap.recon.material.stage import train_material
        from evcap.recon.radiance.stage import load_training_data, train_radiance
    except ImportError:
        from evcap.recon.material import train_material
        from evcap.recon.radiance import load_training_data, train_radiance
    return load_training_data, train_radiance, train_material


def measure_full(args: argparse.Namespace) -> dict:
    """The whole of stage I through reconstruct(): steps a minute and the figures."""
    from evcap.recon.reconstruct import reconstruct

    how = {"preset": args.preset, "stage": "radiance", "device": args.device}
    how |= {"backend": args.backend, "seed": args.seed}
    if "options" not in inspect.signature(reconstruct).parameters:
        run = {**how, **_resolution(args)}  # a baseline from before the options record
    else:
        from evcap.recon.options import ReconstructOptions

        named = {f"stage1.{k}": v for k, v in _resolution(args).items()}
        run = {"options": ReconstructOptions(**how, settings=named)}
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        result = reconstruct(args.session, folder, **run)
        seconds = time.perf_counter() - start
    measured = result.figures.measured()
    out = {"stage_1_seconds": seconds, "stage_1_steps_per_min": 60 * result.iterations / seconds}
    # the training alone (the log's clock: no loading, evaluating or writing)
    training = result.training_log["radiance"][-1]["seconds"]
    out["stage_1_training_steps_per_min"] = 60 * result.iterations / training
    out.update({k: measured[k] for k in FIGURES if k in measured})
    return out


def _resolution(args: argparse.Namespace) -> dict:
    """The render scale asked for, over the preset's."""
    return {} if args.resolution is None else {"resolution": args.resolution}


def _configs(args: argparse.Namespace) -> tuple:
    """Both stages' settings: the preset's at the render scale asked for, as the code measured
    names them (nested, or flat in a baseline from before they were). A module the baseline
    lacks is not asked for: the installed evcap's would be imported in its place."""
    from evcap.recon import config as cfg

    if hasattr(cfg, "material_preset"):  # a baseline from before the settings were nested
        return cfg.preset(args.preset, **_resolution(args)), cfg.material_preset(args.preset)
    from evcap.recon.presets import preset

    named = {f"stage1.{k}": v for k, v in _resolution(args).items()}
    settings = preset(args.preset, named)
    return settings.stage1, settings.stage2


def run_baseline(args: argparse.Namespace) -> dict:
    """The same measurement on commit ``args.baseline``, in a fresh process."""
    from _common import export_commit

    folder = export_commit(args.baseline, ROOT)
    try:
        command = [sys.executable, __file__, "--code", folder.name, "--json-only"]
        command += _forwarded(args)
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode:
            sys.exit(f"the baseline {args.baseline} failed:\n{done.stderr}")
    finally:
        folder.cleanup()
    return json.loads(done.stdout.strip().splitlines()[-1])


def _forwarded(args: argparse.Namespace) -> list[str]:
    """This run's measuring options, for the baseline's process."""
    line = [str(args.session), "--preset", args.preset, "--device", args.device]
    line += ["--seed", str(args.seed), "--from", str(args.start), "--steps", str(args.steps)]
    line += ["--material-steps", str(args.material_steps)]
    line += ["--material-from", str(args.material_from), "--threads", str(args.threads)]
    if args.backend:
        line += ["--backend", args.backend]
    if args.resolution is not None:
        line += ["--resolution", str(args.resolution)]
    if args.full:
        line.append("--full")
    return line


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("session", type=Path, nargs="?")
    parser.add_argument("--scene", default="single_object", help="simulated when no SESSION")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--backend", help="the rasterizer (default: the device's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resolution", type=float, help="render scale (default: the preset's)")
    parser.add_argument("--from", dest="start", type=int, default=450)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--material-from", type=int, default=50)
    parser.add_argument("--material-steps", type=int, default=50)
    parser.add_argument("--threads", type=int, default=0, help="torch's threads (0: its own)")
    parser.add_argument("--no-parts", dest="parts", action="store_false")
    parser.add_argument("--full", action="store_true", help="the whole of stage I, scored")
    parser.add_argument("--baseline", help="a git commit to measure beside this code")
    parser.add_argument("--name", default="steps", help="results/NAME.json")
    parser.add_argument("--code", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--json-only", action="store_true", help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> dict:
    args = parse(argv)
    if args.code is not None:
        use_code(args.code)
    if args.session is None:
        from _common import session_of

        args.session = session_of(args.scene)
    import evcap.recon

    figures = measure_full(args) if args.full else measure(args)
    figures["code"] = str(Path(evcap.recon.__file__).resolve().parent.parent)
    if args.json_only:
        print(json.dumps(figures))
        return figures
    from _common import report

    figures = {
        "session": str(args.session),
        "preset": args.preset,
        "device": args.device,
        "backend": args.backend or "default",
        "resolution": args.resolution or "preset",
        **figures,
    }
    if args.baseline:
        before = run_baseline(args)
        figures.update({f"baseline_{k}": v for k, v in before.items()})
        figures["baseline"] = args.baseline
        rates = ("stage_1_steps_per_s", "stage_2_steps_per_s", "stage_1_steps_per_min")
        for key in (*rates, "stage_1_training_steps_per_min"):
            if key in figures and f"baseline_{key}" in figures:
                figures[f"{key}_ratio"] = figures[key] / figures[f"baseline_{key}"]
    report(args.name, figures)
    return figures


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
