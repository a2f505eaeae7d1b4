"""The layout's rules, checked on the code: the spine (evcap/: the session, the events, the
records) imports no step; each step imports the spine and only the steps the layout draws under
it; the application floor (app/, batch/) sits over them all. The records own their groups, and
ReconstructionFolder owns the files of a reconstruction folder (OUT/)."""

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
    "batch",
    "app",
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
SCENE_KEYS = {
    "sim/scene.py": {"calibration", "threshold_on", "threshold_off"},
    "batch/manifest.py": {"calibration"},  # a manifest group's key: its calibration recording
}


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


def imported(source: str) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


# what each floor may import of evcap besides the spine (the layout of DESIGN.md): the driver
# under the monitor and the simulator's fixtures; the steps meet only through the spine; the
# application floor over everything
ALLOWED = {
    "evcap": set(),
    "acquire": set(),
    "calib": set(),
    "poses": set(),
    "recon": set(),
    "report": set(),
    "sim": {"acquire"},
    "tui": {"acquire"},
    "batch": {"acquire", "calib", "poses", "recon", "report", "sim", "app"},
    "app": {"acquire", "calib", "poses", "recon", "report", "sim", "tui", "batch"},
}
FLOORS = tuple(f for f in ALLOWED if f != "evcap")
ENTRY = "evcap/__main__.py"  # `python -m evcap`: the program's entry, the command's alias


def floor_of(module: str) -> str | None:
    """The floor an evcap module lives on (evcap.recon.x -> recon; evcap.session -> evcap)."""
    if module != "evcap" and not module.startswith("evcap."):
        return None
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in FLOORS else "evcap"


def violations(floor: str, path: str, modules: set[str]) -> list[str]:
    allowed = ALLOWED[floor] | {floor, "evcap"}
    if path == ENTRY:
        allowed = allowed | {"app"}
    return sorted(f"{path}: {m}" for m in modules if floor_of(m) not in (None, *allowed))


def package_modules(floor: str) -> list[Path]:
    folder = ROOT / floor
    paths = sorted(folder.rglob("*.py"))
    if floor == "evcap":
        return [p for p in paths if ".egg-info" not in str(p)]
    return paths


@pytest.mark.parametrize("floor", list(ALLOWED))
def test_each_floor_imports_only_what_the_layout_draws_under_it(floor):
    bad = []
    for p in package_modules(floor):
        rel = str(p.relative_to(ROOT))
        bad += violations(floor, rel, imported(p.read_text()))
    assert not bad, f"{floor} reaches where the layout does not let it: {bad}"


@pytest.mark.parametrize(
    "floor, path, module",
    [
        # the old violations: the demo and the CLI in the spine, the steps reaching sideways
        ("evcap", "evcap/demo.py", "evcap.acquire.device"),
        ("evcap", "evcap/demo.py", "evcap.recon.reconstruct"),
        ("evcap", "evcap/demo.py", "evcap.calib.calibrate"),
        ("evcap", "evcap/demo.py", "evcap.poses.estimate"),
        ("evcap", "evcap/demo.py", "evcap.report.html"),
        ("evcap", "evcap/demo.py", "evcap.sim.truth"),
        ("evcap", "evcap/cli.py", "evcap.recon.config"),
        ("evcap", "evcap/cli.py", "evcap.batch.steps"),
        ("evcap", "evcap/cli.py", "evcap.tui"),
        ("recon", "recon/x.py", "evcap.sim.render"),
        ("report", "report/x.py", "evcap.recon.export"),
        ("acquire", "acquire/x.py", "evcap.tui"),
        ("tui", "tui/x.py", "evcap.app.cli"),
        ("sim", "sim/x.py", "evcap.recon.scene.gaussians"),
        ("batch", "batch/x.py", "evcap.tui"),
    ],
)
def test_the_rules_catch_each_old_violation(floor, path, module):
    assert violations(floor, path, {module})
    assert not violations(floor, path, {"evcap.session", "evcap.records.poses", "numpy"})


