"""The method's ablations of stage II on the simulator's example scenes: the full model, then
each of its terms and effects left out (brightness anchor, edge-guided TV, radiance
distillation, visibility, indirect light). Stage I is fitted once per scene and shared, so the
rows differ by stage II alone. Base color is also measured inside the shadows and the color
bleeding that the simulator's ground truth marks. Writes a table (JSON and Markdown) beside
the method's published means.

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
        [--light learnt|truth]
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
from _common import RESULTS, machine, scene_file, scene_label, session_of

import evcap.recon.material as material
import evcap.recon.radiance as radiance
from evcap.recon.gaussians import START_VALUE, Background, Gaussians
from evcap.recon.reconstruct import reconstruct
from evcap.recon.sh import C0
from evcap.sim.lighting import Environment
from evcap.sim.meshes import build_mesh
from evcap.sim.scene import load_scene

# name -> reconstruct() settings of stage II
VARIANTS = {
    "full": {},
    "no anchor": {"ablate": ("anchor",)},
    "no edge TV": {"ablate": ("tv",)},
    "no distillation": {"ablate": ("distill",)},
    # indirect light stands for what the occluders hide: without visibility it goes too
    "no visibility": {"visibility": "off", "indirect": "off"},
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
    "base_color_psnr_cc_baseline",
    "relit_object_psnr_cc",
    "roughness_mae",
    "pbr_render_psnr_cc",
    "material_seconds",
)


# stage I on the truth's surfaces: every geometry parameter kept, no densification
TRUTH_GEOMETRY = {"densify_until": 0.0, "background_first": 0.0}
TRUTH_GAUSSIANS = 20_000
TRUTH_OPACITY = 0.95


def surface_samples(scene: str, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points spread over the scene's surfaces by area, with the faces' normals."""
    mesh, _, _ = build_mesh(load_scene(scene_file(scene)))
    a, b, c = (mesh.vertices[mesh.faces[:, i]] for i in range(3))
    cross = np.cross(b - a, c - a)
    area = np.linalg.norm(cross, axis=1) / 2
    rng = np.random.default_rng(seed)
    face = rng.choice(len(area), count, p=area / area.sum())
    u, v = rng.random((2, count))
    flip = u + v > 1  # fold the square's far half back into the triangle
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    points = a[face] + u[:, None] * (b - a)[face] + v[:, None] * (c - a)[face]
    normals = cross[face] / np.maximum(2 * area[face], 1e-12)[:, None]
    return points, normals


def truth_gaussians(scene: str, sh_degree: int) -> Gaussians:
    """Flat opaque discs on the truth's surfaces, facing along the surface normal, each as wide
    as the mean spacing of the samples, mid-gray."""
    points, normals = surface_samples(scene, TRUTH_GAUSSIANS)
    mesh, _, _ = build_mesh(load_scene(scene_file(scene)))
    a, b, c = (mesh.vertices[mesh.faces[:, i]] for i in range(3))
    spacing = np.sqrt(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum() / 2 / len(points))
    n = np.where(normals[:, 2:] < 0, -normals, normals)  # a disc is two-sided
    # the rotation taking +z to n: (w, x, y, z) = normalise(1 + n.z, z x n)
    quats = np.stack([1 + n[:, 2], -n[:, 1], n[:, 0], np.zeros(len(n))], 1)
    count = len(points)
    log_scales = np.log([0.8 * spacing, 0.8 * spacing, 0.02 * spacing])
    logit = np.log(TRUTH_OPACITY / (1 - TRUTH_OPACITY))
    return Gaussians(
        torch.as_tensor(points, dtype=torch.float32),
        torch.as_tensor(np.tile(log_scales, (count, 1)), dtype=torch.float32),
        torch.as_tensor(quats / np.linalg.norm(quats, axis=1, keepdims=True), dtype=torch.float32),
        torch.full((count,), float(logit)),
        torch.full((count, 1, 3), START_VALUE / C0),
        torch.zeros(count, (sh_degree + 1) ** 2 - 1, 3),
    )


@contextmanager
def starting_on_truth(scene: str) -> Iterator[None]:
    """Stage I's start replaced by the truth's surfaces, whose geometry does not learn."""
    original = radiance.new_field

    def new_field(data, config, seed, device, backend):
        g = truth_gaussians(scene, config.sh_degree)
        for name in ("means", "log_scales", "quats", "opacity_logits"):
            getattr(g, name).requires_grad_(False)
        return radiance.RadianceField(g, Background(config.background_size), backend).to(device)

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
    args = parser.parse_args(argv)
    rows, stage_one = [], {}
    forced = {"visibility": "on", "indirect": "on"} if args.effects == "on" else {}
    with tempfile.TemporaryDirectory() as scratch:
        tmp = args.work or scratch
        for scene in args.scenes:
            session = session_of(scene)
            label = scene_label(scene)
            base = Path(tmp) / label
            started = time.perf_counter()
            truth = args.geometry == "truth"
            with starting_on_truth(scene) if truth else nullcontext():
                first = reconstruct(
                    session,
                    base,
                    preset=args.preset,
                    device=args.device,
                    stage="radiance",
                    iterations=args.iterations,
                    radiance_settings=TRUTH_GEOMETRY if truth else None,
                )
            stage_one[label] = {
                "object_psnr_cc": first.figures.object_psnr_cc,
                "object_psnr_constant": first.figures.object_psnr_constant,
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
                out = Path(tmp) / f"{label}-{name.replace(' ', '-')}"
                shutil.copytree(base, out)
                with truth_light(scene) if args.light == "truth" else nullcontext():
                    result = reconstruct(
                        session,
                        out,
                        preset=args.preset,
                        device=args.device,
                        stage="material",
                        material_iterations=args.material_iterations,
                        overwrite=True,
                        **{**forced, **settings},
                    )
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
