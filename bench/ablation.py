"""The method's ablations on the simulator's example scenes: the full model, then each of its
terms and effects left out (brightness anchor, edge-guided TV, radiance distillation, stage I's
normal loss, visibility, indirect light). Stage I is fitted once per scene and shared, so those
rows differ by stage II alone; the anchor (in both stages) and the normal loss (stage I's) fit a
stage I of their own. Each row's change against the full model is set beside the method's own
change (its Tables 2, 4 and 8, summed up in method.md). Base color is also measured inside
the shadows and the color bleeding that the simulator's ground truth marks. Writes a table
(JSON and Markdown) beside the method's published means.

With ``--geometry truth`` stage I does not learn the geometry: it starts on the truth's
surfaces (flat, opaque Gaussians sampled over the scene's meshes) and learns only their
radiance and the background from the events. Stage II then runs on geometry that is right, so
its rows say what its terms and effects can do when stage I has done its part. With
``--light truth`` stage II does not learn the light either: it is held at the truth's (the
scene's sky, and its sun as a 4-degree lobe of the same irradiance), so the rows say what the
terms and effects can do when the light is right too.

    .venv/bin/python bench/ablation.py [--scenes single_object multi_object] [--preset tiny]
        [--variants full "no visibility" ...] [--material-iterations N] [--device cpu]
        [--geometry stage-one|truth] [--iterations N] [--effects auto|on] [--work DIR]
        [--light learnt|truth] [--seed N] [--stage-one KEPT_STAGE_ONE_FOLDER]
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from pathlib import Path

import numpy as np
import torch
from _common import RESULTS, flag_settings, machine, scene_file, scene_label, session_of

import evcap.recon.material.stage as material
import evcap.recon.radiance.stage as radiance
from evcap.recon.options import ReconstructOptions
from evcap.recon.reconstruct import reconstruct
from evcap.recon.scene.gaussians import Background, Gaussians
from evcap.records.reconstruction_folder import RENDERS, ReconstructionFolder
from evcap.sim.lighting import Environment
from evcap.sim.meshes import build_mesh, sample_surface
from evcap.sim.scene import load_scene

# name -> stage II's terms left out (reconstruct()'s ablate) and settings (dotted names), and
# stage I's own settings where the variant changes them (it then fits a stage I of its own; the
# others share one)
VARIANTS = {
    "full": {},
    # the method's brightness anchor holds both stages
    "no anchor": {"ablate": ("anchor",), "stage_one": {"stage1.loss.anchor.weight": 0.0}},
    "no edge TV": {"ablate": ("tv",)},
    "no distillation": {"ablate": ("distill",)},
    "no normal loss": {"stage_one": {"stage1.loss.normal.weight": 0.0}},
    # indirect light stands for what the occluders hide: without visibility it goes too
    "no visibility": {"stage2.visibility": "off", "stage2.indirect": "off"},
    # run only where the full model has it, and so the visibility it goes with
    "no indirect": {"stage2.visibility": "on", "stage2.indirect": "off"},
}
SWITCHES_EFFECT = {"no visibility": "visibility", "no indirect": "indirect"}
# method.md: the published means and ablations (7 NeRF-Synthetic scenes, its own renderer)
PUBLISHED = {
    "full": {"normal_mae_deg": 28.93, "base_color_psnr": 22.31, "render_psnr": 22.11},
    "no anchor": {"normal_mae_deg": 36.87, "base_color_psnr": 19.18, "render_psnr": 20.51},
    "no edge TV": {"normal_mae_deg": 35.70, "base_color_psnr": 20.69, "render_psnr": 21.52},
    "no distillation": {"render_psnr": 17.22},
    "no normal loss": {"normal_mae_deg": 33.45, "render_psnr": 21.98},
}
# ours beside the method's: (our column, the method's, which way is better)
COMPARED = (
    ("normal_mae_deg", "normal_mae_deg", -1),
    ("base_color_psnr_gain", "base_color_psnr", 1),
    ("pbr_render_psnr_gain", "render_psnr", 1),
)
COLUMNS = (
    "scene",
    "variant",
    "effects",
    "normal_mae_deg",
    "base_color_psnr_gain",
    "base_color_psnr_gain_shadow",
    "base_color_psnr_gain_bleeding",
    "base_color_psnr_gain_baseline",
    "relit_object_psnr_gain",
    "roughness_mae",
    "pbr_render_psnr_gain",
    "material_seconds",
)


# stage I on the truth's surfaces: every geometry parameter kept, no densification
TRUTH_GEOMETRY = {
    "stage1.densify.start": 0.0,
    "stage1.densify.stop": 0.0,
    "stage1.background.first": 0.0,
}
TRUTH_GAUSSIANS = 20_000
TRUTH_OPACITY = 0.95


def truth_gaussians(scene: str, sh_degree: int) -> Gaussians:
    """Flat opaque discs sampled over the truth's surfaces, mid-gray."""
    mesh, _, _ = build_mesh(load_scene(scene_file(scene)))
    points, normals, spacing = sample_surface(mesh, TRUTH_GAUSSIANS)
    return Gaussians.on_surface(points, normals, spacing, sh_degree, TRUTH_OPACITY)


