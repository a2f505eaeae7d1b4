"""The one write-then-rename of the package: a file is seen whole or not at all."""

import ast
from pathlib import Path

import pytest

from evcap.atomic_write import atomic_path, write_text_atomic


def test_a_file_takes_its_name_when_whole(tmp_path):
    path = tmp_path / "deep" / "state.json"
    write_text_atomic(path, "first")
    assert path.read_text() == "first"
    write_text_atomic(path, "second")
    assert path.read_text() == "second" and sorted(p.name for p in path.parent.iterdir()) == [
        "state.json"
    ]


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_an_error_mid_write_keeps_what_was_there(tmp_path, error):
    path = tmp_path / "checkpoint.pt"
    path.write_text("previous")
    with pytest.raises(error), atomic_path(path) as partial:
        partial.write_text("half")
        raise error
    assert path.read_text() == "previous" and [p.name for p in tmp_path.iterdir()] == [path.name]


def renames(source: str) -> list[int]:
    """Where a source renames a file: os.replace/os.rename, or path.replace/rename(target)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
            continue
        if node.func.attr not in ("replace", "rename"):
            continue
        owner = node.func.value
        if isinstance(owner, ast.Name) and owner.id == "dataclasses":
            continue
        if (isinstance(owner, ast.Name) and owner.id == "os") or (
            len(node.args) == 1 and not node.keywords  # str.replace takes two
        ):
            found.append(node.lineno)
    return found


ROOT = Path(__file__).resolve().parents[1]
FLOORS = ("evcap", "acquire", "calib", "poses", "recon", "report", "sim", "tui", "batch", "app")


@pytest.mark.parametrize(
    "path",
    [p for f in FLOORS for p in sorted((ROOT / f).rglob("*.py")) if p.name != "atomic_write.py"],
    ids=lambda p: str(p.relative_to(ROOT)),
)
def test_the_package_renames_files_only_here(path):
    assert not renames(path.read_text()), f"{path.relative_to(ROOT)}: use evcap.atomic_write"


def test_the_rename_rule_catches_the_old_helpers():
    assert renames("tmp.replace(out / STATE)")  # demo.py, batch/steps.py, recon/export.py
    assert renames("os.replace(tmp, dst)")  # importers/common.py
    assert not renames('name.replace(" ", "-")')
    assert not renames("poses.replace(T_world_cam=T)")
