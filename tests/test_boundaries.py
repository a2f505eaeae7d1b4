"""The steps meet only through the spine: the records own their groups, and recon, calib and
poses import nothing from each other or from the simulator (issue: one owner per exchanged
thing)."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STEPS = (
    "acquire",
    "calib",
    "poses",
    "recon",
    "report",
    "sim",
    "tui",
    "evcap",
    "bench",
    "hw-fixtures",
)
RECORDS = ROOT / "evcap" / "records"
GROUPS = {"calibration", "poses", "gt"}
# dataset names that belong to one record's group and mean nothing else in the code (not
# hot_pixels: also one of the simulator's effects)
DATASETS = {
    "threshold_on",
    "threshold_off",
    "threshold_confidence",
    "event_rate_hz",
    "view_t",
    "view_rms_px",
    "view_corners",
    "T_world_cam",
    "points_xyz",
    "relight_environment",
    "test_T_world_cam",
    "test_radiance",
    "test_depth",
    "test_normal",
    "test_base_color",
    "test_roughness",
    "test_mask",
    "test_relit_radiance",
}


# the scene TOML's own keys (a camera's or a sensor's calibration file, a sensor's thresholds)
SCENE_KEYS = {"sim/scene.py": {"calibration", "threshold_on", "threshold_off"}}


def modules(*steps: str) -> list[Path]:
    out = []
    for step in steps:
        out += [p for p in (ROOT / step).rglob("*.py") if RECORDS not in p.parents]
    return sorted(out)


def group_names(tree: ast.AST) -> list[tuple[int, str]]:
    """Where a group of a record is named: opened, indexed, tested for or written."""
    found = []
    for node in ast.walk(tree):
        args: list[ast.AST] = []
        if isinstance(node, ast.Call):
            name = getattr(node.func, "attr", getattr(node.func, "id", ""))
            if name in ("group", "get", "write_group", "create_group", "require_group"):
                args = list(node.args)
        elif isinstance(node, ast.Subscript):
            args = [node.slice]
        elif isinstance(node, ast.Compare) and any(
            isinstance(op, ast.In | ast.NotIn) for op in node.ops
        ):
            args = [node.left]
        for a in args:
            text = a.value if isinstance(a, ast.Constant) else None
            if isinstance(text, str) and text.strip("/").split("/")[0] in GROUPS:
                found.append((node.lineno, text))
    return found


@pytest.mark.parametrize("path", modules(*STEPS), ids=lambda p: str(p.relative_to(ROOT)))
def test_only_the_records_name_their_groups_and_datasets(path):
    tree = ast.parse(path.read_text())
    named = group_names(tree)
    named += [
        (node.lineno, node.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant) and node.value in DATASETS
    ]
    allowed = SCENE_KEYS.get(str(path.relative_to(ROOT)), set())
    named = [(line, text) for line, text in named if text not in allowed]
    assert not named, f"{path.relative_to(ROOT)} names a record's group or dataset: {named}"


def imported(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


@pytest.mark.parametrize("step", ["recon", "calib", "poses"])
def test_steps_import_only_the_spine(step):
    others = {f"evcap.{s}" for s in ("recon", "calib", "poses", "sim", "report", "tui")}
    others.discard(f"evcap.{step}")
    bad = {
        f"{p.relative_to(ROOT)}: {m}"
        for p in modules(step)
        for m in imported(p)
        if any(m == o or m.startswith(o + ".") for o in others)
    }
    assert not bad, f"{step} reaches into other steps: {sorted(bad)}"