@contextmanager
def starting_on_truth(scene: str) -> Iterator[None]:
    """Stage I's start replaced by the truth's surfaces, whose geometry does not learn."""
    original = radiance.new_field

    def new_field(data, config, seed, device, backend):
        g = truth_gaussians(scene, config.sh_degree)
        for name in ("means", "log_scales", "quats", "opacity_logits"):
            getattr(g, name).requires_grad_(False)
        return radiance.RadianceField(g, Background(config.background.size), backend).to(device)

    radiance.new_field = new_field
    try:
        yield
    finally:
        radiance.new_field = original


SUN_WIDTH_DEG = 4.0


def truth_light_image(scene: str, width: int = 512) -> np.ndarray:
    """The scene's environment as a latitude-longitude image, its sun a narrow lobe of the
    sun's irradiance (the simulator's sun is a disc half a degree wide: no cube map holds it)."""
    env = Environment(load_scene(scene_file(scene)).lighting)
    table = env.table(width)
    h = width // 2
    lat = (0.5 - (np.arange(h) + 0.5) / h) * np.pi
    lon = ((np.arange(width) + 0.5) / width - 0.5) * 2 * np.pi
    lat, lon = np.meshgrid(lat, lon, indexing="ij")
    d = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], -1)
    lobe = np.exp(-(1 - d @ env.sun_direction) / (1 - np.cos(np.deg2rad(SUN_WIDTH_DEG))))
    solid = (lobe * np.cos(lat)).sum() * (np.pi / h) * (2 * np.pi / width)
    return table + lobe[..., None] * env.sun_irradiance * env.scale / solid


@contextmanager
def truth_light(scene: str) -> Iterator[None]:
    """Stage II's light held at the truth's."""
    original = material.new_material_field
    image = truth_light_image(scene)

    def new_material_field(radiance_field, data, config):
        field = original(radiance_field, data, config)
        faces = material.light_from_image(image, field.light.faces.shape[-1])[0]
        faces = faces.clamp(min=1e-4).to(field.light.faces.device)
        with torch.no_grad():  # the inverse of the cube map's softplus
            field.light.faces.copy_(faces + torch.log(-torch.expm1(-faces)))
        field.light.faces.requires_grad_(False)
        return field

    material.new_material_field = new_material_field
    try:
        yield
    finally:
        material.new_material_field = original


