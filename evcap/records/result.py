"""What a reconstruction found (OUT/metrics.json, through ReconstructionFolder).
``ReconstructionResult`` is its one writer (`evcap reconstruct`) and reader (the CLI, the
demo, the report, the benches); ``Figures`` names and describes each accuracy figure once."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from evcap.atomic_write import write_text_atomic
from evcap.errors import InputError

STAGE_I, STAGE_II, RUN = "stage I (radiance)", "stage II (material)", "run"
# the figures a user is shown after a run (`evcap reconstruct`, the demo, `evcap batch`'s
# summary), in this order; metrics.json and the report hold them all
SHOWN = (
    "object_psnr",
    "object_psnr_gain",
    "object_psnr_constant",
    "normal_mae_deg",
    "depth_rel_err",
    "depth_within_5pct",
    "background_clear",
    "silhouette_iou",
    "render_psnr",
    "render_psnr_gain",
    "blur_psnr",
    "base_color_psnr",
    "base_color_psnr_gain",
    "base_color_psnr_constant",
    "base_color_psnr_gain_baseline",
    "roughness_mae",
    "pbr_render_psnr",
    "pbr_render_psnr_gain",
    "relit_object_psnr",
    "relit_object_psnr_gain",
    "relit_object_psnr_constant",
    "relit_object_psnr_gain_baseline",
)


def _figure(name: str, unit: str, stage: str):
    return field(default=None, metadata={"name": name, "unit": unit, "stage": stage})


@dataclass
class Figures:
    """The accuracy figures on the held-out views (None: not measured, e.g. no truth; NaN:
    measured without a number, e.g. LPIPS without its weights). Images are compared in sRGB,
    raw first; ``_gain``: after one gain per color channel fitted once by least squares (linear
    radiance) over the scored pixels of all held-out views, relit views with the gain of their
    un-relit fit; ``object_``: on the object's pixels only; ``_affine_per_view``: a diagnostic,
    never a result."""

    object_psnr: float | None = _figure("object PSNR, as rendered", "dB", STAGE_I)
    object_psnr_gain: float | None = _figure("object PSNR, after one gain", "dB", STAGE_I)
    object_psnr_constant: float | None = _figure(
        "object PSNR of the best constant color (no object)", "dB", STAGE_I
    )
    object_psnr_affine_per_view: float | None = _figure(
        "object PSNR after an affine fit per view (diagnostic only)", "dB", STAGE_I
    )
    object_ssim_gain: float | None = _figure("object SSIM, after one gain", "", STAGE_I)
    render_psnr: float | None = _figure("render PSNR", "dB", STAGE_I)
    render_ssim: float | None = _figure("render SSIM", "", STAGE_I)
    render_psnr_gain: float | None = _figure("render PSNR, after one gain", "dB", STAGE_I)
    render_ssim_gain: float | None = _figure("render SSIM, after one gain", "", STAGE_I)
    blur_psnr: float | None = _figure(
        "PSNR of the truth blurred by 25 px (whole image)", "dB", STAGE_I
    )
    lpips: float | None = _figure("LPIPS (AlexNet)", "", STAGE_I)
    depth_rel_err: float | None = _figure("depth error, share of the distance", "", STAGE_I)
    depth_abs_err: float | None = _figure("depth error, mean absolute", "scene units", STAGE_I)
    depth_within_5pct: float | None = _figure(
        "object pixels with their depth within 5 %", "fraction", STAGE_I
    )
    background_clear: float | None = _figure(
        "pixels off the object seen through (alpha < 0.5)", "fraction", STAGE_I
    )
    silhouette_iou: float | None = _figure(
        "silhouette (alpha >= 0.5) against the object's, intersection over union", "", STAGE_I
    )
    radiance_normal_mae_deg: float | None = _figure("normal error, mean angle", "deg", STAGE_I)
    # the last stage's normals: stage II's after it, else stage I's
    normal_mae_deg: float | None = _figure("normal error, mean angle", "deg", STAGE_II)
    pbr_render_psnr: float | None = _figure("shaded render PSNR", "dB", STAGE_II)
    pbr_render_ssim: float | None = _figure("shaded render SSIM", "", STAGE_II)
    pbr_render_psnr_gain: float | None = _figure(
        "shaded render PSNR, after one gain", "dB", STAGE_II
    )
    pbr_render_ssim_gain: float | None = _figure("shaded render SSIM, after one gain", "", STAGE_II)
    base_color_psnr: float | None = _figure("base color PSNR", "dB", STAGE_II)
    base_color_ssim: float | None = _figure("base color SSIM", "", STAGE_II)
    base_color_psnr_gain: float | None = _figure("base color PSNR, after one gain", "dB", STAGE_II)
    base_color_ssim_gain: float | None = _figure("base color SSIM, after one gain", "", STAGE_II)
    base_color_psnr_constant: float | None = _figure(
        "base color PSNR of the best constant color", "dB", STAGE_II
    )
    base_color_psnr_gain_baseline: float | None = _figure(
        "stage I's radiance taken as the base color, PSNR after one gain", "dB", STAGE_II
    )
    base_color_psnr_gain_shadow: float | None = _figure(
        "base color PSNR in shadows", "dB", STAGE_II
    )
    shadow_share: float | None = _figure("surface in shadow", "fraction", STAGE_II)
    base_color_psnr_gain_bleeding: float | None = _figure(
        "base color PSNR where color bleeds", "dB", STAGE_II
    )
    bleeding_share: float | None = _figure("surface with color bleeding", "fraction", STAGE_II)
    roughness_mae: float | None = _figure("roughness error, mean absolute", "", STAGE_II)
    relit_psnr: float | None = _figure("relit render PSNR", "dB", STAGE_II)
    relit_ssim: float | None = _figure("relit render SSIM", "", STAGE_II)
    relit_psnr_gain: float | None = _figure("relit render PSNR, after one gain", "dB", STAGE_II)
    relit_ssim_gain: float | None = _figure("relit render SSIM, after one gain", "", STAGE_II)
    relit_object_psnr: float | None = _figure("relit object PSNR", "dB", STAGE_II)
    relit_object_ssim: float | None = _figure("relit object SSIM", "", STAGE_II)
    relit_object_psnr_gain: float | None = _figure(
        "relit object PSNR, after one gain", "dB", STAGE_II
    )
    relit_object_ssim_gain: float | None = _figure(
        "relit object SSIM, after one gain", "", STAGE_II
    )
    relit_object_psnr_constant: float | None = _figure(
        "relit object PSNR of the best constant color", "dB", STAGE_II
    )
    relit_object_psnr_gain_baseline: float | None = _figure(
        "the views never relit, object PSNR against the relit truth, after one gain",
        "dB",
        STAGE_II,
    )

    @classmethod
    def of(cls, figures: dict[str, float | None]) -> Figures:
        """The figures named in ``figures``; one given as None was measured without a number
        (NaN, shown as n/a), unlike one not given at all."""
        unknown = set(figures) - set(cls.names())
        if unknown:
            raise ValueError(f"unknown figures {sorted(unknown)}: describe them in Figures")
        return cls(**{k: math.nan if v is None else float(v) for k, v in figures.items()})

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def describe(cls, name: str) -> tuple[str, str, str]:
        """(readable name, unit, stage) of a figure."""
        f = {f.name: f for f in dataclasses.fields(cls)}[name]
        return f.metadata["name"], f.metadata["unit"], f.metadata["stage"]

    def measured(self) -> dict[str, float]:
        """The figures that were measured, by name, in the order above."""
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}

    def shown(self) -> dict[str, float]:
        """The measured figures of SHOWN, in its order."""
        measured = self.measured()
        return {k: measured[k] for k in SHOWN if k in measured}


@dataclass
class ReconstructionResult:
    """What `evcap reconstruct` found and how it ran; OUT/metrics.json."""

    views: str = ""  # what the figures were measured on
    figures: Figures = field(default_factory=Figures)
    preset: str | None = None
    seed: int | None = None
    zero_events: str | None = None  # what pixels without events were taken to mean
    device: str | None = None
    backend: str | None = None
    interrupted: bool = False  # by Ctrl-C: what was learnt so far
    # stage I (radiance)
    iterations: int | None = None
    gaussians: int | None = None
    seconds: float | None = None
    history: list[dict] = field(default_factory=list)  # figures along the training
    # stage II (material)
    material_iterations: int | None = None
    material_seconds: float | None = None
    effects: dict[str, bool] | None = None  # each effect and term: modelled or not
    # where "auto" chose visibility and indirect light: the base color's variation at stage
    # II's start under each choice (recon.material.base_variation; the lowest was chosen)
    effect_variation: dict[str, float] | None = None
    relit: bool | None = None  # relit under a new light
    # the training losses along the way, per stage ("radiance", "material")
    training_log: dict[str, list[dict]] = field(default_factory=dict)

    @property
    def has_material(self) -> bool:
        return self.material_iterations is not None

    # -- metrics.json --------------------------------------------------------------------------

    def to_json(self) -> dict:
        """The flat JSON object of metrics.json: the figures beside the run's fields (those
        that are set: a stage-I run has no stage-II fields)."""
        out = {k: v for k, v in vars(self).items() if k != "figures" and v is not None}
        out.update(self.figures.measured())
        return _clean(out)

    @classmethod
    def from_json(cls, data: dict) -> ReconstructionResult:
        names = {f.name for f in dataclasses.fields(cls)} - {"figures"}
        figures = Figures.of({k: data[k] for k in Figures.names() if k in data})
        return cls(figures=figures, **{k: v for k, v in data.items() if k in names})

    def write(self, path: Path) -> Path:
        write_text_atomic(path, json.dumps(self.to_json(), indent=2) + "\n")
        return path

    @classmethod
    def read(cls, path: Path) -> ReconstructionResult:
        """The result in ``path``; InputError naming the problem when it is missing or
        damaged."""
        if not path.exists():
            raise InputError(f"{path} is not there: the reconstruction did not finish")
        try:
            data = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise InputError(f"{path} is not readable JSON ({e})") from None
        if not isinstance(data, dict):
            raise InputError(f"{path} does not hold a table of results")
        try:
            return cls.from_json(data)
        except TypeError as e:
            raise InputError(f"{path} is not a reconstruction's result ({e})") from None


def _clean(value):
    """JSON-ready: NaN and infinity as null, numpy scalars as Python's."""
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
