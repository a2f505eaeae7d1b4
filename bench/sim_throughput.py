"""Simulator speed at the DAVIS346's 346 x 260: time per rendered frame, events simulated per
second, and the cost of each sensor effect (each alone, against the clean sensor); then each
bundled example scene simulated whole with its own settings, its time per stage, and the error
that sharing the specular light between key renders leaves (against the exact integral, on a
stretch of key renders in the middle of the path).

    .venv/bin/python bench/sim_throughput.py [--seconds S] [--size 346x260] [--scenes NAME ...]

``--size`` also scales the bundled scenes' cameras (their lenses keep their angles).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import SCENES, report

from evcap.sim.render import Renderer
from evcap.sim.scene import Scene, load_scene
from evcap.sim.simulate import ANCHOR_EVERY, Simulator, simulate
from evcap.sim.specular_reuse import SpecularFrame, specular_between
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


def scaled(scene: Scene, size: tuple[int, int]) -> Scene:
    """``scene`` with its camera at ``size`` (the same lens, the pixels scaled)."""
    c = scene.camera
    k = size[0] / c.width
    camera = dataclasses.replace(
        c, width=size[0], height=size[1], fx=c.fx * k, fy=c.fy * k, cx=c.cx * k, cy=c.cy * k
    )
    return dataclasses.replace(scene, camera=camera)


def sharing_error(scene: Scene) -> dict:
    """The specular light shared between key renders against the exact integral, on the key
    renders between two anchors in the middle of the path: log radiance error quantiles (the
    threshold is about 0.2) and the share of surface pixels integrated exactly."""
    sim = Simulator(scene)
    n = sim.camera.width * sim.camera.height
    times = [scene.trajectory.duration_s * 0.5e6]
    times += sim._key_times(times[0], scene.trajectory.duration_s * 1e6)
    renders = [sim._render(t) for t in times]
    exact = [sim.renderer.environment_specular(r.specular_inputs) for r in renders]
    a = SpecularFrame.of(n, renders[0].specular_inputs, exact[0])
    b = SpecularFrame.of(n, renders[-1].specular_inputs, exact[-1])
    errors, integrated, total = [np.zeros(0)], 0, 0
    for t, r, truth in zip(times[1:-1], renders[1:-1], exact[1:-1], strict=True):
        inputs = r.specular_inputs
        s = (t - times[0]) / (times[-1] - times[0])
        shared, count = specular_between(sim.renderer, a, b, s, inputs, inputs.rows)
        integrated, total = integrated + count, total + len(inputs.rows)
        rest = r.radiance[inputs.rows]  # everything but the environment's specular light
        dark = scene.sensor.dark_level
        errors.append(np.abs(np.log(rest + shared + dark) - np.log(rest + truth + dark)).max(1))
    e = np.concatenate(errors)
    q = np.quantile(e, [0.5, 0.99, 0.999, 1.0]) if len(e) else np.zeros(4)
    return {
        "log_error_p50": float(q[0]),
        "log_error_p99": float(q[1]),
        "log_error_p999": float(q[2]),
        "log_error_max": float(q[3]),
        "integrated_share": integrated / max(total, 1),
    }


def bundled(names: list[str], size: tuple[int, int] | None, folder: Path) -> dict:
    """Each scene simulated whole: wall time, time per stage, renders, events."""
    out = {}
    for name in names:
        scene = load_scene(SCENES / f"{name}.toml")
        if size is not None:
            scene = scaled(scene, size)
        start = time.perf_counter()
        stats = simulate(scene, folder / f"{name}.h5", overwrite=True)
        wall = time.perf_counter() - start
        out[name] = {
            "wall_s": round(wall, 1),
            "stage_seconds": {k: round(v, 1) for k, v in stats.seconds.items()},
            "key_renders": stats.key_renders,
            "refined_pixel_renders": stats.refined_pixels,
            "specular_integrated": stats.exact_specular,
            "specular_shared": stats.shared_specular,
            "events": stats.events,
            "aps_frames": stats.frames,
            "sharing": sharing_error(scene),
        }
        print(name, out[name], flush=True)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=0.25, help="scene time simulated")
    parser.add_argument("--size", default="346x260", help="the sensor's width x height")
    parser.add_argument(
        "--scenes",
        nargs="*",
        default=sorted(p.stem for p in SCENES.glob("*.toml")),
        help="bundled scenes simulated whole (default: all)",
    )
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    own_size = None if args.size == "346x260" else size
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
        figures["anchor_every"] = ANCHOR_EVERY
        figures["scenes"] = bundled(args.scenes, own_size, folder)
    report("sim_throughput", figures)


if __name__ == "__main__":
    main()