def cell(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"
    return "" if v is None else str(v)


def change(ours: float | None, full: float | None, better: int) -> str:
    """How much a variant moved a figure against the full model, signed so that + is better."""
    if ours is None or full is None:
        return "-"
    return f"{better * (ours - full):+.2f}"


def directions(rows: list[dict]) -> list[str]:
    """Markdown rows: each variant's change against its scene's full model beside the
    method's change against its full model."""
    heads = ["normal MAE deg", "base color dB", "render dB"]
    lines = ["| scene | variant | " + " | ".join(heads) + " |", "|---|---|---|---|---|"]
    full = {r["scene"]: r for r in rows if r["variant"] == "full"}
    method = PUBLISHED["full"]
    for r in rows:
        if r["variant"] == "full" or r["scene"] not in full:
            continue
        theirs = PUBLISHED.get(r["variant"], {})
        cells = [
            f"{change(r.get(o), full[r['scene']].get(o), b)} / "
            f"{change(theirs.get(m), method.get(m), b)}"
            for o, m, b in COMPARED
        ]
        lines.append(f"| {r['scene']} | {r['variant']} | " + " | ".join(cells) + " |")
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenes", nargs="+", default=["single_object", "multi_object"])
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--material-iterations", type=int, help="stage II steps (preset's)")
    parser.add_argument("--iterations", type=int, help="stage I steps (preset's)")
    parser.add_argument(
        "--geometry",
        default="stage-one",
        choices=["stage-one", "truth"],
        help="stage I learns the geometry, or starts on the truth's surfaces and keeps them",
    )
    parser.add_argument(
        "--effects",
        default="auto",
        choices=["auto", "on"],
        help="visibility and indirect light in the full model: as stage II decides, or on",
    )
    parser.add_argument(
        "--light",
        default="learnt",
        choices=["learnt", "truth"],
        help="stage II learns the light, or holds it at the truth's",
    )
    parser.add_argument("--work", type=Path, help="keep the runs in this folder (default: none)")
    parser.add_argument("--seed", type=int, default=0, help="both stages' seed")
    parser.add_argument(
        "--stage-one",
        type=Path,
        help="a kept stage I of the one scene (a reconstruction folder made with --preset and "
        "--seed) shared by the variants instead of fitting one",
    )
    args = parser.parse_args(argv)
    if args.stage_one is not None and len(args.scenes) != 1:
        parser.error("--stage-one is the stage I of one scene: give one scene")
    rows, stage_one = [], {}
    forced = {"stage2.visibility": "on", "stage2.indirect": "on"} if args.effects == "on" else {}
    truth = args.geometry == "truth"

    def run_of(stage: str, settings: dict, **more: object) -> ReconstructOptions:
        """The options of a run of ``stage`` with ``settings``, the steps asked for over them."""
        steps = {"iterations": args.iterations, "material_iterations": args.material_iterations}
        settings = {**settings, **flag_settings(stage, **steps)}
        how = {"preset": args.preset, "device": args.device, "seed": args.seed}
        return ReconstructOptions(**how, stage=stage, settings=settings, **more)

    def fit_stage_one(scene: str, session: Path, out: Path, settings: dict) -> dict:
        started = time.perf_counter()
        options = run_of("radiance", {**(TRUTH_GEOMETRY if truth else {}), **settings})
        with starting_on_truth(scene) if truth else nullcontext():
            first = reconstruct(session, out, options)
        return {**first.figures.measured(), "seconds": time.perf_counter() - started}

    with tempfile.TemporaryDirectory() as scratch:
        tmp = args.work or scratch
        for scene in args.scenes:
            session = session_of(scene)
            label = scene_label(scene)
            base = Path(tmp) / label
            if args.stage_one is not None:
                kept = ReconstructionFolder(args.stage_one)
                stage_two = kept.checkpoint("material").name
                shutil.copytree(
                    kept.root,
                    base,
                    ignore=shutil.ignore_patterns(RENDERS, stage_two),
                    dirs_exist_ok=True,  # a --work folder run again
                )
                first = ReconstructionFolder(base).read_result()
                stage_one[label] = first.figures.measured()
            else:
                stage_one[label] = fit_stage_one(scene, session, base, {})
            full_effects = None
            for name in args.variants:
                settings = dict(VARIANTS[name])
                own = settings.pop("stage_one", None)
                ablate = settings.pop("ablate", ())
                effect = SWITCHES_EFFECT.get(name)
                if effect and full_effects is not None and not full_effects[effect]:
                    continue  # the full model left it out already on this scene
                out = Path(tmp) / f"{label}-{name.replace(' ', '-')}"
                if own is None:
                    shutil.copytree(
                        base, out, ignore=shutil.ignore_patterns(RENDERS), dirs_exist_ok=True
                    )
                else:
                    stage_one[f"{label} {name}"] = fit_stage_one(scene, session, out, own)
                settings = {**forced, **settings}
                options = run_of("material", settings, ablate=ablate, resume="go on or start over")
                with truth_light(scene) if args.light == "truth" else nullcontext():
                    result = reconstruct(session, out, options)
                if name == "full":
                    full_effects = result.effects
                on = ",".join(k for k, v in result.effects.items() if v)
                found = {k: v for k, v in result.to_json().items() if k != "training_log"}
                row = {"scene": label, "variant": name, **found, "effects": on}
                rows.append(row)
                print(" ".join(f"{c}={cell(row.get(c))}" for c in COLUMNS), flush=True)
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(cell(r.get(c)) for c in COLUMNS) + " |" for r in rows]
    lines += ["", "The method's published means (NeRF-Synthetic, raw PSNR):", ""]
    lines += ["| variant | normal MAE deg | base color PSNR | render PSNR |", "|---|---|---|---|"]
    for name, p in PUBLISHED.items():
        values = [p.get(k) for k in ("normal_mae_deg", "base_color_psnr", "render_psnr")]
        lines.append(f"| {name} | " + " | ".join(cell(v) for v in values) + " |")
    lines += ["", "Each variant against the full model, here / the method's (+ better):", ""]
    lines += directions(rows)
    table = "\n".join(lines) + "\n"
    RESULTS.mkdir(exist_ok=True)
    name = "ablation" if args.preset == "tiny" else f"ablation_{args.preset}"
    if args.geometry == "truth":
        name += "_truth_geometry"
    if args.effects == "on":
        name += "_effects_on"
    if args.light == "truth":
        name += "_truth_light"
    (RESULTS / f"{name}.json").write_text(
        json.dumps(
            {
                "benchmark": "ablation",
                "machine": machine(),
                "preset": args.preset,
                "geometry": args.geometry,
                "effects": args.effects,
                "light": args.light,
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
