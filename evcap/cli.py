"""The `evcap` command: parses arguments and hands over to the step that does the work.

Kept thin and light: each subcommand imports what it needs when it runs, so that
`evcap --help` (and `evcap record`) never wait for torch or other heavy packages.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from evcap import __version__
from evcap.errors import EvcapError, InputError


def _cmd_import(args: argparse.Namespace) -> int:
    from evcap._progress import progress_bar
    from evcap.aedat4 import import_aedat4

    with progress_bar(f"importing {args.file}") as update:
        summary = import_aedat4(
            args.file,
            args.output,
            color_filter=args.color_filter,
            overwrite=args.force,
            progress=update,
        )
    print(
        f"{args.output}: {summary.events:,} events, {summary.frames:,} frames, "
        f"{summary.imu:,} IMU samples, {summary.triggers:,} triggers"
    )
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    from evcap._progress import progress_bar
    from evcap.session import Session
    from evcap.summary import format_summary, summarize

    with progress_bar(f"checking {args.session}") as update:
        session = Session.open(args.session, progress=update)
    with session, progress_bar(f"reading {args.session}") as update:
        summary = summarize(session, update)
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="evcap",
        description="Record, calibrate and reconstruct scenes with a color event camera.",
    )
    parser.add_argument("--version", action="version", version=f"evcap {__version__}")
    sub = parser.add_subparsers(title="commands", metavar="COMMAND", required=True)

    p = sub.add_parser(
        "import",
        help="convert an AEDAT 4 file (iniVation DV) into a session file",
        description="Convert an AEDAT 4 file (events, frames, IMU, triggers) into a session.",
    )
    p.add_argument("file", help="the .aedat4 file")
    p.add_argument("-o", "--output", required=True, help="the session file to write (.h5)")
    p.add_argument(
        "--color-filter",
        choices=["MONO", "RGBG", "GRGB", "GBGR", "BGRG"],
        default=None,
        help="the sensor's color filter (default: RGBG if the file has color frames, else MONO)",
    )
    p.add_argument("-f", "--force", action="store_true", help="overwrite the output file")
    p.set_defaults(run=_cmd_import)

    p = sub.add_parser(
        "info",
        help="describe a session: sensor, duration, stream counts, event rate",
        description="Check a session file and describe it.",
    )
    p.add_argument("session", help="the session file (.h5)")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(run=_cmd_info)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except InputError as e:
        print(f"evcap: error: {e}", file=sys.stderr)
        return 2
    except EvcapError as e:
        print(f"evcap: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("evcap: interrupted", file=sys.stderr)
        return 130
