"""The method's Table 1, our row beside it: a scene laid out as the NeRF-Synthetic release through
`evcap simulate --from-images` and both stages of `evcap reconstruct`, every held-out view scored.

    .venv/bin/python bench/paper_table.py SCENE_DIR [--preset fast] [--scale 1] [--seeds 0 1 2]
        [--background white|learnt] [--device cpu] [--backend B] [--iterations N]
        [--material-iterations N] [--lpips-weights ALEXNET.pth LINEAR_HEADS.pth]

Background. The release composites every image over white, as the field's protocol states (EventNeRF
a constant colour, Robust e-NeRF ``alpha_over_white_bg``): with ``--background white`` (the
default) both stages hold the backdrop at that known white (the setting stage1.background.known)
and the views are scored over it; ``--background learnt`` learns it from the events as
`evcap reconstruct` does for a real capture (where no view looked, it is free). The table says
which.

Protocol. The events come from the scene's continuous path, transforms_test.json's orbit (the
sensor at the images' size times --scale); every view of transforms_train.json is held out (other
directions, never seen by the events) and scored:
- render: stage II's physically based render, the whole image against the release's (over
  white) as the reconstruction renders it (the paper's "rendered image"): PSNR (the mean
  over the views of each view's), SSIM, LPIPS;
- normal MAE: stage II's shading normals against the normals derived from the release's depth,
  where the truth has a surface; depth error: a share of the distance there;
- beside them stage I's radiance (whole image), and both stages on the object's pixels alone
  with what the best constant color scores there;
- stage I's silhouette (alpha >= 0.5) against the object's pixels (IoU) and the backdrop seen
  through: the share of the pixels off the object where alpha is under 0.5;
- base color: the release has no albedo, so it cannot be scored.
Raw figures first; then after one gain per color channel (no offset: the events leave only
that undetermined), fitted once over all held-out views together. An affine fit per view is
given as a diagnostic only (`_affine_per_view`): it also forgives haze.

Before the reconstruction the truth itself is checked: the decoded depth of path views 10
apart must agree where they see the same point, and so must the normals derived from it.
Each seed's figures go to
results/paper_table/<scene>-<preset>-x<scale>-<background>-seed<N>.json (four of its views
beside their truth to .png: SHEET_COLUMNS) and are
read back, not rerun, by a later call with the same settings (--rerun to redo them, --rescore
to score their fields in results/fields/ again); the table, mean and spread over the seeds, to
results/paper_table-<scene>-<background>.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from _common import RESULTS, flag_settings, machine

from evcap.images import srgb
from evcap.recon.evaluate.lpips import Lpips
from evcap.recon.evaluate.metrics import (
    affine_per_view_psnr,
    background_clear,
    depth_rel_err,
    gain_fit,
    normal_mae_deg,
    psnr,
    silhouette_iou,
    ssim_map,
)
from evcap.recon.evaluate.views import render_views
from evcap.recon.export import load_checkpoint, load_material_checkpoint
from evcap.recon.options import Feedback, ReconstructOptions
from evcap.recon.reconstruct import pick_device, reconstruct
from evcap.recon.scene.optics import SensorOptics
from evcap.records import GroundTruth, ReconstructionFolder, TruthViews
from evcap.session import Session
from evcap.sim.from_images import rays, simulate_from_images

# The method's Table 1 (reference/method.md): per scene normal MAE, base colour PSNR and render
# PSNR; SSIM and LPIPS are given for the 7-scene mean only.
METHOD = {
    "chair": (27.47, 23.35, 24.77),
    "drums": (25.89, 18.40, 20.06),
    "ficus": (40.24, 27.36, 23.51),
    "hotdog": (19.16, 22.41, 19.77),
    "lego": (29.12, 20.79, 22.75),
    "materials": (34.67, 19.92, 19.54),
    "mic": (25.97, 23.92, 24.36),
    "7-scene mean": (28.93, 22.31, 22.11),
}
METHOD_MEAN_EXTRA = {"render_ssim": 0.902, "render_lpips": 0.105}
METHOD_RUN = "30,000 + 10,000 steps, 800 x 800, A5000 GPU"
NO_ALBEDO = "n/a (no albedo in the release)"
NO_LPIPS = "n/a (no weights)"
# --background: the backdrop's radiance both stages hold (linear RGB), None: learnt
BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "learnt": None}

# the table's columns: (heading, the figure's key in a row)
COLUMNS = (
    ("row", "row"),
    ("render PSNR", "render_psnr"),
    ("render SSIM", "render_ssim"),
    ("render LPIPS", "render_lpips"),
    ("normal MAE (deg)", "normal_mae_deg"),
    ("depth err", "depth_rel_err"),
    ("base color PSNR", "base_color_psnr"),
    ("object PSNR", "object_psnr"),
    ("constant color on the object", "object_psnr_constant"),
)


def truth_agreement(session: Path, apart: int = 10) -> dict:
    """How well the path's depth and normal truth agree between views ``apart`` views apart:
    each view's surface points projected into the other view, where that view sees them
    (its depth there within 2 %, not occluded): the median depth disagreement (share of
    the distance) and median angle between the two views' normals (degrees)."""
    with Session.open(session) as s:
        truth = GroundTruth.read(s, along_path=True)
    depth, normal, poses, K = truth.path.depth, truth.path.normal, truth.path.T_world_cam, truth.K
    h, w = depth.shape[1:]
    apart = max(1, min(apart, len(depth) // 3))  # a short path: views closer together
    ray = rays(K, h, w)
    dz, angles = [], []
    for i in range(0, len(depth) - apart, apart):
        j = i + apart
        ok = np.linalg.norm(normal[i], axis=-1) > 0.5
        p = ray[ok] * depth[i][ok][:, None]
        to_j = np.linalg.inv(poses[j]) @ poses[i]
        q = p @ to_j[:3, :3].T + to_j[:3, 3]
        n = normal[i][ok] @ to_j[:3, :3].T
        u = np.round(q[:, 0] / q[:, 2] * K[0, 0] + K[0, 2]).astype(int)
        v = np.round(q[:, 1] / q[:, 2] * K[1, 1] + K[1, 2]).astype(int)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        z_j = depth[j][v[inside], u[inside]]
        n_j = normal[j][v[inside], u[inside]]
        rel = (q[inside, 2] - z_j) / np.maximum(z_j, 1e-9)
        seen = (z_j > 0) & (np.abs(rel) < 0.02) & (np.linalg.norm(n_j, axis=-1) > 0.5)
        dz.append(np.abs(rel[seen]))
        cos = np.clip((n[inside][seen] * n_j[seen]).sum(-1), -1, 1)
        angles.append(np.degrees(np.arccos(cos)))
    dz, angles = np.concatenate(dz), np.concatenate(angles)
    return {
        "truth_depth_disagreement": float(np.median(dz)),
        "truth_normal_disagreement_deg": float(np.median(angles)),
        "truth_points_compared": int(len(dz)),
    }


def image_figures(
    pred: np.ndarray, truth: np.ndarray, prefix: str, lpips: Lpips | None
) -> dict[str, float | str]:
    """Whole-image figures of linear renders [N, H, W, 3]: PSNR (the mean of each view's), SSIM
    and LPIPS raw, then after one gain per channel fitted over all views (``_gain``); the PSNR
    after an affine fit per view (``_affine_per_view``, a diagnostic)."""
    out: dict[str, float | str] = {}
    seen = srgb(truth)
    gain = gain_fit(pred, truth)
    for name, image in (("", pred), ("_gain", pred * gain)):
        shown = srgb(image)
        views = zip(shown, seen, strict=True)
        out[f"{prefix}_psnr{name}"] = float(np.mean([psnr(a, b) for a, b in views]))
        out[f"{prefix}_ssim{name}"] = float(ssim_map(shown, seen).mean())
        out[f"{prefix}_lpips{name}"] = NO_LPIPS if lpips is None else lpips(shown, seen)
    everywhere = np.ones(truth.shape[:-1], bool)
    out[f"{prefix}_psnr_affine_per_view"] = affine_per_view_psnr(pred, truth, everywhere)
    out[f"{prefix}_gain_rgb"] = [round(float(g), 4) for g in gain]
    return out


def object_figures(
    pred: np.ndarray, truth: np.ndarray, mask: np.ndarray, prefix: str
) -> dict[str, float]:
    """A render on the object's pixels of all views together, raw and after the gain fitted
    there, beside the best constant color there."""
    seen = srgb(truth)[mask]
    gain = gain_fit(pred, truth, mask)
    return {
        f"{prefix}_psnr": psnr(srgb(pred)[mask], seen),
        f"{prefix}_psnr_gain": psnr(srgb(pred[mask] * gain), seen),
        "object_psnr_constant": psnr(np.broadcast_to(seen.mean(0), seen.shape), seen),
    }


def score(
    out: Path,
    session: Path,
    device: str,
    backend: str,
    lpips: Lpips | None,
    picture: Path | None = None,
) -> dict[str, float | str]:
    """Both stages' checkpoints in OUT rendered at every held-out view and scored; four of the
    views beside their truth written to ``picture`` (PNG)."""
    folder = ReconstructionFolder(out)
    if folder.poses.exists():
        raise SystemExit(f"{out}: stage I refined the poses; the table scores views at the truth's")
    with Session.open(session) as s:
        truth: TruthViews = GroundTruth.read(s).held_out_views()
        optics = SensorOptics.from_session(s)
    mask = truth.object_mask()
    figures: dict[str, float | str] = {"views": len(truth)}
    radiance, _ = load_checkpoint(folder.checkpoint("radiance"), device, backend)
    stage_1 = render_views(radiance, truth.T_world_cam, optics, device)
    figures.update(image_figures(stage_1["radiance"], truth.radiance, "radiance", lpips))
    figures.update(object_figures(stage_1["radiance"], truth.radiance, mask, "object"))
    figures["radiance_normal_mae_deg"] = normal_mae_deg(stage_1["normal"], truth.normal)
    figures["depth_rel_err"] = depth_rel_err(stage_1["depth"], truth.depth)
    figures["background_clear"] = background_clear(stage_1["alpha"], mask)
    figures["silhouette_iou"] = silhouette_iou(stage_1["alpha"], mask)
    shown = np.unique(np.linspace(0, len(truth) - 1, min(4, len(truth))).round().astype(int))
    stage_1_shown = stage_1["radiance"][shown] * figures["radiance_gain_rgb"]
    del stage_1, radiance
    material = load_material_checkpoint(folder.checkpoint("material"), device, backend)
    stage_2 = render_views(material, truth.T_world_cam, optics, device)
    figures.update(image_figures(stage_2["radiance"], truth.radiance, "render", lpips))
    figures.update(object_figures(stage_2["radiance"], truth.radiance, mask, "render_object"))
    figures["normal_mae_deg"] = normal_mae_deg(stage_2["normal"], truth.normal)
    figures["base_color_psnr"] = NO_ALBEDO
    if picture is not None:
        columns = [
            srgb(truth.radiance[shown]),
            srgb(stage_1_shown),
            srgb(stage_2["radiance"][shown] * figures["render_gain_rgb"]),
            stage_2["normal"][shown] * 0.5 + 0.5,
            truth.normal[shown] * 0.5 + 0.5,
        ]
        write_sheet(columns, picture)
    return figures


SHEET_COLUMNS = "truth | stage I radiance | stage II render | stage II normals | true normals"


def write_sheet(columns: list[np.ndarray], path: Path) -> None:
    """Images [V, H, W, 3] in [0, 1], one list entry a column, one view a row, as a PNG."""
    import cv2

    rows = [np.concatenate([c[v] for c in columns], 1) for v in range(len(columns[0]))]
    sheet = np.clip(np.concatenate(rows, 0), 0, 1)[..., ::-1]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), (sheet * 255 + 0.5).astype(np.uint8))


