"""What accuracy costs in time: stage I of `evcap reconstruct` on the simulator's example scenes,
for the presets and a sweep of iterations and render resolution around `fast`. Records quality
on the held-out views (on the object's pixels: PSNR raw, PSNR and SSIM after one gain, beside the
best constant color's PSNR; normal and depth error; whole-image PSNR beside the blurred truth's)
against wall time and Gaussian count; writes a table (JSON and Markdown) and a plot (PNG).

    .venv/bin/python bench/recon_pareto.py [--scenes single_object] [--presets tiny fast]
        [--seeds 3] [--iterations 1000 3000 6000] [--resolutions 0.5 1.0] [--device cpu]
        [--merge] [--figure PNG]

--merge keeps the rows of the previous results that this run does not redo, so the sweep can
be run apart from the presets (`--presets --seeds 0 --merge`).

The scenes are simulated once into bench/results/sessions/ (a few minutes each). `paper` is
for a GPU: name it with --presets and --device cuda. The plot needs matplotlib
(`pip install -e '.[bench]'`).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from _common import RESULTS, flag_settings, machine, markdown_table, scene_label, session_of

from evcap.recon.options import ReconstructOptions
from evcap.recon.presets import PRESETS
from evcap.recon.reconstruct import reconstruct

FAST = (PRESETS["fast"].iterations, PRESETS["fast"].resolution)
LABELS = {"preset": "presets", "seed": "fast, other seeds", "sweep": "fast: iterations, scale"}
COLUMNS = (
    "scene",
    "run",
    "iterations",
    "resolution",
    "seconds",
    "gaussians",
    "object_psnr",
    "object_psnr_gain",
    "object_psnr_constant",
    "object_ssim_gain",
    "normal_mae_deg",
    "depth_rel_err",
    "render_psnr",
    "render_psnr_gain",
    "blur_psnr",
)


def is_fast(row: dict) -> bool:
    """A sweep row with the fast preset's own steps and scale (the preset's row says it)."""
    return row["group"] == "sweep" and (row["iterations"], row["resolution"]) == FAST


def run_one(session: Path, preset: str, device: str, seed: int = 0, **flags: object) -> dict:
    """Stage I's result as a row: its figures beside the run's fields (no training log);
    ``flags``: its iterations and resolution (the preset's where not given)."""
    settings = flag_settings("radiance", **flags)
    options = ReconstructOptions(
        preset=preset, stage="radiance", device=device, seed=seed, settings=settings
    )
    with tempfile.TemporaryDirectory() as out:
        result = reconstruct(session, out, options)
    return {k: v for k, v in result.to_json().items() if k != "training_log"}


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = sorted({r["scene"] for r in rows})
    fig, axes = plt.subplots(2, len(scenes), figsize=(6 * len(scenes), 7.6), squeeze=False)
    for column, scene in enumerate(scenes):
        mine = [r for r in rows if r["scene"] == scene]
        for ax, key in zip(axes[:, column], ("object_psnr_gain", "normal_mae_deg"), strict=True):
            for group, marker in (("preset", "o"), ("seed", "^"), ("sweep", "s")):
                pts = [r for r in mine if r["group"] == group and r.get(key) is not None]
                if not pts:
                    continue
                x = [r["seconds"] / 60 for r in pts]
                y = [r[key] for r in pts]
                sizes = [20 + r["gaussians"] / 1000 for r in pts]
                ax.scatter(x, y, s=sizes, marker=marker, label=LABELS[group], alpha=0.8)
                for r, xy in zip(pts, zip(x, y, strict=True), strict=True):
                    ax.annotate(r["run"], xy, fontsize=7, xytext=(4, 2), textcoords="offset points")
            ax.set_xscale("log")
            ax.grid(alpha=0.3)
        constant = [r["object_psnr_constant"] for r in mine if r.get("object_psnr_constant")]
        top, bottom = axes[0, column], axes[1, column]
        if constant:
            top.axhline(max(constant), color="gray", ls="--", lw=1, label="a constant color")
        top.set_ylabel("object PSNR after one gain, dB")
        top.set_title(f"stage I on {scene}, held-out views ({rows[0]['device']})")
        top.legend(fontsize=8)
        bottom.set_ylabel("normal error on the object, degrees")
        bottom.set_xlabel("wall time, minutes (log); marker area ~ Gaussians")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenes", nargs="+", default=["single_object"])
    parser.add_argument("--presets", nargs="*", default=["tiny", "fast"])
    parser.add_argument("--iterations", nargs="*", type=int, default=[1000, 3000, 6000])
    parser.add_argument("--resolutions", nargs="*", type=float, default=[0.5, 1.0])
    parser.add_argument("--seeds", type=int, default=3, help="runs of fast with seeds 0..N-1")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--merge", action="store_true", help="keep the previous rows not rerun")
    parser.add_argument("--figure", type=Path, help="also write the plot here")
    args = parser.parse_args(argv)

    rows = []
    previous = RESULTS / "recon_pareto.json"
    kept = json.loads(previous.read_text())["runs"] if args.merge and previous.exists() else []

    def record(scene: str, group: str, name: str, result: dict) -> None:
        row = {"scene": scene, "group": group, "run": name, **result}
        rows.append(row)
        print(" ".join(f"{c}={row.get(c)}" for c in COLUMNS), flush=True)

    for given in args.scenes:
        session, scene = session_of(given), scene_label(given)
        for preset in args.presets:
            result = run_one(session, preset, args.device)
            record(scene, "preset", preset, {**result, "resolution": None})
        for seed in range(1, args.seeds):  # seed 0 is the fast preset's run above
            result = run_one(session, "fast", args.device, seed=seed)
            record(scene, "seed", f"fast, seed {seed}", {**result, "resolution": None})
        has_fast = any(r["scene"] == scene and r["run"] == "fast" for r in kept + rows)
        for iterations in args.iterations:
            for resolution in args.resolutions:
                if has_fast and (iterations, resolution) == FAST:
                    continue  # that is the fast preset
                result = run_one(
                    session, "fast", args.device, iterations=iterations, resolution=resolution
                )
                name = f"{iterations} it, x{resolution:g}"
                record(scene, "sweep", name, {**result, "resolution": resolution})

    redone = {(r["scene"], r["run"]) for r in rows}
    rows = [r for r in kept if (r["scene"], r["run"]) not in redone and not is_fast(r)] + rows
    spread = {}
    for scene in map(scene_label, args.scenes):
        seeded = [
            r["object_psnr_gain"]
            for r in rows
            if r["scene"] == scene and (r["group"] == "seed" or r["run"] == "fast")
        ]
        if len(seeded) > 1:
            spread[scene] = (max(seeded) - min(seeded), len(seeded))
    table = markdown_table(rows, COLUMNS) + "".join(
        f"\n{scene}: object PSNR over {n} seeds of fast spans {s:.2f} dB\n"
        for scene, (s, n) in spread.items()
    )
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "recon_pareto.json").write_text(
        json.dumps(
            {
                "benchmark": "recon_pareto",
                "machine": machine(),
                "runs": rows,
                "seed_spread_db": {scene: s for scene, (s, _) in spread.items()},
            },
            indent=2,
        )
    )
    (RESULTS / "recon_pareto.md").write_text(table)
    print(table)
    try:
        plot(rows, RESULTS / "recon_pareto.png")
    except ImportError:
        print("no matplotlib: the plot is skipped (pip install -e '.[bench]')")
        return rows
    if args.figure:
        args.figure.parent.mkdir(parents=True, exist_ok=True)
        plot(rows, args.figure)
    print(f"-> {RESULTS / 'recon_pareto.json'}, .md, .png")
    return rows


if __name__ == "__main__":
    main()
