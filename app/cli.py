"""The `evcap` command: parses arguments and hands over to the step that does the work.

Kept thin and light: each command (app/commands_*.py) imports what it needs when it runs, so
that `evcap --help` (and `evcap record`) never wait for torch or other heavy packages.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from evcap import __version__
from evcap.app import commands_capture, commands_pipeline, commands_steps
from evcap.app.command import Command
from evcap.errors import EvcapError, InputError

# in the order `evcap --help` lists them
COMMANDS: tuple[Command, ...] = (
    *commands_capture.COMMANDS,
    *commands_steps.COMMANDS,
    *commands_pipeline.COMMANDS,
)


class _HelpFormatter(argparse.HelpFormatter):
    """argparse measures the command names without the indent they are printed with, so the
    longest one would sit on a line of its own."""

    def add_argument(self, action: argparse.Action) -> None:
        super().add_argument(action)
        if isinstance(action, argparse._SubParsersAction):
            self._action_max_length += self._indent_increment


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="evcap",
        description="Record, calibrate and reconstruct scenes with a color event camera.",
        formatter_class=_HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"evcap {__version__}")
    sub = parser.add_subparsers(title="commands", metavar="COMMAND", required=True)
    for command in COMMANDS:
        p = sub.add_parser(command.name, help=command.help, description=command.description)
        command.arguments(p)
        p.set_defaults(run=command.run)
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
    except KeyboardInterrupt as e:
        print(f"evcap: interrupted{f': {e}' if str(e) else ''}", file=sys.stderr)
        return 130
