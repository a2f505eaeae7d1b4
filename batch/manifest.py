"""The batch's manifest: which recordings, in groups, each group with the calibration recording
to apply to its recordings.

    # paths are relative to the manifest's folder; globs are expanded, sorted
    [[group]]
    calibration = "calibration/board.h5"         # optional
    board = "charuco:5x4:0.04:0.03:DICT_4X4_50"  # optional: the board seen in it
    recordings = ["drawer-1/*.h5", "vase.h5"]

A calibration recording that already holds its /calibration (``evcap calibrate`` ran on it) is
applied as it is; otherwise it is calibrated first, once for its group.
"""

from __future__ import annotations

import glob
import re
from dataclasses import dataclass
from pathlib import Path

from evcap.errors import InputError, InputNotFoundError
from evcap.toml_file import Table, read_toml


@dataclass(frozen=True)
class Group:
    name: str  # its calibration's folder in the output: OUTDIR/calibration/NAME
    calibration: Path | None
    board: str | None


@dataclass(frozen=True)
class Recording:
    name: str  # its folder in the output: OUTDIR/NAME
    path: Path
    group: Group


@dataclass(frozen=True)
class Manifest:
    path: Path
    recordings: tuple[Recording, ...]

    @property
    def groups(self) -> tuple[Group, ...]:
        """The groups with a calibration, each once."""
        seen = dict.fromkeys(r.group for r in self.recordings if r.group.calibration is not None)
        return tuple(seen)


def read_manifest(path: str | Path) -> Manifest:
    path = Path(path).resolve()
    top = Table(read_toml(path, "manifest"), str(path))
    raw_groups = top.get("group", list, required=True)
    top.done()
    if not raw_groups:
        raise InputError(f"{path}: the manifest has no [[group]]")
    entries: list[tuple[Path, Group]] = []
    for i, raw in enumerate(raw_groups, 1):
        if not isinstance(raw, dict):
            raise InputError(f"{path}: group {i} must be a table ([[group]])")
        t = Table(raw, f"{path} [[group]] {i}")
        calibration = t.get("calibration", str)
        calibration = _existing(path.parent, calibration, t.where) if calibration else None
        # a group's name: its calibration recording's, numbered (stems may repeat)
        name = f"{i}-{calibration.stem}" if calibration else str(i)
        group = Group(name, calibration, t.get("board", str))
        patterns = t.get("recordings", list, required=True)
        t.done()
        if not patterns or not all(isinstance(p, str) for p in patterns):
            raise InputError(f"{t.where}: recordings must be a list of paths or globs")
        for pattern in patterns:
            found = _expand(path.parent, pattern)
            if not found:
                raise InputNotFoundError(f"{t.where}: no recording matches {pattern!r}")
            entries += [(p, group) for p in found]
    return Manifest(path, _named(path, entries))


def _existing(base: Path, name: str, where: str) -> Path:
    p = (base / name).resolve()
    if not p.is_file():
        raise InputNotFoundError(f"{where}: calibration recording {p} not found")
    return p


def _expand(base: Path, pattern: str) -> list[Path]:
    full = str(base / pattern)
    if glob.has_magic(full):
        return sorted(Path(p).resolve() for p in glob.glob(full, recursive=True))
    p = Path(full).resolve()
    return [p] if p.exists() else []


def _named(manifest: Path, entries: list[tuple[Path, Group]]) -> tuple[Recording, ...]:
    """Each recording once (the first group that lists it), named by its file's stem, or by
    its path from the manifest's folder where two stems are alike."""
    unique: dict[Path, Group] = {}
    for p, group in entries:
        unique.setdefault(p, group)
    stems = [p.stem for p in unique]
    names = []
    for p in unique:
        name = p.stem
        if stems.count(name) > 1:
            try:
                name = str(p.relative_to(manifest.parent).with_suffix(""))
            except ValueError:
                name = str(p.with_suffix(""))
        names.append(re.sub(r"[^\w.-]+", "-", name).strip("-") or "recording")
    if len(set(names)) < len(names):
        twice = sorted({n for n in names if names.count(n) > 1})
        raise InputError(f"{manifest}: recordings named alike after cleaning: {', '.join(twice)}")
    return tuple(
        Recording(name, p, group) for name, (p, group) in zip(names, unique.items(), strict=True)
    )
