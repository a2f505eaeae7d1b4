"""Write-then-rename, the one way evcap writes a file that must never be seen half-made."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

SUFFIX = ".partial"


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A path beside ``path`` to write to, renamed to ``path`` when the block ends without an
    error: a crash, a kill or Ctrl-C mid-write leaves what ``path`` held before (or nothing),
    and the half-made file is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + SUFFIX)
    try:
        yield partial
        partial.replace(path)
    finally:
        partial.unlink(missing_ok=True)


def write_text_atomic(path: str | Path, text: str) -> None:
    """``text`` (UTF-8) into ``path``, which takes its name only when written whole."""
    with atomic_path(path) as partial:
        partial.write_text(text, encoding="utf-8")
