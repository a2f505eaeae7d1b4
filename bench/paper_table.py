"""The method's own benchmark: a NeRF-Synthetic scene (mic) through `evcap simulate
--from-images` and stage I of `evcap reconstruct`, beside the method's Table 1.

    .venv/bin/python bench/paper_table.py [--data ../shared/data/nerf-synthetic-mic]
        [--scale 0.4] [--preset fast] [--seed 5] [--device cpu]

The camera moves through transforms_test.json's views (the 360-degree orbit); the held-out
views are 8 of transforms_train.json's (other directions, never used for events). Before the
reconstruction, the truth itself is checked: the decoded depth of path views 10 apart must
agree where they see the same point (the encoding, see evcap.sim.from_images.decode_depth),
and so must the normals derived from it. Any scene laid out as the release is (--data
../nerf_synthetic/lego) runs unchanged. Writes results/paper_table-<scene>.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from _common import RESULTS, machine, markdown_table

from evcap.recon.reconstruct import reconstruct
from evcap.records import GroundTruth
from evcap.session import Session
from evcap.sim.from_images import rays, simulate_from_images

# The method's Table 1 (reference/method.md): normal MAE, base colour PSNR, render PSNR.
METHOD = {
    scene: dict(zip(("normal_mae_deg", "base_color_psnr", "render_psnr"), values, strict=True))
    for scene, values in {
        "chair": (27.47, 23.35, 24.77),
        "drums": (25.89, 18.40, 20.06),
        "ficus": (40.24, 27.36, 23.51),
        "hotdog": (19.16, 22.41, 19.77),
        "lego": (29.12, 20.79, 22.75),
        "materials": (34.67, 19.92, 19.54),
        "mic": (25.97, 23.92, 24.36),
        "7-scene mean": (28.93, 22.31, 22.11),
    }.items()
}
METHOD_RUN = {"resolution": "800 x 800", "iterations": "30,000 + 10,000", "device": "A5000 GPU"}
COLUMNS = (
    "row",
    "preset",
    "resolution",
    "iterations",
    "seconds",
    "render_psnr",
    "render_psnr_cc",
    "object_psnr_cc",
    "object_psnr_constant",
    "normal_mae_deg",
    "depth_rel_err",
    "base_color_psnr",
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    here = Path(__file__).resolve().parent
    ap.add_argument("--data", type=Path, default=here.parents[1] / "shared/data/nerf-synthetic-mic")
    ap.add_argument("--scale", type=float, default=0.4)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    name = args.data.name.removeprefix("nerf-synthetic-")
    session = RESULTS / "sessions" / f"{name}-x{args.scale:g}.h5"
    if not session.exists():
        session.parent.mkdir(parents=True, exist_ok=True)
        print(f"simulating {name} at x{args.scale:g} (once) ...", flush=True)
        t = time.time()
        n = simulate_from_images(
            args.data / "transforms_test.json",
            session,
            held_out=args.data / "transforms_train.json",
            scale=args.scale,
        )
        print(f"{n:,} events, {time.time() - t:.0f} s", flush=True)
    check = truth_agreement(session)
    print(json.dumps(check), flush=True)
    out = RESULTS / "fields" / f"{name}-{args.preset}"
    t = time.time()
    figures = reconstruct(
        session,
        out,
        preset=args.preset,
        seed=args.seed,
        device=args.device,
        stage="radiance",
        overwrite=True,
    )
    seconds = time.time() - t
    with Session.open(session) as s:
        h, w = s.sensor.height, s.sensor.width
    ours = {
        "row": f"evcap, {name}",
        "preset": args.preset,
        "resolution": f"{w} x {h}",
        "iterations": figures.get("iterations"),
        "seconds": round(seconds),
        **{k: figures.get(k) for k in COLUMNS if k in figures},
    }
    rows = [ours] + [
        {"row": f"method, {scene}", "preset": "paper", **METHOD_RUN, **values}
        for scene, values in METHOD.items()
        if scene in (name, "7-scene mean")
    ]
    table = markdown_table(rows, COLUMNS)
    print(table)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"paper_table-{name}.md").write_text(table)
    doc = {"benchmark": "paper_table", "machine": machine(), "truth": check, "rows": rows}
    path = RESULTS / f"paper_table-{name}.json"
    path.write_text(json.dumps(doc, indent=2))
    print(f"-> {path}")


if __name__ == "__main__":
    main()