def simulated(scene: Path, scale: float) -> Path:
    """The scene's events at ``scale`` with every view of transforms_train.json held out,
    simulated once into results/sessions/ (again when a kept one holds other views)."""
    views = len(json.loads((scene / "transforms_train.json").read_text())["frames"])
    session = RESULTS / "sessions" / f"{scene_name(scene)}-x{scale:g}.h5"
    if session.exists():
        with Session.open(session) as s:
            if len(GroundTruth.read(s).held_out_views()) != views:
                print(f"{session}: not every held-out view; simulated again", flush=True)
                session.unlink()
    if not session.exists():
        session.parent.mkdir(parents=True, exist_ok=True)
        print(f"simulating {scene.name} at x{scale:g} (once) ...", flush=True)
        started = time.perf_counter()
        n = simulate_from_images(
            scene / "transforms_test.json",
            session,
            held_out=scene / "transforms_train.json",
            scale=scale,
            test_views=views,
        )
        print(f"{n:,} events, {time.perf_counter() - started:.0f} s", flush=True)
    return session


def scene_name(scene: Path) -> str:
    return scene.resolve().name.removeprefix("nerf-synthetic-")


def run_seed(session: Path, args: argparse.Namespace, seed: int, lpips: Lpips | None) -> dict:
    """One seed's run (both stages) and its figures; read back when it was run already."""
    settings = {
        "preset": args.preset,
        "scale": args.scale,
        "iterations": args.iterations,
        "material_iterations": args.material_iterations,
        "device": args.device,
        "backend": args.backend,
        "lpips": lpips is not None,
        "background": args.background,
    }
    name = f"{scene_name(args.scene)}-{args.preset}-x{args.scale:g}-{args.background}-seed{seed}"
    path = RESULTS / "paper_table" / f"{name}.json"
    out = RESULTS / "fields" / name
    if path.exists() and not args.rerun:
        done = json.loads(path.read_text())
        if done["settings"] == settings and args.rescore:
            print(f"seed {seed}: its fields in {out} scored again", flush=True)
            started = time.perf_counter()
            done["figures"] = score(
                out, session, args.device, done["backend"], lpips, path.with_suffix(".png")
            )
            done["scoring_seconds"] = time.perf_counter() - started
            path.write_text(json.dumps(done, indent=2))
            return done
        if done["settings"] == settings:
            print(f"seed {seed}: read from {path}", flush=True)
            return done
    overrides: dict[str, object] = {"stage1.background.known": BACKGROUNDS[args.background]}
    overrides |= flag_settings(
        iterations=args.iterations, material_iterations=args.material_iterations
    )
    options = ReconstructOptions(
        preset=args.preset,
        device=args.device,
        backend=args.backend,
        seed=seed,
        settings=overrides,
        resume="start over",
    )
    result = reconstruct(session, out, options, Feedback(progress=Progress(f"seed {seed}")))
    started = time.perf_counter()
    figures = score(out, session, args.device, result.backend, lpips, path.with_suffix(".png"))
    run = {
        "seed": seed,
        "settings": settings,
        "backend": result.backend,
        "iterations": result.iterations,
        "material_iterations": result.material_iterations,
        "gaussians": result.gaussians,
        "stage_1_seconds": result.seconds,
        "stage_2_seconds": result.material_seconds,
        "scoring_seconds": time.perf_counter() - started,
        "figures": figures,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(run, indent=2))
    print(f"seed {seed}: -> {path}", flush=True)
    return run


