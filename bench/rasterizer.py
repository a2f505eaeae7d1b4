"""Rasterizer speed: forward and forward+backward time per view for each backend, on 1 and 2
threads (and gsplat on a CUDA GPU when there is one), side by side in one run.

The Gaussians are what training renders: stage I of `evcap reconstruct --preset fast` on the
single-object scene (14.5k Gaussians; fitted once, with the compiled backend, into
bench/results/fields/), seen from a held-out view, at 173 x 130 (the sensor's pinhole at half
scale, where fast trained before this backend) and at the sensor's 346 x 260; 5k of them drawn
at random for the 5k rows. The method's scale (100k Gaussians at 800 x 800) has no such fit
here: a synthetic field stands for it, half flattened on a sphere's surface, half through the
volume around it, about 1.5 render pixels across, opacities 0.05 to 0.95. The backward pass
takes a fixed random weighting of every output (color, depth, alpha, normals). The runs take
turns, round after round, and each figure is the fastest of its rounds. ``--baseline REF``
times commit REF's compiled rasterizer too, in a process of its own, taking its turn in every
round (bench/_raster_timing.py), on the same Gaussians and views.

    .venv/bin/python bench/rasterizer.py [--quick] [--repeats N] [--scene S] [--preset P]
        [--iterations N] [--scale X] [--baseline REF]
"""

from __future__ import annotations

import argparse
import functools
import math
import statistics
from pathlib import Path

import numpy as np
import torch
from _common import RESULTS, export_commit, flag_settings, report, scene_label, session_of
from _raster_timing import BaselineRasterizer, time_once

from evcap.recon.export import load_checkpoint
from evcap.recon.scene.optics import SensorOptics
from evcap.records import GroundTruth, ReconstructionFolder
from evcap.session import Session

ROOT = Path(__file__).resolve().parent.parent
BASELINE = "cpu at the baseline"  # the backend column of the baseline's rows

# (field, width, height, Gaussians, channels): the fast preset's size, the sensor's, the method's
CONFIGS = [
    ("trained", 173, 130, 5_000, 3),
    ("trained", 173, 130, 15_000, 3),
    ("trained", 173, 130, 15_000, 10),
    ("trained", 346, 260, 15_000, 3),
    ("synthetic", 800, 800, 100_000, 3),
]


def trained(
    n: int,
    width: int,
    height: int,
    channels: int,
    seed: int = 0,
    scene: str = "single_object",
    preset: str = "fast",
    iterations: int | None = None,
):
    """The stage-I field of ``scene`` at ``preset`` (fitted once), from its first held-out view
    through the sensor's pinhole scaled to width x height; n of its Gaussians at most."""
    from evcap.recon.options import ReconstructOptions
    from evcap.recon.reconstruct import reconstruct

    session = session_of(scene)
    steps = "" if iterations is None else f"_{iterations}"
    out = RESULTS / "fields" / f"{scene_label(scene)}_{preset}{steps}"
    checkpoint = ReconstructionFolder(out).checkpoint("radiance")
    if not checkpoint.exists():
        print(f"fitting stage I of {scene} at {preset} (once) ...", flush=True)
        options = ReconstructOptions(
            preset=preset,
            stage="radiance",
            settings=flag_settings("radiance", iterations=iterations),
            resume="go on or start over",
        )
        reconstruct(session, out, options)
    field, _ = load_checkpoint(Path(checkpoint))
    with Session.open(session) as s:
        poses = GroundTruth.read(s).held_out_views().T_world_cam
        optics = SensorOptics.from_session(s)
    g = field.gaussians
    keep = torch.randperm(len(g), generator=torch.Generator().manual_seed(seed))[:n]
    keep = keep.sort().values
    K = torch.tensor(optics.K * width / optics.width, dtype=torch.float32)
    K[2, 2] = 1
    view = torch.as_tensor(np.linalg.inv(poses[0]), dtype=torch.float32)
    colors = torch.rand(len(keep), channels, generator=torch.Generator().manual_seed(seed))
    params = [
        g.means.detach()[keep],
        g.quats.detach()[keep],
        g.log_scales.detach()[keep],
        g.opacities.detach()[keep],
        colors,
    ]
    return params, (view, K, width, height)


def synthetic(n: int, width: int, height: int, channels: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    half = n // 2
    on_surface = torch.nn.functional.normalize(torch.randn(half, 3, generator=g), dim=1) * 0.5
    around = (torch.rand(n - half, 3, generator=g) - 0.5) * torch.tensor([2.4, 1.8, 1.6])
    means = torch.cat([on_surface, around])
    quats = torch.randn(n, 4, generator=g)
    f = 0.72 * width  # the DAVIS346's lens: about 70 degrees across
    distance = 1.4
    pixel = distance / f
    log_scales = math.log(1.5 * pixel) + 0.5 * torch.randn(n, 3, generator=g)
    log_scales[:half, 2] -= 2.0  # the surface's Gaussians are flat
    opacities = 0.05 + 0.9 * torch.rand(n, generator=g)
    features = torch.rand(n, channels, generator=g)
    view = torch.eye(4)
    view[2, 3] = distance
    K = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
    params = [means, quats, log_scales, opacities, features]
    return params, (view, K, width, height)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="the 173 x 130 rows only")
    parser.add_argument("--repeats", type=int, default=10, help="timed rounds per figure")
    parser.add_argument("--scene", default="single_object", help="the trained field's scene")
    parser.add_argument("--preset", default="fast", help="the trained field's preset")
    parser.add_argument("--iterations", type=int, help="the trained field's steps (preset's)")
    parser.add_argument("--scale", type=float, default=1.0, help="every row's image size times")
    parser.add_argument("--baseline", help="a git commit whose rasterizer is timed beside")
    parser.add_argument("--baseline-code", type=Path, help=argparse.SUPPRESS)  # a checkout
    args = parser.parse_args(argv)
    exported = export_commit(args.baseline, ROOT) if args.baseline else None
    code = Path(exported.name) if exported else args.baseline_code
    try:
        rows = _rows(args, code)
    finally:
        if exported is not None:
            exported.cleanup()
    report("rasterizer", {**_figures(rows), "baseline": args.baseline, "rows": rows})


