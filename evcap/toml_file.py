"""TOML files of the user's (scenes, biases), read with errors that name the file."""

from __future__ import annotations

import os
import tomllib
from pathlib import Path

from evcap.errors import InputError, InputNotFoundError


def read_toml(path: str | os.PathLike, what: str) -> dict:
    """The document at ``path``; ``what`` names the kind of file in the errors ("scene")."""
    path = Path(path)
    if not path.is_file():
        raise InputNotFoundError(f"{path}: no such {what} file")
    try:
        return tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path} is not valid TOML: {e}") from None