# the files of a reconstruction folder: named by evcap/records/reconstruction_folder.py alone
FOLDER_RECORD = ROOT / "evcap" / "records" / "reconstruction_folder.py"
OUT_NAMES = {
    "config.toml",
    "metrics.json",
    "gaussians.ply",
    "poses.h5",
    "environment.png",
    "report.html",
    "checkpoint",
    "renders",
    "radiance.pt",
    "material.pt",
    "-state.pt",
}
OUT_ENDINGS = (".pt", "_radiance.png", "_radiance_gain.png", "_normal.png", "_depth.png")


def out_file_names(source: str) -> list[tuple[int, str]]:
    """Where a source names a file of OUT/ (in a string or a piece of an f-string)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            v = node.value
            if any(c.isspace() for c in v):
                continue  # prose (a help text), not a path
            if v.strip("/") in OUT_NAMES or v.endswith(OUT_ENDINGS) or "checkpoint/" in v:
                found.append((node.lineno, v))
    return found


@pytest.mark.parametrize(
    "path",
    [p for f in (*ALLOWED, "bench") for p in package_modules(f) if p != FOLDER_RECORD],
    ids=lambda p: str(p.relative_to(ROOT)),
)
def test_only_the_folder_record_names_the_files_of_a_reconstruction(path):
    named = out_file_names(path.read_text())
    assert not named, f"{path.relative_to(ROOT)} names a file of OUT/: {named}"


@pytest.mark.parametrize(
    "source",
    [
        'path = out / "checkpoint" / "radiance.pt"',  # recon/reconstruct.py, demo.py
        'marks = ("config.toml", "metrics.json", "checkpoint/radiance.pt")',  # report/html.py
        'done = (job.reconstruction / "metrics.json").exists()',  # batch/steps.py
        'return out / "checkpoint" / f"{stage}-state.pt"',  # recon/resume.py
        'shutil.copyfile(page, ctx.out / "report.html")',  # demo.py
        'cv2.imwrite(f"{stem}_radiance.png", image)',  # recon/export.py
    ],
)
def test_the_file_rule_catches_each_old_naming(source):
    assert out_file_names(source)


def test_the_folder_record_names_every_file_it_owns():
    named = {v for _, v in out_file_names(FOLDER_RECORD.read_text())}
    assert {"config.toml", "metrics.json", "gaussians.ply", "report.html", "-state.pt"} <= named


def figure_lists(source: str) -> list[int]:
    """Where a source lists three or more of the figures by name (a tuple, list or set, or the
    keys of a dict of labels)."""
    from evcap.records import Figures

    names = set(Figures.names())
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Dict):
            labels = all(isinstance(v, ast.Constant) for v in node.values)
            items = node.keys if labels else []
        elif isinstance(node, ast.Tuple | ast.List | ast.Set):
            items = node.elts
        else:
            continue
        hits = [e for e in items if isinstance(e, ast.Constant) and e.value in names]
        if len(hits) >= 3:
            found.append(node.lineno)
    return found


RESULT_RECORD = ROOT / "evcap" / "records" / "result.py"


@pytest.mark.parametrize(
    "path",
    [p for f in ALLOWED for p in package_modules(f) if p != RESULT_RECORD],
    ids=lambda p: str(p.relative_to(ROOT)),
)
def test_the_figures_a_user_is_shown_are_listed_once(path):
    """evcap/records/result.py's SHOWN is the one list (the CLI, the demo and the batch's
    summary used to keep their own)."""
    assert not figure_lists(path.read_text()), f"{path.relative_to(ROOT)} lists figures"


def test_the_figure_rule_catches_a_list_of_its_own():
    assert figure_lists('FIGURES = ("object_psnr_gain", "normal_mae_deg", "depth_rel_err")')
    labels = '{"object_psnr_gain": "object", "normal_mae_deg": "normals", "depth_rel_err": "depth"}'
    assert figure_lists(labels)
