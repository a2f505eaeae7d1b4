"""OUT/, the folder `evcap reconstruct` writes, and the one place that names its files:

    config.toml            the settings it ran with ([stage1], [stage2]: by their dotted names,
                           `evcap reconstruct --settings` reads it); [reconstruct] names the session
    metrics.json           what it found (records.result.ReconstructionResult)
    gaussians.ply          stage I's Gaussians (3DGS layout)
    poses.h5               stage I's refined camera path, when it refined it
    environment.png        the light stage II learnt
    checkpoint/            radiance.pt, material.pt; STAGE-state.pt while a stage is unfinished
    renders/               stage I's views; material/: stage II's; relit/: under a new light
    report.html            `evcap report`'s page
    mesh.glb               `evcap view`'s mesh (`evcap export`'s, when asked to write it here)
    viewer.html            `evcap view`'s page

reconstruct, resume, the exports, the report and the pipeline all go through it.
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from evcap.atomic_write import write_text_atomic
from evcap.errors import InputError, InputNotFoundError
from evcap.records.result import ReconstructionResult

Training = Literal["radiance", "material"]  # stage I, stage II
# config.toml's tables: how the run was asked for (the session named), each stage's settings
Section = Literal["reconstruct", "stage1", "stage2"]
Renders = Literal["radiance", "material", "relit"]  # stage I's, stage II's, relit views
Split = Literal["test", "path"]  # the held-out views, or views along the camera path
# a rendered view's maps, each a PNG (radiance_gain: after the one gain per channel)
ViewMap = Literal["radiance", "radiance_gain", "depth", "normal", "base_color", "roughness"]

CONFIG = "config.toml"
METRICS = "metrics.json"
PLY = "gaussians.ply"
POSES = "poses.h5"
ENVIRONMENT = "environment.png"
REPORT = "report.html"
MESH = "mesh.glb"
VIEWER = "viewer.html"
CHECKPOINTS = "checkpoint"
RENDERS = "renders"
RENDER_FOLDERS: dict[Renders, tuple[str, ...]] = {
    "radiance": (),
    "material": ("material",),
    "relit": ("relit",),
}


@dataclass(frozen=True)
class ReconstructionFolder:
    """A reconstruction folder (OUT): where each of its files lies, and reading them."""

    root: Path

    def __init__(self, root: str | Path) -> None:
        object.__setattr__(self, "root", Path(root))

    def __str__(self) -> str:
        return str(self.root)

    # -- where ---------------------------------------------------------------------------------

    @property
    def config(self) -> Path:
        return self.root / CONFIG

    @property
    def metrics(self) -> Path:
        return self.root / METRICS

    @property
    def ply(self) -> Path:
        return self.root / PLY

    @property
    def poses(self) -> Path:
        return self.root / POSES

    @property
    def environment(self) -> Path:
        return self.root / ENVIRONMENT

    @property
    def report(self) -> Path:
        return self.root / REPORT

    @property
    def mesh(self) -> Path:
        return self.root / MESH

    @property
    def viewer(self) -> Path:
        return self.root / VIEWER

    def checkpoint(self, stage: Training) -> Path:
        return self.root / CHECKPOINTS / f"{stage}.pt"

    def training_state(self, stage: Training) -> Path:
        """Where an unfinished stage's training state lies."""
        return self.root / CHECKPOINTS / f"{stage}-state.pt"

    def renders(self, kind: Renders = "radiance") -> Path:
        return self.root.joinpath(RENDERS, *RENDER_FOLDERS[kind])

    def views_values(self, kind: Renders, split: Split) -> Path:
        """The exact values of the rendered views (.npz, one array per map)."""
        return self.renders(kind) / f"{split}.npz"

    def view_image(self, kind: Renders, split: Split, index: int, map: ViewMap) -> Path:
        """One map of one rendered view as a PNG; a relit view is its radiance alone."""
        if kind == "relit":
            return self.renders(kind) / f"{split}_{index:03d}.png"
        return self.renders(kind) / f"{split}_{index:03d}_{map}.png"

    @property
    def relit_environment(self) -> Path:
        """The new light the relit views are lit by."""
        return self.renders("relit") / ENVIRONMENT

    def relit_views(self) -> list[Path]:
        folder = self.renders("relit")
        return sorted(p for p in folder.glob("*.png") if p.name != ENVIRONMENT)

    def rendered_images(self) -> list[Path]:
        """Every PNG of the stages' rendered views (not the relit ones), in order."""
        folder, relit = self.renders(), self.renders("relit")
        if not folder.is_dir():
            return []
        return sorted(p for p in folder.rglob("*.png") if relit not in p.parents)

    def shown_views(self) -> list[Path]:
        """The rendered views a page shows: stage II's render where there is one, else stage
        I's radiance after its gain where it was, held-out views first; else stage I's
        radiance as rendered."""
        for kind, map in (("material", "radiance"), ("radiance", "radiance_gain")):
            for split in ("test", "path"):
                first = self.view_image(kind, split, 0, map)  # type: ignore[arg-type]
                if first.exists():
                    return sorted(first.parent.glob(first.name.replace("_000_", "_*_")))
        return sorted(self.renders().glob("*_radiance.png"))

    # -- what it holds -------------------------------------------------------------------------

    def holds_reconstruction(self) -> bool:
        """A reconstruction was started here (settings, results or stage I's checkpoint)."""
        return any(p.exists() for p in (self.config, self.metrics, self.checkpoint("radiance")))

    def finished(self) -> bool:
        """A run ended here and said what it found."""
        return self.metrics.exists()

    def stage_done(self, stage: Training) -> bool:
        """The stage's outputs are here (stage I's Gaussians, stage II's checkpoint)."""
        return (self.ply if stage == "radiance" else self.checkpoint("material")).exists()

    def check(self) -> None:
        """InputError unless this is a reconstruction folder, saying what to give instead."""
        hint = "give the OUT folder of `evcap reconstruct SESSION -o OUT`"
        if not self.root.is_dir():
            raise InputNotFoundError(f"{self.root}: no such folder; {hint}")
        if not self.holds_reconstruction():
            marks = (self.config, self.metrics, self.checkpoint("radiance"))
            names = ", ".join(str(p.relative_to(self.root)) for p in marks)
            raise InputError(
                f"{self.root} is not a reconstruction folder (it has none of {names}); {hint}"
            )

    # -- settings and results ------------------------------------------------------------------

    def write_config(self, sections: dict[str, dict]) -> None:
        """The settings as TOML, one table per section, a nested dict a table under it
        ([stage1.densify]); scalars and lists of numbers (None left out)."""
        lines: list[str] = []

        def table(name: str, values: dict) -> None:
            lines.append(f"[{name}]")
            nested = {k: v for k, v in values.items() if isinstance(v, dict)}
            for k, v in values.items():
                if isinstance(v, bool):
                    lines.append(f"{k} = {str(v).lower()}")
                elif isinstance(v, int | float):
                    lines.append(f"{k} = {v!r}")
                elif isinstance(v, list | tuple) and all(isinstance(x, int | float) for x in v):
                    lines.append(f"{k} = [{', '.join(repr(x) for x in v)}]")
                elif v is not None and k not in nested:
                    lines.append(f"{k} = {json.dumps(str(v))}")
            lines.append("")
            for k, v in nested.items():
                table(f"{name}.{k}", v)

        for section, values in sections.items():
            table(section, values)
        write_text_atomic(self.config, "\n".join(lines))

    def read_config(self) -> dict:
        """config.toml's tables ({} when there is none)."""
        if not self.config.exists():
            return {}
        try:
            return tomllib.loads(self.config.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise InputError(f"{self.config} is not valid TOML: {e}") from None

    def settings(self, section: Section) -> dict:
        """One table of config.toml ({} when it is not there)."""
        return self.read_config().get(section, {})

    def session(self) -> Path:
        """The session the reconstruction was made from, as config.toml names it; a relative
        name is relative to where `evcap reconstruct` ran: tried from here, then beside OUT."""
        named = self.settings("reconstruct").get("session")
        if not named:
            raise InputError(
                f"{self.config} does not name the session the reconstruction was made from; "
                "name it with --session SESSION"
            )
        path = Path(named)
        for candidate in (path, self.root / path, self.root.parent / path):
            if candidate.is_file():
                return candidate
        raise InputNotFoundError(
            f"the session {named} that {self.config} names is not there (seen from "
            f"{Path.cwd()}); name it with --session SESSION"
        )

    def read_result(self) -> ReconstructionResult:
        return ReconstructionResult.read(self.metrics)

    def write_result(self, result: ReconstructionResult) -> Path:
        return result.write(self.metrics)

    def previous_result(self) -> ReconstructionResult:
        """What an earlier run found (nothing when it did not finish)."""
        return self.read_result() if self.finished() else ReconstructionResult()
