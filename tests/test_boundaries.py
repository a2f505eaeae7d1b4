"""The layout's rules, checked on the code: the spine (evcap/: the session, the events, the
records) imports no step; each step imports the spine and only the steps the layout draws under
it; the pipeline (pipeline/) sits over the steps, the batch (batch/) over the pipeline and the
application (app/) over them all (import-linter's contracts in pyproject.toml, run here). The
records own their groups, and ReconstructionFolder owns the files of a reconstruction folder
(OUT/)."""

import ast
import os
import subprocess
import sys
import tempfile
import tomllib
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
    "pipeline",
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


# -- the layering: pyproject.toml's import-linter contracts ([tool.importlinter]) ---------------

PYPROJECT = ROOT / "pyproject.toml"
# each package of evcap and the folder it lives in (evcap.acquire: acquire/)
PACKAGE_DIRS: dict[str, str] = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"][
    "package-dir"
]
FLOORS = tuple(PACKAGE_DIRS.values())  # the folders of the package: the spine and the floors
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")  # the venv's


def package_modules(floor: str) -> list[Path]:
    folder = ROOT / floor
    paths = sorted(folder.rglob("*.py"))
    if floor == "evcap":
        return [p for p in paths if ".egg-info" not in str(p)]
    return paths


def _own_folder(root: Path, parts: list[str]) -> Path:
    """ROOT/PARTS as folders of their own (a linked one unfolded into links to its entries), so
    that what is added there stays out of the repository."""
    folder = root
    for part in parts:
        folder = folder / part
        if folder.is_symlink():
            source = folder.resolve()
            folder.unlink()
            folder.mkdir()
            for entry in source.iterdir():
                if entry.name != "__pycache__":
                    (folder / entry.name).symlink_to(entry)
        folder.mkdir(exist_ok=True)
    return folder


def installed_layout(root: Path, planted: dict[str, str] | None = None) -> None:
    """evcap laid out under ROOT as pip installs it, in links to the repository's files: each
    folder where package-dir puts it. (import-linter finds a package by its folder, and the
    repository's evcap/ holds the spine alone: `lint-imports` run there sees no floor.)
    ``planted``: modules (by name) and their source, written beside the links."""
    for package, folder in sorted(PACKAGE_DIRS.items()):  # a package before its children
        *parents, name = package.split(".")
        (_own_folder(root, parents) / name).symlink_to(ROOT / folder, target_is_directory=True)
    for module, source in (planted or {}).items():
        *parents, name = module.split(".")
        (_own_folder(root, parents) / f"{name}.py").write_text(source)


def lint_imports(planted: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """`lint-imports` on pyproject.toml's contracts, over the installed layout (in a temporary
    folder, removed whatever happens), with the ``planted`` modules."""
    with tempfile.TemporaryDirectory() as tmp:
        installed_layout(Path(tmp), planted)
        return subprocess.run(
            [LINT_IMPORTS, "--no-cache", "--no-logo", PYPROJECT],
            cwd=tmp,  # lint-imports looks for the package here first
            capture_output=True,
            text=True,
            env={**os.environ, "COLUMNS": "200"},  # its report's lines unbroken
        )


def test_the_code_keeps_the_layering_contracts():
    """The spine under the steps, the steps apart (the monitor and the simulator on the driver),
    the pipeline over them, the batch and the application on top; acquire and tui without
    torch. pyproject.toml's [tool.importlinter] says each contract and why."""
    r = lint_imports()
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 broken" in r.stdout


# an import each contract forbids, by the package it is planted in; the first ones are the
# violations the layout once had: the demo and the CLI in the spine, the steps reaching sideways
PLANTED = {
    "evcap.records": [
        "evcap.acquire.device",
        "evcap.recon.reconstruct",
        "evcap.calib.calibrate",
        "evcap.poses.estimate",
        "evcap.report.html",
        "evcap.sim.truth",
        "evcap.recon.config",
        "evcap.batch.steps",
        "evcap.tui",
        "evcap.pipeline",
    ],
    "evcap.recon": ["evcap.sim.render"],
    "evcap.report": ["evcap.recon.export"],
    "evcap.acquire": ["evcap.tui", "torch", "pycolmap"],
    "evcap.tui": ["evcap.app.cli", "torch"],
    "evcap.sim": ["evcap.recon.scene.gaussians"],
    "evcap.calib": ["evcap.acquire.device", "evcap.poses.estimate"],
    "evcap.batch": ["evcap.tui", "evcap.app.cli"],
    "evcap.pipeline": ["evcap.batch.run", "evcap.app.demo", "evcap.tui"],
}
PROBE = "_layering_probe"


def test_the_contracts_catch_each_forbidden_import():
    modules = {f"{p}.{PROBE}": "".join(f"import {m}\n" for m in ms) for p, ms in PLANTED.items()}
    r = lint_imports(modules)
    report = r.stdout + r.stderr
    assert r.returncode != 0, report
    missed = [
        f"{p} -> {m}"
        for p, ms in PLANTED.items()
        for line, m in enumerate(ms, 1)
        if f"{p}.{PROBE} -> {m} (l.{line})" not in report
    ]
    assert not missed, f"the contracts let these through: {missed}\n{report}"


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
    [p for f in (*FLOORS, "bench") for p in package_modules(f) if p != FOLDER_RECORD],
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
    [p for f in FLOORS for p in package_modules(f) if p != RESULT_RECORD],
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


def test_a_module_of_evcap_on_no_floor_is_caught():
    """A new module of the spine is placed on its floor in pyproject.toml's layers."""
    r = lint_imports({f"evcap.{PROBE}": "import evcap.session\n"})
    assert r.returncode != 0 and f"- evcap.{PROBE}" in r.stdout, r.stdout + r.stderr


if __name__ == "__main__":  # `.venv/bin/python tests/test_boundaries.py`: the contracts' report
    r = lint_imports()
    print(r.stdout + r.stderr)
    sys.exit(r.returncode)