def _rows(args: argparse.Namespace, code: Path | None) -> list[dict]:
    """Every configuration's row per run (backend, threads; the baseline's code)."""
    fields = {
        "trained": functools.partial(
            trained, scene=args.scene, preset=args.preset, iterations=args.iterations
        ),
        "synthetic": synthetic,
    }
    configs = [
        (field, round(width * args.scale), round(height * args.scale), n, channels)
        for field, width, height, n, channels in CONFIGS
        if not args.quick or width == 173
    ]
    threads_before = torch.get_num_threads()
    gsplat = False
    if torch.cuda.is_available():
        from evcap.recon.raster import _gsplat as _raster_gsplat

        gsplat = _raster_gsplat.available()
    rows = []
    baseline = BaselineRasterizer(code) if code is not None else None
    for field, width, height, n, channels in configs:
        params, view = fields[field](n, width, height, channels)
        n = len(params[0])
        # the torch backend takes seconds a view at the largest size: fewer repeats there
        repeats = args.repeats if width * height * n < 1e10 else 3
        runs = [("cpu", "cpu", t) for t in (1, 2)] + [("torch", "cpu", t) for t in (1, 2)]
        runs += [("gsplat", "cuda", None)] if gsplat else []
        runs += [(BASELINE, "cpu", t) for t in (1, 2)] if baseline else []
        times: dict = {run: [] for run in runs}
        g = torch.Generator().manual_seed(1)
        weights = torch.rand(height, width, channels + 5, generator=g)
        if baseline:
            baseline.load(params, view, weights)
        # round by round, so that a slow moment of the machine falls on every run alike;
        # the first round compiles (or loads the cached build) and is not counted
        for round_ in range(repeats + 1):
            for run in runs:
                backend, device, threads = run
                if backend == BASELINE:
                    fwd, total, alpha = baseline.time_once(threads)
                else:
                    if threads:
                        torch.set_num_threads(threads)
                    fwd, total, alpha = time_once(backend, params, view, weights, device)
                if round_:
                    times[run].append((fwd, total))
        for (backend, device, threads), measured in times.items():
            # the fastest of the rounds: the machine's noise only ever adds time
            fwd, total = (min(m[i] for m in measured) for i in (0, 1))
            rows.append(
                {
                    "field": field,
                    "width": width,
                    "height": height,
                    "gaussians": n,
                    "channels": channels,
                    "backend": backend,
                    "threads": threads,
                    "forward_ms": 1000 * fwd,
                    "forward_backward_ms": 1000 * total,
                    "median_forward_backward_ms": 1000 * statistics.median(m[1] for m in measured),
                    "mean_alpha": alpha,
                }
            )
            print(
                f"{field:>9} {width} x {height}, {n:>7,} Gaussians, {channels:>2} channels, "
                f"{backend:>6} on {threads or device}: forward {1000 * fwd:8.1f} ms, "
                f"forward+backward {1000 * total:8.1f} ms",
                flush=True,
            )
    torch.set_num_threads(threads_before)
    if baseline:
        baseline.close()
    return rows


def _figures(rows: list[dict]) -> dict:
    """The compiled backend on 2 threads against the torch one, itself on 1 thread, and the
    baseline's compiled backend (where it ran), per configuration."""

    def timing(config, backend, threads, key):
        return next(
            r[key]
            for r in rows
            if (r["field"], r["width"], r["height"], r["gaussians"], r["channels"]) == config
            and r["backend"] == backend
            and r["threads"] == threads
        )

    baseline = any(r["backend"] == BASELINE for r in rows)
    figures: dict = {}
    for row in rows:
        if row["backend"] != "cpu" or row["threads"] != 2:
            continue
        config = tuple(row[k] for k in ("field", "width", "height", "gaussians", "channels"))
        field, width, height, n, channels = config
        name = f"{field}_{width}x{height}_{round(n / 1000)}k_{channels}ch"
        for key, label in (("forward_backward_ms", ""), ("median_forward_backward_ms", "_median")):
            torch_ms, cpu_ms = timing(config, "torch", 2, key), timing(config, "cpu", 2, key)
            figures[f"{name}_cpu_vs_torch_2_threads{label}"] = torch_ms / cpu_ms
            figures[f"{name}_cpu_2_vs_1_thread{label}"] = timing(config, "cpu", 1, key) / cpu_ms
            if baseline:  # how many times faster than the baseline's, each on 2 threads
                before = timing(config, BASELINE, 2, key)
                figures[f"{name}_cpu_vs_baseline_2_threads{label}"] = before / cpu_ms
        if baseline:
            before = timing(config, BASELINE, 2, "forward_ms")
            figures[f"{name}_cpu_vs_baseline_2_threads_forward"] = before / row["forward_ms"]
    return figures


if __name__ == "__main__":
    main()
