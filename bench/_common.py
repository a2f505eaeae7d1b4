"""Shared by the benchmarks: where results go and how they are printed."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import tempfile
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
SCENES = Path(__file__).resolve().parent.parent / "sim" / "scenes"


def machine() -> dict:
    return {
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "python": platform.python_version(),
    }


def report(name: str, figures: dict) -> None:
    """Print ``figures`` and write them with the machine description to results/NAME.json."""
    RESULTS.mkdir(exist_ok=True)
    for key, value in figures.items():
        if isinstance(value, list):  # a table: printed by the bench itself
            print(f"{key:<32} ({len(value)} rows in the JSON)")
        elif isinstance(value, float):
            print(f"{key:<32} {value:,.3f}")
        else:
            print(f"{key:<32} {value}")
    out = RESULTS / f"{name}.json"
    out.write_text(json.dumps({"benchmark": name, "machine": machine(), **figures}, indent=2))
    print(f"-> {out}")


def markdown_table(rows: list[dict], columns: tuple[str, ...]) -> str:
    """A Markdown table of ``rows`` in ``columns`` (3 significant digits; empty when absent)."""

    def cell(v: object) -> str:
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"
        return "" if v is None else str(v)

    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(cell(r.get(c)) for c in columns) + " |" for r in rows]
    return "\n".join(lines) + "\n"


# the flags the benches share, as the reconstruction's settings (recon/presets.py names them)
FLAG_SETTINGS = {
    "iterations": "stage1.iterations",
    "resolution": "stage1.resolution",
    "material_iterations": "stage2.iterations",
}
STAGE_PARTS = {"radiance": ("stage1",), "material": ("stage2",), "all": ("stage1", "stage2")}


def flag_settings(stage: str = "all", **flags: object) -> dict[str, object]:
    """The settings a bench's flags give over the preset's, by dotted name (iterations=N:
    {"stage1.iterations": N}; FLAG_SETTINGS), leaving out those not given (None) and those of
    a stage that ``stage`` does not run (reconstruct() refuses them)."""
    out = {}
    for flag, value in flags.items():
        name = FLAG_SETTINGS[flag]
        if value is not None and name.split(".")[0] in STAGE_PARTS[stage]:
            out[name] = value
    return out


def scene_file(scene: str) -> Path:
    """The scene file of ``scene``: one of the simulator's example scenes by name, or a path."""
    return Path(scene) if scene.endswith(".toml") else SCENES / f"{scene}.toml"


def scene_label(scene: str) -> str:
    """A scene's name in tables and folder names: an example scene's, or a file's stem."""
    return Path(scene).stem


def session_of(scene: str) -> Path:
    """The session of ``scene``: a session file (.h5) as it is; a scene (an example scene's
    name, or a .toml) simulated once into results/sessions/ (again when the renderer has
    changed since)."""
    from evcap.records import GroundTruth
    from evcap.session import Session
    from evcap.sim.render import RENDERER_VERSION
    from evcap.sim.scene import load_scene
    from evcap.sim.simulate import simulate

    if scene.endswith(".h5"):
        return Path(scene)
    path = RESULTS / "sessions" / f"{scene_label(scene)}.h5"
    if path.exists():  # made by an older renderer: its truth is not today's
        with Session.open(path, validate=False) as s:
            stale = GroundTruth.read(s).renderer_version != RENDERER_VERSION
        if stale:
            path.unlink()
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        print(f"simulating {scene} (once) ...", flush=True)
        simulate(load_scene(scene_file(scene)), path)
    return path


def export_commit(ref: str, root: Path) -> tempfile.TemporaryDirectory:
    """The tree of commit ``ref`` of the repository at ``root``, in a temporary folder (a
    baseline's code, measured beside this checkout's)."""
    folder = tempfile.TemporaryDirectory()
    tree = subprocess.run(
        ["git", "-C", str(root), "archive", ref], check=True, capture_output=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", folder.name], input=tree, check=True)
    return folder
