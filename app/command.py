"""One subcommand of `evcap`: its arguments beside the handler that runs it.

Each commands_* module lists its commands in COMMANDS; app/cli.py adds them to the parser.
"""

from __future__ import annotations

from argparse import ArgumentParser, Namespace
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Command:
    name: str
    # the one line of `evcap --help`
    help: str
    # the paragraph of `evcap NAME --help`
    description: str
    # adds the command's arguments to its parser (light: runs for every `evcap` call)
    arguments: Callable[[ArgumentParser], None]
    # does the work and returns the exit status; imports what it needs when it runs
    run: Callable[[Namespace], int]
