"""TOML files of the user's (scenes, biases, replay fixtures), read with errors that name the
file, the table and the key."""

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


class Table:
    """A TOML table being read: typed look-ups whose errors name the file and the key."""

    def __init__(self, data: dict, where: str) -> None:
        self.data, self.where, self.used = data, where, set()

    def get(self, key: str, kind, default=None, required: bool = False):
        self.used.add(key)
        if key not in self.data:
            if required:
                raise InputError(f"{self.where}: missing {key}")
            return default
        value = self.data[key]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if kind == "vec3":
            if (
                not isinstance(value, list)
                or len(value) != 3
                or not all(isinstance(v, int | float) for v in value)
            ):
                raise InputError(f"{self.where}: {key} must be 3 numbers, got {value!r}")
            return tuple(float(v) for v in value)
        if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            name = {float: "number", int: "whole number", str: "string", dict: "table"}.get(
                kind, getattr(kind, "__name__", kind)
            )
            raise InputError(f"{self.where}: {key} must be a {name}, got {value!r}")
        return value

    def table(self, key: str) -> Table:
        value = self.get(key, dict, {})
        return Table(value, f"{self.where} [{key}]")

    def done(self) -> None:
        unknown = set(self.data) - self.used
        if unknown:
            raise InputError(f"{self.where}: unknown key(s) {', '.join(sorted(unknown))}")
