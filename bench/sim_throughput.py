"""Simulator speed at the DAVIS346's 346 x 260: time per rendered frame, events simulated per
second, and the cost of each sensor effect (each alone, against the clean sensor).

    .venv/bin/python bench/sim_throughput.py [--seconds S] [--size 346x260]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from _common import report

from evcap.sim.render import Renderer
from evcap.sim.scene import load_scene
from evcap.sim.simulate import simulate
from evcap.sim.trajectory import Trajectory

SCENE = """
[scene]
name = "bench"
[sensor]
color_filter = "RGBG"
{effects}
[camera]
width = {width}
height = {height}
fx = {fx}
[trajectory]
kind = "orbit"
radius = 2.2
height = 0.8
degrees = {degrees}
duration_s = {duration}
[lighting]
environment = "sky"
[materials.paint]
procedural = {{ kind = "checker", scale = 8, colors = [[0.8, 0.25, 0.1], [0.9, 0.85, 0.6]] }}
roughness = 0.4
[[objects]]
type = "sphere"
radius = 0.6
material = "paint"
[gt]
fps = 5
test_views = 0
"""

EFFECTS = {
    "threshold_spread": "{ sigma = 0.03 }",
    "background_activity": "{ rate_hz = 0.1 }",
    "shot_noise": "{ rate_hz = 1.0 }",
    "hot_pixels": "{ count = 20, rate_hz = 200.0 }",
    "refractory": "{ period_us = 500 }",
    "bandwidth": "{ cutoff_hz = 300.0 }",
    "timestamp_jitter": "{ sigma_us = 20.0 }",
    "dropped": "{ probability = 0.02 }",
}


def scene_file(
    folder: Path, duration: float, effect: str | None = None, size: tuple[int, int] = (346, 260)
) -> Path:
    effects = f"[sensor.effects]\n{effect} = {EFFECTS[effect]}" if effect else ""
    path = folder / f"{effect or 'clean'}.toml"
    # the camera circles at 60 degrees per second (about 250 pixels per second at the object at
    # 346 x 260; the lens keeps its angle at other sizes)
    width, height = size
    path.write_text(
        SCENE.format(
            effects=effects,
            duration=duration,
            degrees=60.0 * duration,
            width=width,
            height=height,
            fx=250.0 * width / 346,
        )
    )
    return path


def run(path: Path, out: Path) -> tuple[float, object]:
    start = time.perf_counter()
    stats = simulate(load_scene(path), out, overwrite=True)
    return time.perf_counter() - start, stats


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=0.25, help="scene time simulated")
    parser.add_argument("--size", default="346x260", help="the sensor's width x height")
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        scene = load_scene(scene_file(folder, args.seconds, size=size))
        renderer = Renderer(scene)
        pose = Trajectory(scene.trajectory).pose(0.0)
        renderer.render_full(pose)  # compile
        times = []
        for _ in range(5):
            start = time.perf_counter()
            renderer.render_full(pose)
            times.append(time.perf_counter() - start)
        out = folder / "s.h5"
        run(scene_file(folder, 0.01, size=size), out)  # warm up
        clean_s, clean = run(scene_file(folder, args.seconds, size=size), out)
        figures = {
            "resolution": args.size,
            "render_ms_per_frame": 1000 * statistics.median(times),
            "scene_seconds": args.seconds,
            "events": clean.events,
            "wall_s": clean_s,
            "events_per_s": clean.events / clean_s,
            "wall_s_per_scene_s": clean_s / args.seconds,
            "key_renders": clean.key_renders,
            "refined_pixel_renders": clean.refined_pixels,
            "stage_seconds": {k: round(v, 3) for k, v in clean.seconds.items()},
        }
        for effect in EFFECTS:
            seconds, stats = run(scene_file(folder, args.seconds, effect, size), out)
            figures[f"effect_{effect}_cost"] = seconds / clean_s
    report("sim_throughput", figures)


if __name__ == "__main__":
    main()
