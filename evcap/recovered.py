"""Whether a reconstruction recovered the object, as a user judges it against the truth: its
silhouette, its normals and depth, its pixels against a constant color after one gain, the
backdrop seen through. ``shortfalls`` names each figure that misses its bar; a disc facing the
camera, a blob and an empty scene each miss one (tests/recon/test_recovered.py)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass


@dataclass(frozen=True)
class Bar:
    """What a reconstruction's held-out figures must reach (the demo's: issue 72)."""

    silhouette_iou: float = 0.9
    """The rendered silhouette against the truth's, at least."""
    normals_deg: float = 15.0
    """Stage I's normals, mean angle on the object, at most."""
    depth_rel_err: float = 0.05
    """The depth's mean error as a share of the distance, at most."""
    over_constant_db: float = 3.0
    """The object after one gain per channel over the best constant color, at least (dB)."""
    background_clear: float = 0.9
    """The pixels off the object seen through, at least."""


@dataclass(frozen=True)
class Check:
    """One figure against its bar."""

    name: str
    value: float | None
    """None: not measured."""
    limit: float
    sense: str
    """">=" or "<=": which side of ``limit`` passes."""
    unit: str

    @property
    def met(self) -> bool:
        v = self.value
        return v is not None and (v >= self.limit if self.sense == ">=" else v <= self.limit)

    def __str__(self) -> str:
        shown = "not measured" if self.value is None else f"{self.value:.3g}{self.unit}"
        return f"{self.name} {shown}, the bar {self.sense} {self.limit:g}{self.unit}"


def checks(figures: Mapping[str, float | None], bar: Bar = Bar()) -> list[Check]:
    """Each of ``bar``'s figures as measured in ``figures`` (metrics.json's names), in the
    order a user reads them."""
    normals = figures.get("radiance_normal_mae_deg")  # stage I's; the last stage's without it
    normals = figures.get("normal_mae_deg") if normals is None else normals
    gain, constant = figures.get("object_psnr_gain"), figures.get("object_psnr_constant")
    over = None if gain is None or constant is None else gain - constant
    return [
        Check("silhouette IoU", figures.get("silhouette_iou"), bar.silhouette_iou, ">=", ""),
        Check("normals", normals, bar.normals_deg, "<=", " deg"),
        Check("depth error", figures.get("depth_rel_err"), bar.depth_rel_err, "<=", ""),
        Check("object over a constant color", over, bar.over_constant_db, ">=", " dB"),
        Check("backdrop clear", figures.get("background_clear"), bar.background_clear, ">=", ""),
    ]


def shortfalls(figures: Mapping[str, float | None], bar: Bar = Bar()) -> list[str]:
    """Each figure of ``figures`` that misses ``bar``, with its value and the bar; a figure not
    measured counts as missed (NaN fails both senses). [] when the object is recovered."""
    return [str(c) for c in checks(figures, bar) if not c.met]
