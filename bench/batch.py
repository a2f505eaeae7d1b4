"""`evcap batch`'s throughput on this machine: the same manifest of four tiny recordings
(reconstruction at `tiny` and the report) on a Ray started here with 1 and then 2 workers
(cores), each step a one-core task; and, for scale, in this process without Ray. The time is
the whole call as a user waits for it (Ray's start included).

    .venv/bin/python bench/batch.py [--recordings 4] [--preset tiny]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from _common import report

from evcap.batch.manifest import read_manifest
from evcap.batch.run import run_batch
from evcap.recon.options import ReconstructOptions
from evcap.sim.scene import load_scene
from evcap.sim.simulate import simulate

SCENE = """
[scene]
name = "batch-bench"
seed = {seed}
[sensor]
color_filter = "RGBG"
[camera]
width = 96
height = 72
fx = 90.0
[trajectory]
kind = "orbit"
radius = 2.2
height = 0.8
height_swing = 0.4
swings = 1
degrees = 60.0
duration_s = 0.5
[lighting]
environment = "sky"
[materials.paint]
procedural = {{ kind = "checker", scale = 6, colors = [[0.8, 0.25, 0.1], [0.9, 0.85, 0.6]] }}
roughness = 0.4
[[objects]]
type = "sphere"
radius = 0.6
material = "paint"
[gt]
fps = 10
test_views = 2
"""
STEPS = ("reconstruct", "report")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--recordings", type=int, default=4)
    parser.add_argument("--preset", default="tiny")
    parser.add_argument(
        "--ray-workers", type=int, nargs="*", default=[1, 2], help="Ray's runs (none: in process)"
    )
    parser.add_argument("--scene", type=Path, help="the recordings' scene file (default: its own)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        (root / "recordings").mkdir()
        for i in range(args.recordings):
            scene = root / f"scene{i}.toml"
            scene.write_text(args.scene.read_text() if args.scene else SCENE.format(seed=i))
            simulate(load_scene(scene), root / "recordings" / f"object{i}.h5")
        (root / "manifest.toml").write_text('[[group]]\nrecordings = ["recordings/*.h5"]\n')
        manifest = read_manifest(root / "manifest.toml")
        figures: dict = {"recordings": args.recordings, "preset": args.preset}
        runs = {"in process": {"use_ray": False}}
        runs |= {f"ray, {n} worker(s)": {"use_ray": True, "workers": n} for n in args.ray_workers}
        for name, how in runs.items():
            out = root / name.replace(" ", "-").replace(",", "")
            started = time.perf_counter()
            options = ReconstructOptions(preset=args.preset)
            rows = run_batch(manifest, out, steps=STEPS, options=options, **how)
            seconds = time.perf_counter() - started
            if any(r.status != "done" for r in rows):
                raise SystemExit(f"{name}: {[(r.name, r.status, r.error) for r in rows]}")
            figures[f"{name}: seconds"] = seconds
            figures[f"{name}: recordings per minute"] = 60 * args.recordings / seconds
            figures[f"{name}: step seconds, summed"] = sum(r.seconds for r in rows)
        if {1, 2} <= set(args.ray_workers):
            one, two = (figures[f"ray, {n} worker(s): seconds"] for n in (1, 2))
            figures["throughput, 2 workers over 1"] = one / two
    report("batch", figures)


if __name__ == "__main__":
    main()
