"""The method's ablations of stage II on the simulator's example scenes: the full model, then
each of its terms and effects left out (brightness anchor, edge-guided TV, radiance
distillation, visibility, indirect light). Stage I is fitted once per scene and shared, so the
rows differ by stage II alone. Base color is also measured inside the shadows and the color
bleeding that the simulator's ground truth marks. Writes a table (JSON and Markdown) beside
the method's published means.

    .venv/bin/python bench/ablation.py [--scenes single_object multi_object] [--preset tiny]
        [--variants full "no visibility" ...] [--material-iterations N] [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

from _common import RESULTS, machine, session_of

from evcap.recon.reconstruct import reconstruct

# name -> reconstruct() settings of stage II
VARIANTS = {
    "full": {},
    "no anchor": {"ablate": ("anchor",)},
    "no edge TV": {"ablate": ("tv",)},
    "no distillation": {"ablate": ("distill",)},
    "no visibility": {"visibility": "off"},
    "no indirect": {"indirect": "off"},
}
SWITCHES_EFFECT = {"no visibility": "visibility", "no indirect": "indirect"}
# method.md: the published means and ablations (7 NeRF-Synthetic scenes, its own renderer)
PUBLISHED = {
    "full": {"normal_mae_deg": 28.93, "base_color_psnr": 22.31, "render_psnr": 22.11},
    "no anchor": {"normal_mae_deg": 36.87, "base_color_psnr": 19.18, "render_psnr": 20.51},
    "no edge TV": {"normal_mae_deg": 35.70, "base_color_psnr": 20.69, "render_psnr": 21.52},
    "no distillation": {"render_psnr": 17.22},
}
COLUMNS = (
    "scene",
    "variant",
    "effects",
    "normal_mae_deg",
    "base_color_psnr_cc",
    "base_color_psnr_cc_shadow",
    "base_color_psnr_cc_bleeding",
    "roughness_mae",
    "pbr_render_psnr_cc",
    "material_seconds",
)


def cell(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"
    return "" if v is None else str(v)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenes", nargs="+", default=["single_object", "multi_object"])
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--material-iterations", type=int, help="stage II steps (preset's)")
    args = parser.parse_args()
    rows, stage_one = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.scenes:
            session = session_of(scene)
            base = Path(tmp) / scene
            started = time.perf_counter()
            first = reconstruct(
                session, base, preset=args.preset, device=args.device, stage="radiance"
            )
            stage_one[scene] = {
                "render_psnr_cc": first.figures.render_psnr_cc,
                "normal_mae_deg": first.figures.normal_mae_deg,
                "seconds": time.perf_counter() - started,
            }
            full_effects = None
            for name in args.variants:
                settings = VARIANTS[name]
                effect = SWITCHES_EFFECT.get(name)
                if effect and full_effects is not None and not full_effects[effect]:
                    continue  # the full model left it out already on this scene
                out = Path(tmp) / f"{scene}-{name.replace(' ', '-')}"
                shutil.copytree(base, out)
                result = reconstruct(
                    session,
                    out,
                    preset=args.preset,
                    device=args.device,
                    stage="material",
                    material_iterations=args.material_iterations,
                    overwrite=True,
                    **settings,
                )
                if name == "full":
                    full_effects = result.effects
                on = ",".join(k for k, v in result.effects.items() if v)
                found = {k: v for k, v in result.to_json().items() if k != "training_log"}
                row = {"scene": scene, "variant": name, **found, "effects": on}
                rows.append(row)
                print(" ".join(f"{c}={cell(row.get(c))}" for c in COLUMNS), flush=True)
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(cell(r.get(c)) for c in COLUMNS) + " |" for r in rows]
    lines += ["", "The method's published means (NeRF-Synthetic, raw PSNR):", ""]
    lines += ["| variant | normal MAE deg | base color PSNR | render PSNR |", "|---|---|---|---|"]
    for name, p in PUBLISHED.items():
        values = [p.get(k) for k in ("normal_mae_deg", "base_color_psnr", "render_psnr")]
        lines.append(f"| {name} | " + " | ".join(cell(v) for v in values) + " |")
    table = "\n".join(lines) + "\n"
    RESULTS.mkdir(exist_ok=True)
    name = "ablation" if args.preset == "tiny" else f"ablation_{args.preset}"
    (RESULTS / f"{name}.json").write_text(
        json.dumps(
            {
                "benchmark": "ablation",
                "machine": machine(),
                "preset": args.preset,
                "stage_one": stage_one,
                "runs": rows,
                "published": PUBLISHED,
            },
            indent=2,
        )
    )
    (RESULTS / f"{name}.md").write_text(table)
    print(table)
    print(f"-> {RESULTS / name}.json, .md")


if __name__ == "__main__":
    main()
