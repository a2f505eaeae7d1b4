"""Nested settings: a stage's config is a frozen dataclass whose fields are numbers, strings or
the small configs of its components (dataclasses again). One field is named by its dotted path
(``densify.grad_threshold``); the docstring under a field (an attribute docstring) says what it
is. These functions read, replace, write and describe such configs; nothing here imports torch
(the command line imports it to list and check the names)."""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import textwrap
import tomllib
import typing
from collections.abc import Iterator, Mapping
from types import UnionType
from typing import Any, TypeVar

from evcap.errors import InputError

C = TypeVar("C")


def is_config(value: object) -> bool:
    return dataclasses.is_dataclass(value) and not isinstance(value, type)


# how a setting's None is written where None cannot be (TOML), and read back (a settings file,
# --set NAME=none)
NONE = "none"


def to_dict(config: object, none: object = None) -> dict:
    """The config as nested dicts (tuples as lists: what TOML and JSON hold; None as ``none``:
    NONE for TOML)."""

    def plain(v: Any) -> Any:
        if isinstance(v, tuple | list):
            return [plain(x) for x in v]
        return none if v is None else v

    return {
        f.name: to_dict(v, none) if is_config(v := getattr(config, f.name)) else plain(v)
        for f in dataclasses.fields(config)
    }


def from_dict(cls: type[C], data: Mapping[str, Any], where: str = "") -> C:
    """The config of class ``cls`` from nested dicts (to_dict's); a name it does not have is
    refused, one it leaves out takes the default."""
    kinds = _field_types(cls)
    unknown = set(data) - set(kinds)
    if unknown:
        names = ", ".join(sorted(where + k for k in unknown))
        raise InputError(f"unknown setting(s): {names}")
    values = {}
    for name, value in data.items():
        kind = kinds[name]
        if _config_class(kind) is not None and isinstance(value, Mapping):
            values[name] = from_dict(_config_class(kind), value, f"{where}{name}.")
        else:
            values[name] = _as_tuple(value)
    return cls(**values)


def names(config: object, prefix: str = "") -> Iterator[tuple[str, object]]:
    """Every leaf setting as (dotted name, value), in the fields' order."""
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if is_config(value):
            yield from names(value, f"{prefix}{f.name}.")
        else:
            yield prefix + f.name, value


def with_overrides(config: C, overrides: Mapping[str, object]) -> C:
    """The config with the settings named by dotted names replaced, all at once (a config's
    checks see its settings as they end, never a mix of old and new); an unknown name is
    refused with the names it might have meant."""
    named = [(dotted.split("."), value, dotted) for dotted, value in overrides.items()]
    return _replace(config, named)


def _replace(config: Any, named: list[tuple[list[str], object, str]]) -> Any:
    """``config`` with each (path, value, dotted name) in ``named`` set; a later one wins."""
    fields = {f.name for f in dataclasses.fields(config)}
    changes: dict[str, object] = {}
    within: dict[str, list] = {}
    for path, value, dotted in named:
        head = path[0]
        if head not in fields:
            raise InputError(f"unknown setting {dotted!r}{_suggestion(config, dotted)}")
        current = getattr(config, head)
        if len(path) > 1:
            if not is_config(current):
                raise InputError(f"unknown setting {dotted!r}: {head} is not a group of settings")
            within.setdefault(head, []).append((path[1:], value, dotted))
        elif is_config(current):
            raise InputError(f"{dotted!r} is a group of settings; name one of them ({head}.NAME)")
        else:
            changes[head] = _checked(_field_types(type(config))[head], value, dotted)
    for head, inner in within.items():
        changes[head] = _replace(getattr(config, head), inner)
    return dataclasses.replace(config, **changes) if changes else config


def _suggestion(config: object, dotted: str) -> str:
    last = dotted.split(".")[-1]
    close = [n for n, _ in names(config) if n.split(".")[-1] == last]
    return f"; did you mean {' or '.join(close)}?" if close else ""


def _checked(kind: Any, value: object, dotted: str) -> object:
    """``value`` as a setting of type ``kind`` (an int where a float goes; a list where a tuple
    goes), or a clear error."""
    value = _as_tuple(value)
    options = typing.get_args(kind) if typing.get_origin(kind) in (typing.Union, UnionType) else ()
    for option in options or (kind,):
        if option is type(None) and (value is None or value == NONE):
            return None
        if typing.get_origin(option) is typing.Literal:
            if value in typing.get_args(option):
                return value
            continue
        if option is float and isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
        if option is int and isinstance(value, int) and not isinstance(value, bool):
            return value
        if option in (bool, str) and type(value) is option:
            return value
        if typing.get_origin(option) is tuple and isinstance(value, tuple):
            return value
    choices = [repr(c) for o in options or (kind,) for c in typing.get_args(o)]
    expected = ", ".join(choices) if choices and "Literal" in str(kind) else _name(kind)
    raise InputError(f"{dotted} = {value!r}: expected {expected}")


def _name(kind: Any) -> str:
    return getattr(kind, "__name__", str(kind).replace("typing.", ""))


def parse_assignments(items: list[str], where: str = "--set") -> dict[str, object]:
    """``NAME=VALUE`` pairs (VALUE as TOML reads it: 2e-4, true, "bound", [1, 1, 1]; a bare
    word is a string) as {dotted name: value}."""
    out: dict[str, object] = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise InputError(f"{where} {item!r}: expected NAME=VALUE (e.g. densify.every=50)")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        out[name] = value
    return out


def flatten(table: Mapping[str, Any], prefix: str = "") -> dict[str, object]:
    """A TOML file's nested tables as {dotted name: value}."""
    out: dict[str, object] = {}
    for key, value in table.items():
        if isinstance(value, Mapping):
            out.update(flatten(value, f"{prefix}{key}."))
        else:
            out[prefix + key] = value
    return out


def describe(config: object, prefix: str = "") -> Iterator[tuple[str, object, str]]:
    """(dotted name, value, its field's docstring) of every leaf setting."""
    docs = field_docs(type(config))
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if is_config(value):
            yield from describe(value, f"{prefix}{f.name}.")
        else:
            yield prefix + f.name, value, docs.get(f.name, "")


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of a dataclass (the string literal after it), a base
    class's for the fields it defines."""
    out: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if dataclasses.is_dataclass(klass):
            out.update(_own_field_docs(klass))
    return out


def _own_field_docs(cls: type) -> dict[str, str]:
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    out = {}
    for a, b in zip(body, body[1:], strict=False):
        if (
            isinstance(a, ast.AnnAssign)
            and isinstance(a.target, ast.Name)
            and isinstance(b, ast.Expr)
            and isinstance(b.value, ast.Constant)
            and isinstance(b.value.value, str)
        ):
            out[a.target.id] = " ".join(b.value.value.split())
    return out


def _field_types(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _config_class(kind: Any) -> type | None:
    return kind if isinstance(kind, type) and dataclasses.is_dataclass(kind) else None


def _as_tuple(value: Any) -> Any:
    if isinstance(value, list | tuple):
        return tuple(_as_tuple(v) for v in value)
    return value
