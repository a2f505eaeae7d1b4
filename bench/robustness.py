"""The reconstruction under a real sensor's flaws and under pose noise: the ideal sensor against
a DAVIS346 as published and measured (sim/sensor_profiles.py), each of its effects alone and
some beyond it, the reconstruction with the sensor's calibration and without it; and the true
poses perturbed as in the method's Table 9 (rotation 0.5 / 1 / 2 / 5 degrees, translation in
proportion). Figures on the held-out views' object pixels (PSNR against a constant color's,
normals, depth) and stage II's base color.

    .venv/bin/python bench/robustness.py [--scenes single_object mic] [--rows ideal davis346 ...]
        [--preset fast] [--iterations N] [--resolution X] [--stage all|radiance] [--seed 5]

A row is a sensor (the events are simulated once per scene and sensor, into
results/sessions/), what the reconstruction knows of it ("truth": the simulated sensor's
calibration, as `evcap calibrate` measures a real one; "nominal": uniform thresholds and
nothing else, what a user without a calibration has) and the pose noise. Each run is kept in
results/robustness/ (its figures as JSON, its OUT folder beside them) and read back when asked
again with the same settings (--rerun: run again).
"mic" is NeRF-Synthetic's, from ../shared/data (its held-out views the release's train views).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from _common import RESULTS, flag_settings, machine, markdown_table, scene_file, scene_label

from evcap.recon.options import ReconstructOptions
from evcap.recon.reconstruct import reconstruct
from evcap.records import Calibration, Poses
from evcap.sim.sensor_profiles import PROFILES, SensorProfile

MIC = Path(__file__).resolve().parents[2] / "shared/data/nerf-synthetic-mic"
DAVIS346 = PROFILES["davis346"]
IDEAL = PROFILES["ideal"]
# the method's Table 9: 0.5 deg with 0.005 units of translation, 5 deg with 0.05, its cameras
# about 4 units from the object: translation 0.25 % of the distance per degree
TRANSLATION_PER_DEGREE = 0.0025


def _alone(name: str, **effect: dict) -> SensorProfile:
    return SensorProfile(name, IDEAL.threshold_on, IDEAL.threshold_off, effect)


@dataclass(frozen=True)
class Row:
    sensor: SensorProfile
    calibration: str = "truth"  # "truth", or "nominal": uniform thresholds (below)
    nominal: tuple[float, float] | None = None  # the nominal thresholds (None: the sensor's)
    noise_rates: bool = False  # the calibration's noise rates in the event loss
    refractory_bound: bool = False  # crowded events' windows a lower bound (events/windows.py)
    noise_filter_ms: float = 0.0  # the background-activity filter's time (0: none)
    pose_noise_deg: float = 0.0


DIM = SensorProfile(  # v2e's "noisy" preset: a dim scene
    "dim",
    IDEAL.threshold_on,
    IDEAL.threshold_off,
    {
        "threshold_spread": {"sigma": 0.05},
        "background_activity": {"rate_hz": 0.1},
        "shot_noise": {"rate_hz": 5.0},
        "bandwidth": {"cutoff_hz": 30.0},
    },
)
HOT = _alone("hot pixels", hot_pixels={"count": 20, "rate_hz": 200.0})
REFRACTORY = _alone("refractory", refractory=DAVIS346.effects["refractory"])
FOOTPRINT = DAVIS346.effects["footprint"]
# the profile as it was before its pixels had a footprint: points
POINT_PIXELS = dataclasses.replace(
    DAVIS346,
    name="davis346",  # its session the one simulated before (the digest tells them apart)
    effects={k: v for k, v in DAVIS346.effects.items() if k != "footprint"},
)
SPREAD = _alone("threshold spread", threshold_spread=DAVIS346.effects["threshold_spread"])

# in the order they are run: what the issue asks first
ROWS: dict[str, Row] = {
    "ideal": Row(IDEAL),
    "davis346": Row(DAVIS346),
    "footprint 0.28 px": Row(_alone("footprint", footprint=FOOTPRINT)),
    "davis346, uncalibrated": Row(DAVIS346, "nominal"),
    "davis346, uncalibrated 0.2": Row(DAVIS346, "nominal", (0.2, 0.2)),
    "davis346, refractory bound": Row(DAVIS346, refractory_bound=True),
    # all the calibration knows: thresholds, hot pixels, refractory period and noise rates
    "davis346, bound and noise rates": Row(DAVIS346, noise_rates=True, refractory_bound=True),
    "pose noise 0.5 deg": Row(IDEAL, pose_noise_deg=0.5),
    "pose noise 1 deg": Row(IDEAL, pose_noise_deg=1.0),
    "pose noise 2 deg": Row(IDEAL, pose_noise_deg=2.0),
    "pose noise 5 deg": Row(IDEAL, pose_noise_deg=5.0),
    "thresholds 0.134 / 0.203": Row(
        SensorProfile("asymmetric", DAVIS346.threshold_on, DAVIS346.threshold_off)
    ),
    "threshold spread 0.03": Row(SPREAD),
    "threshold spread 0.03, uncalibrated": Row(SPREAD, "nominal"),
    "background activity 0.1 Hz": Row(
        _alone("background", background_activity=DAVIS346.effects["background_activity"])
    ),
    "refractory 0.5 ms": Row(REFRACTORY),
    "refractory 0.5 ms, bound": Row(REFRACTORY, refractory_bound=True),
    "refractory 0.5 ms, footprint": Row(
        _alone(
            "refractory footprint", refractory=REFRACTORY.effects["refractory"], footprint=FOOTPRINT
        )
    ),
    "davis346 point pixels": Row(POINT_PIXELS),
    "davis346 point pixels, bound": Row(POINT_PIXELS, refractory_bound=True),
    "bandwidth 300 Hz": Row(_alone("bandwidth", bandwidth=DAVIS346.effects["bandwidth"])),
    "hot pixels 20 at 200 Hz": Row(HOT),
    "hot pixels 20 at 200 Hz, uncalibrated": Row(HOT, "nominal"),
    "dim light (v2e noisy)": Row(DIM),
    "dim light, noise rates": Row(DIM, noise_rates=True),
    "dim light, noise filter 5 ms": Row(DIM, noise_filter_ms=5.0),
    "timestamp jitter 20 us": Row(_alone("jitter", timestamp_jitter={"sigma_us": 20.0})),
    "dropped 2 %": Row(_alone("dropped", dropped={"probability": 0.02})),
}
COLUMNS = (
    "scene",
    "row",
    "iterations",
    "object_psnr",
    "object_psnr_gain",
    "object_psnr_constant",
    "normal_mae_deg",
    "depth_rel_err",
    "base_color_psnr",
    "base_color_psnr_gain",
    "events",
    "given_back_on",
    "given_back_off",
    "seconds",
)


def digest(value: object) -> str:
    """A short, file-name-safe key of ``value`` (as JSON)."""
    return hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()[:10]


def images_of(scene: str) -> Path | None:
    """The NeRF-Synthetic folder of ``scene`` ("mic", or a folder laid out as the release's),
    None for a simulator scene."""
    if scene == "mic":
        return MIC
    return Path(scene) if Path(scene, "transforms_test.json").exists() else None


def simulated(scene: str, sensor: SensorProfile, scale: float) -> Path:
    """The scene seen by ``sensor``, simulated once into results/sessions/."""
    from evcap.sim.from_images import simulate_from_images
    from evcap.sim.render import RENDERER_VERSION
    from evcap.sim.scene import load_scene, with_sensor_profile
    from evcap.sim.simulate import simulate

    images = images_of(scene)
    # made again when the renderer changes: its truth would not be today's
    key = digest(
        [sensor.threshold_on, sensor.threshold_off, sensor.effects, images and scale]
        + [RENDERER_VERSION]
    )
    name = f"{scene_label(scene)}-{sensor.name.replace(' ', '_')}-{key}"
    path = RESULTS / "sessions" / "robustness" / f"{name}.h5"
    if path.exists():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    print(f"simulating {scene} with the {sensor.name} sensor (once) ...", flush=True)
    started = time.perf_counter()
    if images is not None:
        views = len(json.loads((images / "transforms_train.json").read_text())["frames"])
        simulate_from_images(
            images / "transforms_test.json",
            path,
            held_out=images / "transforms_train.json",
            scale=scale,
            test_views=views,
            profile=sensor,
        )
    else:
        simulate(with_sensor_profile(load_scene(scene_file(scene)), sensor), path)
    print(f"  {time.perf_counter() - started:.0f} s", flush=True)
    return path


def prepared(session: Path, row: Row, folder: Path, seed: int) -> Path:
    """The session as the row's reconstruction sees it: a copy with the nominal calibration
    or perturbed poses where the row asks (the session itself otherwise)."""
    if row.calibration == "truth" and row.pose_noise_deg == 0:
        return session
    copy = folder / session.name
    shutil.copyfile(session, copy)
    if row.calibration == "nominal":
        cal = _read_calibration(copy)
        on, off = row.nominal or (row.sensor.threshold_on, row.sensor.threshold_off)
        shape = (cal.height, cal.width)
        nominal = Calibration(
            cal.width,
            cal.height,
            "nominal thresholds (bench/robustness.py)",
            K=cal.K,
            distortion_model=cal.distortion_model,
            dist=cal.dist,
            threshold_on=np.full(shape, on, np.float32),
            threshold_off=np.full(shape, off, np.float32),
        )
        nominal.write(copy)
    if row.pose_noise_deg:
        poses = Poses.read_file(copy)
        perturb(poses, row.pose_noise_deg, np.random.default_rng(seed)).write(copy)
    return copy


def _read_calibration(path: Path) -> Calibration:
    from evcap.session import Session

    with Session.open(path, validate=False) as s:
        return Calibration.read(s)


def perturb(poses: Poses, degrees: float, rng: np.random.Generator) -> Poses:
    """Each pose turned by a random rotation of RMS angle ``degrees`` and moved by a random
    offset of RMS length TRANSLATION_PER_DEGREE * degrees * the distance to the point the
    cameras look at (the method's Table 9 perturbs each camera independently)."""
    from evcap.rotations import exp_so3

    T = poses.T_world_cam.copy()
    n = len(T)
    centre = _looked_at(T)
    distance = float(np.median(np.linalg.norm(T[:, :3, 3] - centre, axis=1)))
    rotvec = rng.normal(0, np.radians(degrees) / np.sqrt(3), (n, 3))
    offset = rng.normal(0, TRANSLATION_PER_DEGREE * degrees * distance / np.sqrt(3), (n, 3))
    T[:, :3, :3] = exp_so3(rotvec) @ T[:, :3, :3]
    T[:, :3, 3] += offset
    return dataclasses.replace(poses, T_world_cam=T, source=f"{poses.source}, perturbed")


def _looked_at(T: np.ndarray) -> np.ndarray:
    """The point nearest to every camera's optical axis (least squares)."""
    d = T[:, :3, 2]
    A = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    return np.linalg.solve(A.sum(0), (A @ T[:, :3, 3, None]).sum(0))[:, 0]


def run_row(scene: str, name: str, args: argparse.Namespace) -> dict:
    row = ROWS[name]
    settings = {
        "preset": args.preset,
        "iterations": args.iterations,
        "resolution": args.resolution,
        "material_iterations": args.material_iterations,
        "stage": args.stage,
        "seed": args.seed,
        "scale": args.scale if images_of(scene) else None,
    }
    key = f"{scene_label(scene)}-{name}-{digest(settings)}".replace(" ", "_").replace("/", "-")
    path = RESULTS / "robustness" / f"{key}.json"
    if path.exists() and not args.rerun:
        print(f"{scene}, {name}: read from {path}", flush=True)
        out = json.loads(path.read_text())
        if "given_back_on" not in out:  # kept before this figure existed
            out.update(given_back(simulated(scene, row.sensor, args.scale)))
            path.write_text(json.dumps(out, indent=2))
        return out
    session = simulated(scene, row.sensor, args.scale)
    out_folder = path.with_suffix("")  # the run's OUT: its renders, beside the truth's
    shutil.rmtree(out_folder, ignore_errors=True)
    overrides = {
        "stage1.event_loss.noise_rates": row.noise_rates,
        "stage1.windows.refractory_bound": row.refractory_bound,
        "stage1.windows.noise_filter_ms": row.noise_filter_ms,
        "stage1.poses.refine": "off",
    }
    overrides |= flag_settings(
        args.stage,
        iterations=args.iterations,
        resolution=args.resolution,
        material_iterations=args.material_iterations,
    )
    options = ReconstructOptions(
        preset=args.preset, stage=args.stage, seed=args.seed, settings=overrides
    )
    with tempfile.TemporaryDirectory() as tmp:
        used = prepared(session, row, Path(tmp), args.seed)
        started = time.perf_counter()
        result = reconstruct(used, out_folder, options)
        seconds = time.perf_counter() - started
    figures = {k: v for k, v in result.to_json().items() if k not in ("history", "training_log")}
    out = {
        "scene": scene_label(scene),
        "row": name,
        "settings": settings,
        **_events(session),
        **given_back(session),
        "seconds": seconds,
        **figures,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2))
    print(" ".join(f"{k}={out.get(k)}" for k in COLUMNS), flush=True)
    return out


def _events(session: Path) -> dict:
    """The session's events, and their highest rate over 1 ms (a DAVIS346's bus carries
    12 MEv/s: above it, a real sensor drops events)."""
    from evcap.session import Session

    with Session.open(session, validate=False) as s:
        t = s.events().t
    per_ms = np.bincount((t - t.min()) // 1000) if len(t) else np.zeros(1)
    return {"events": len(t), "peak_mev_per_s": float(per_ms.max()) / 1e3}


def given_back(session: Path, least: float = 0.3) -> dict:
    """How much of the truth's change the events give back: between consecutive views along
    the path, on the surface's pixels whose log signal changed by more than ``least``, the
    events' sum (ON times its threshold, OFF less its) over the change, brightenings and
    darkenings apart. The ideal sensor's shortfall is the thresholds' quantization (a pixel
    keeps up to a threshold's change unspoken); a refractory period's dropped events add
    theirs."""
    from evcap.records import GroundTruth
    from evcap.session import Session
    from evcap.sim.scene import SensorSpec
    from evcap.sim.sensor import ChannelMap

    with Session.open(session, validate=False) as s:
        truth = GroundTruth.read(s, along_path=True)
        ev = s.events()
        w, h = s.sensor.width, s.sensor.height
        channels = ChannelMap(w, h, s.sensor.color_filter)
    views = truth.path
    if views.radiance is None or views.depth is None or truth.threshold_on is None:
        return {}
    on, off = truth.threshold_on.ravel(), truth.threshold_off.ravel()
    px = ev.y.astype(np.int64) * w + ev.x
    step = np.where(ev.p > 0, on[px], -off[px])
    sums = np.zeros((2, 2))  # [brightening, darkening] x [events, truth]
    for i in range(len(truth.t) - 1):
        a, b = np.searchsorted(ev.t, truth.t[i : i + 2])
        said = np.bincount(px[a:b], weights=step[a:b], minlength=w * h)
        logs = [
            np.log(channels.of(views.radiance[j].reshape(-1, 3)) + SensorSpec.dark_level)
            for j in (i, i + 1)
        ]
        change = logs[1] - logs[0]
        surface = (views.depth[i].ravel() > 0) & (views.depth[i + 1].ravel() > 0)
        for k, moved in enumerate((change > least, change < -least)):
            sums[k] += said[surface & moved].sum(), change[surface & moved].sum()
    share = sums[:, 0] / np.where(sums[:, 1] == 0, np.nan, sums[:, 1])
    return {"given_back_on": float(share[0]), "given_back_off": float(share[1])}


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["single_object", "mic"])
    parser.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--iterations", type=int)
    parser.add_argument("--material-iterations", type=int)
    parser.add_argument("--resolution", type=float)
    parser.add_argument("--stage", default="all", choices=["all", "radiance"])
    parser.add_argument("--scale", type=float, default=0.5, help="mic's image scale")
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--rerun", action="store_true", help="run again what was kept")
    parser.add_argument("--name", default="robustness", help="the results' file name")
    args = parser.parse_args(argv)
    rows = [run_row(scene, name, args) for scene in args.scenes for name in args.rows]
    for scene in {r["scene"] for r in rows}:  # each row's change against the ideal's
        ideal = next((r for r in rows if r["scene"] == scene and r["row"] == "ideal"), None)
        for r in rows:
            if ideal is not None and r["scene"] == scene:
                for k in ("object_psnr_gain", "normal_mae_deg"):
                    if r.get(k) is not None and ideal.get(k) is not None:
                        r[f"{k}_change"] = r[k] - ideal[k]
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{args.name}.json"
    path.write_text(json.dumps({"benchmark": args.name, "machine": machine(), "runs": rows}))
    changes = ("object_psnr_gain", "normal_mae_deg")  # each beside its change
    columns = tuple(c for k in COLUMNS for c in ((k, f"{k}_change") if k in changes else (k,)))
    table = markdown_table(rows, columns)
    (RESULTS / f"{args.name}.md").write_text(table)
    print(table)
    print(f"-> {path}, .md")
    return rows


if __name__ == "__main__":
    main()
