"""The commands of the application floor that run the whole pipeline: batch, demo."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from evcap.app.command import Command
from evcap.app.demo import PRESETS as DEMO_PRESETS
from evcap.app.reconstruct_flags import add_reconstruct_arguments, options_from
from evcap.pipeline import STEPS


def _batch_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("manifest", metavar="MANIFEST", help="the manifest (TOML)")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="the output folder")
    p.add_argument("--address", help="an existing Ray cluster's address (host:port)")
    p.add_argument(
        "--steps",
        nargs="+",
        default=list(STEPS),
        choices=STEPS,
        help="the steps to run (default: all of them, in this order)",
    )
    add_reconstruct_arguments(p)
    p.add_argument("--cpus", type=int, default=1, help="cores per step's task (default 1)")
    p.add_argument(
        "--workers", type=int, help="cores of the Ray started here (default: all of them)"
    )
    p.add_argument(
        "--in-process", action="store_true", help="without Ray, one recording after the other"
    )


def _batch(args: argparse.Namespace) -> int:
    from evcap._progress import progress_bar
    from evcap.batch.manifest import read_manifest
    from evcap.batch.run import run_batch

    options = options_from(args)
    options.resolved()  # a setting misnamed is refused before any recording runs
    manifest = read_manifest(args.manifest)
    with progress_bar(f"{len(manifest.recordings)} recordings") as update:
        rows = run_batch(
            manifest,
            args.output,
            steps=tuple(args.steps),
            options=options,
            cpus=args.cpus,
            address=args.address,
            workers=args.workers,
            use_ray=False if args.in_process else None,
            say=print,
            progress=update,
        )
    failed = [r for r in rows if r.status != "done"]
    print(
        f"{len(rows) - len(failed)} of {len(rows)} recordings done; "
        f"{Path(args.output) / 'index.html'} shows them side by side"
    )
    for r in failed:
        print(f"  {r.name}: {r.status}: {r.error}", file=sys.stderr)
    return 1 if failed else 0


BATCH = Command(
    "batch",
    help="many recordings through every step, on a Ray cluster",
    description="Run each recording a manifest names (TOML: [[group]] tables with "
    "recordings = [paths or globs] and the calibration recording to apply) through the "
    "steps, as the single commands do, into OUT/<recording>/, with OUT/index.html and "
    "OUT/summary.csv/.json side by side. Each step is a Ray task (Ray started here, or "
    "the cluster at --address); without Ray (pip install 'evcap[cluster]') the recordings "
    "run one after the other here. Steps already done are skipped on a rerun; a recording "
    "that fails is listed with its error and the others go on.",
    arguments=_batch_arguments,
    run=_batch,
)


def _demo_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "-o", "--output", default="evcap-demo", metavar="DIR", help="default: evcap-demo"
    )
    p.add_argument("--fixtures", metavar="DIR", help="where the demo's captures are")
    p.add_argument("-f", "--force", action="store_true", help="start a demo folder over")
    add_reconstruct_arguments(p, preset="small", presets=DEMO_PRESETS)


def _demo(args: argparse.Namespace) -> int:
    from evcap.app.demo import run_demo

    options = options_from(args)
    options.resolved()  # a setting misnamed is refused before the demo starts
    run_demo(args.output, options, fixtures=args.fixtures, force=args.force)
    return 0


DEMO = Command(
    "demo",
    help="the whole pipeline on a bundled capture (no camera needed)",
    description="Replay a bundled capture of a simulated color scene through the driver, "
    "calibrate it from a bundled calibration recording, estimate its poses from the "
    "events, reconstruct it (both stages) and write DIR/report.html. Each step is saved "
    "as it ends: run the same command again after Ctrl-C to go on.",
    arguments=_demo_arguments,
    run=_demo,
)

# in the order `evcap --help` lists them
COMMANDS = (BATCH, DEMO)