class Progress:
    """Prints a run's step every 500 and the time since it started."""

    def __init__(self, label: str) -> None:
        self.label, self.started = label, time.perf_counter()

    def __call__(self, step: int, total: int, text: str) -> None:
        if step % 500 == 0 or step == total:
            elapsed = time.perf_counter() - self.started
            print(f"  {self.label} {elapsed:6.0f} s: step {step} of {total}: {text}", flush=True)


def summary(runs: list[dict]) -> dict[str, dict]:
    """Each figure over the seeds: {"mean", "std", "values"} (text figures as they are)."""
    out = {}
    for key, first in runs[0]["figures"].items():
        values = [r["figures"][key] for r in runs]
        if isinstance(first, str | list):
            out[key] = {"mean": first, "std": None, "values": values}
        else:
            out[key] = {
                "mean": float(np.mean(values)),
                "std": float(np.std(values, ddof=1)) if len(values) > 1 else None,
                "values": values,
            }
    return out


def table(name: str, label: str, figures: dict[str, dict]) -> str:
    """Our rows (raw, gain-corrected; stage I beside them) and the method's, as Markdown."""

    def cell(key: str) -> str:
        if key not in figures:
            return ""
        f = figures[key]
        if isinstance(f["mean"], str):
            return f["mean"]
        text = f"{f['mean']:.3g}" if abs(f["mean"]) < 100 else f"{f['mean']:.0f}"
        return text if f["std"] is None else f"{text} ± {f['std']:.2g}"

    def row(title: str, keys: dict[str, str]) -> str:
        return "| " + " | ".join([title, *(cell(keys.get(k, "")) for _, k in COLUMNS[1:])]) + " |"

    same = {k: k for _, k in COLUMNS}
    gain = {k: f"{k}_gain" for k in ("render_psnr", "render_ssim", "render_lpips")}
    stage_1 = {f"render_{m}": f"radiance_{m}" for m in ("psnr", "ssim", "lpips")}
    stage_1["normal_mae_deg"] = "radiance_normal_mae_deg"
    stage_1["object_psnr"] = "object_psnr"
    stage_1["object_psnr_constant"] = "object_psnr_constant"
    stage_1_gain = {k: f"{v}_gain" for k, v in stage_1.items() if k.startswith("render_")}
    stage_1_gain["object_psnr"] = "object_psnr_gain"
    stage_1_gain["object_psnr_constant"] = "object_psnr_constant"
    lines = [
        "| " + " | ".join(h for h, _ in COLUMNS) + " |",
        "|" + "---|" * len(COLUMNS),
        row(f"evcap, {name}, {label}: raw", {**same, "object_psnr": "render_object_psnr"}),
        row(
            "  after one gain per channel (all views)",
            {
                **gain,
                "normal_mae_deg": "normal_mae_deg",
                "depth_rel_err": "depth_rel_err",
                "object_psnr": "render_object_psnr_gain",
                "object_psnr_constant": "object_psnr_constant",
            },
        ),
        row("  stage I radiance, raw", {**stage_1, "depth_rel_err": "depth_rel_err"}),
        row("  stage I radiance, gain", stage_1_gain),
    ]
    for scene in (name, "7-scene mean"):
        if scene in METHOD:
            normal, base, render = METHOD[scene]
            extra = METHOD_MEAN_EXTRA if scene == "7-scene mean" else {}
            values = {"render_psnr": render, "normal_mae_deg": normal, "base_color_psnr": base}
            values.update(extra)
            cells = [f"{values[k]:.3g}" if k in values else "" for _, k in COLUMNS[1:]]
            lines.append("| " + " | ".join([f"method, {scene} ({METHOD_RUN})", *cells]) + " |")
    if "silhouette_iou" in figures:
        lines.append("")
        lines.append(
            f"Stage I's silhouette (alpha >= 0.5) against the truth's: IoU "
            f"{cell('silhouette_iou')}; the backdrop seen through (alpha < 0.5 off the object): "
            f"{cell('background_clear')} of its pixels."
        )
    diagnostic = figures.get("render_psnr_affine_per_view")
    if diagnostic is not None:
        lines.append("")
        lines.append(
            f"Diagnostic only: render PSNR after an affine fit per view "
            f"{diagnostic['mean']:.3g} dB (stage I: "
            f"{figures['radiance_psnr_affine_per_view']['mean']:.3g} dB)."
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path, help="a folder laid out as the NeRF-Synthetic release")
    ap.add_argument("--scale", type=float, default=1.0, help="the sensor's size / the images'")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument(
        "--background",
        choices=sorted(BACKGROUNDS),
        default="white",
        help="the backdrop: the release's known white, or learnt from the events",
    )
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--backend")
    ap.add_argument("--iterations", type=int, help="stage I's steps (default: the preset's)")
    ap.add_argument("--material-iterations", type=int, help="stage II's (the preset's)")
    ap.add_argument(
        "--lpips-weights",
        type=Path,
        nargs="+",
        help="the torchvision AlexNet state dict and LPIPS's linear heads (one file or two)",
    )
    ap.add_argument("--rerun", action="store_true", help="redo seeds whose figures are kept")
    ap.add_argument(
        "--rescore",
        action="store_true",
        help="score the kept seeds' fields again, not trained again (the scoring or the "
        "held-out truth changed; the events must be the same)",
    )
    args = ap.parse_args(argv)
    for needed in ("transforms_test.json", "transforms_train.json"):
        if not (args.scene / needed).is_file():
            raise SystemExit(f"{args.scene}: no {needed}; give a folder laid out as NeRF-Synthetic")
    args.device = pick_device(args.device)
    name = scene_name(args.scene)
    lpips = Lpips(*args.lpips_weights, device=args.device) if args.lpips_weights else None
    session = simulated(args.scene, args.scale)
    check = truth_agreement(session)
    print(json.dumps(check), flush=True)
    runs = [run_seed(session, args, seed, lpips) for seed in args.seeds]
    with Session.open(session) as s:
        h, w = s.sensor.height, s.sensor.width
    first = runs[0]
    minutes = [(r["stage_1_seconds"] + r["stage_2_seconds"]) / 60 for r in runs]
    label = (
        f"{args.preset}, background {args.background}, {w} x {h}, "
        f"{first['iterations']:,} + {first['material_iterations']:,} steps, "
        f"seeds {' '.join(map(str, args.seeds))}, "
        f"{' / '.join(f'{m:.0f}' for m in minutes)} min a run on {describe_device(args.device)}"
    )
    figures = summary(runs)
    text = table(name, label, figures)
    print(text)
    doc = {
        "benchmark": "paper_table",
        "scene": name,
        "label": label,
        "machine": machine(),
        "truth": check,
        "figures": figures,
        "runs": runs,
        "method": {"run": METHOD_RUN, "scenes": METHOD, "mean_extra": METHOD_MEAN_EXTRA},
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"paper_table-{name}-{args.background}.md").write_text(text)
    path = RESULTS / f"paper_table-{name}-{args.background}.json"
    path.write_text(json.dumps(doc, indent=2))
    print(f"-> {path}, .md")
    return doc


def describe_device(device: str) -> str:
    import os

    if device == "cuda":
        return torch.cuda.get_device_name()
    return f"{os.cpu_count()} CPU cores"


if __name__ == "__main__":
    main()
