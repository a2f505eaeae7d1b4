"""Stage I geometry: each candidate change against the settings as they are, over seeds, on
the held-out views: the object's pixels (PSNR raw and after one gain beside a constant color's,
normal error, depth error as a share of the distance), the silhouette against the truth's
(IoU) and the backdrop left clear; each figure's mean and spread (largest less smallest) over
the seeds, and the time it took.

    .venv/bin/python bench/geometry.py [--scenes single_object multi_object] [--preset fast]
        [--iterations N] [--resolution X] [--seeds 0 1 2] [--variants base binary ...] [--merge]

A variant is a name and the stage-I settings it changes (VARIANTS, by their dotted names within
stage I: recon/radiance/config.py); `base` changes nothing.
Seeds 0, 1, 2 (the default) report a change; choose among changes on tuning seeds (3 and up).
--iterations and --resolution screen the variants on a shorter run than the preset's.
--merge keeps the rows of the previous results that this run does not redo.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from _common import RESULTS, flag_settings, machine, markdown_table, scene_label, session_of

from evcap.recon.options import ReconstructOptions
from evcap.recon.reconstruct import reconstruct

VARIANTS: dict[str, dict] = {
    "base": {},
    "no spread": {"loss.spread.weight": 0.0},
    "spread 1": {"loss.spread.weight": 1.0},
    "spread 30": {"loss.spread.weight": 30.0},
    "no background first": {"background.first": 0.0},
    "background first 0.2": {"background.first": 0.2},
    "no smoothing": {"loss.smooth.weight": 0.0},
    "smoothing 0.1": {"loss.smooth.weight": 0.1},
    "smoothing 1": {"loss.smooth.weight": 1.0},
    "curvature": {"loss.curvature.weight": 1.0},
    "binary": {"loss.binary.weight": 0.1},
    "flatten": {"loss.flatten.weight": 0.1},
    "confine": {"densify.confine": 1.5},
    "alpha 0.1": {"loss.alpha.weight": 0.1},
    "no alpha": {"loss.alpha.weight": 0.0},
    "no background variation": {"loss.background_tv.weight": 0.0},
    "neither": {"loss.alpha.weight": 0.0, "loss.background_tv.weight": 0.0},
    "opacity 0.05": {"loss.opacity.weight": 0.05},
    "init 1000": {"init.gaussians": 1000},
    "background 256": {"background.size": 256},
    "normal 0.2": {"loss.normal.weight": 0.2},
    "normal late": {"loss.normal.start": 0.3},
    "bound": {"event_loss.zero_events": "bound"},
    "silent 0.1": {"event_loss.silent_weight": 0.1},
    "quiet tv 1": {"loss.quiet_tv.weight": 1.0},
    "coarse to fine": {"coarse.until": 0.3, "coarse.resolution": 0.375},
}
FIGURES = (
    "seconds",
    "gaussians",
    "object_psnr",
    "object_psnr_gain",
    "object_psnr_constant",
    "normal_mae_deg",
    "depth_rel_err",
    "silhouette_iou",
    "background_clear",
    "render_psnr",
    "render_psnr_gain",
)
COLUMNS = ("scene", "variant", "seed", "iterations", "resolution", *FIGURES)
SPREAD_COLUMNS = ("scene", "variant", "seeds") + tuple(
    f"{f} {part}" for f in FIGURES[2:] for part in ("mean", "spread")
)


def over_seeds(rows: list[dict]) -> list[dict]:
    """Each (scene, variant)'s figures over its seeds: the mean and the spread (largest less
    smallest)."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["variant"], r["iterations"]), []).append(r)
    out = []
    for (scene, variant, _), runs in groups.items():
        row: dict = {"scene": scene, "variant": variant}
        row["seeds"] = " ".join(str(r["seed"]) for r in runs)
        for f in FIGURES[2:]:
            values = [r[f] for r in runs if r.get(f) is not None]
            if values:
                row[f"{f} mean"] = sum(values) / len(values)
                row[f"{f} spread"] = max(values) - min(values)
        out.append(row)
    return out


def run(session: Path, preset: str, seed: int, args: argparse.Namespace, settings: dict) -> dict:
    named = {f"stage1.{k}": v for k, v in settings.items()}
    named |= flag_settings("radiance", iterations=args.iterations, resolution=args.resolution)
    options = ReconstructOptions(preset=preset, stage="radiance", seed=seed, settings=named)
    with tempfile.TemporaryDirectory() as out:
        result = reconstruct(session, out, options)
    return {k: v for k, v in result.to_json().items() if k not in ("history", "training_log")}


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenes", nargs="+", default=["single_object", "multi_object"])
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--iterations", type=int)
    parser.add_argument("--resolution", type=float)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--merge", action="store_true", help="keep the previous rows not rerun")
    args = parser.parse_args(argv)

    path = RESULTS / "geometry.json"
    kept = json.loads(path.read_text())["runs"] if args.merge and path.exists() else []
    rows = []
    for scene in args.scenes:
        session = session_of(scene)
        for name in args.variants:
            for seed in args.seeds:
                started = time.perf_counter()
                result = run(session, args.preset, seed, args, VARIANTS[name])
                row = {
                    "scene": scene_label(scene),
                    "variant": name,
                    "preset": args.preset,
                    "seed": seed,
                    "resolution": args.resolution,
                    "wall_seconds": time.perf_counter() - started,
                    **result,
                }
                rows.append(row)
                print(" ".join(f"{k}={row.get(k)}" for k in COLUMNS), flush=True)

    def key(r: dict) -> tuple:
        return r["scene"], r["variant"], r["iterations"], r.get("seed")

    redone = {key(r) for r in rows}
    rows = [r for r in kept if key(r) not in redone] + rows
    RESULTS.mkdir(exist_ok=True)
    summary = {"benchmark": "geometry", "machine": machine(), "runs": rows}
    path.write_text(json.dumps(summary | {"over_seeds": over_seeds(rows)}, indent=2))
    table = markdown_table(rows, COLUMNS) + "\n" + markdown_table(over_seeds(rows), SPREAD_COLUMNS)
    (RESULTS / "geometry.md").write_text(table)
    print(table)
    print(f"-> {path}, .md")
    return rows


if __name__ == "__main__":
    main()
