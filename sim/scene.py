"""Scenes for the simulator, described in TOML (the format is documented in sim/scenes/README.md).

``load_scene(path)`` reads and checks a scene file and returns a ``Scene``: what is in it
(objects and their materials), how it is lit, the camera and its path, the sensor and the
effects it should simulate. Every sensor effect, shadows and indirect light are off unless the
scene asks for them. Errors name the file and the key.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path

from evcap.errors import InputError, InputNotFoundError
from evcap.events import check_color_filter
from evcap.sim.sensor_profiles import SensorProfile, sensor_profile
from evcap.toml_file import Table, read_toml


@dataclass(frozen=True)
class Material:
    """Dielectric (metallic 0): a base color and a GGX roughness."""

    base_color: tuple[float, float, float] = (0.7, 0.7, 0.7)  # linear RGB, 0..1
    roughness: float = 0.5  # GGX roughness (perceptual: alpha = roughness^2), 0.02..1
    texture: Path | None = None  # an image (sRGB) mapped by the object's UVs, over base_color
    procedural: dict | None = None  # {"kind": "checker"|"stripes"|"noise", ...} (see README)


@dataclass(frozen=True)
class SceneObject:
    kind: str  # "sphere", "box", "plane", "mesh", "charuco"
    material: str  # a key of Scene.materials
    params: dict  # the kind's parameters (center, radius, size, path, ...)


SPECULAR_SIDE = 12  # GGX samples per pixel of the specular light: a 12 x 12 grid


@dataclass(frozen=True)
class Lighting:
    environment: str = "sky"  # "sky", or a path to an equirectangular image (.hdr/.exr/.png)
    sky: dict = field(default_factory=dict)  # the analytic sky's colors and sun
    intensity: float = 1.0  # multiplies the environment
    rotation_deg: float = 0.0  # of the environment about the world's up axis
    points: tuple[dict, ...] = ()  # point lights: position, intensity (RGB radiant intensity)
    shadows: bool = False  # visibility of the environment and the lights
    indirect: bool = False  # one bounce of diffuse light between surfaces (color bleeding)
    samples: int = 256  # directions for the baked diffuse light (shadows, indirect)
    # GGX samples of the specular light per pixel: a side x side grid (a scene whose shading
    # nobody grades, such as a calibration board's, can take fewer: a render costs about this)
    specular_side: int = SPECULAR_SIDE


@dataclass(frozen=True)
class CameraSpec:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion_model: str = "none"  # "none", "radtan" (plumb_bob), "equidistant"
    distortion: tuple[float, ...] = ()
    source: str = "scene"  # where the intrinsics come from


@dataclass(frozen=True)
class TrajectorySpec:
    kind: str  # "orbit", "handheld", "linear", "static"
    duration_s: float
    params: dict


# Sensor effects and their parameters (each off unless listed in [sensor.effects]).
EFFECTS = {
    "threshold_spread": {"sigma": float},  # per-pixel, per-polarity threshold: N(C, sigma)
    "background_activity": {"rate_hz": float},  # leak events per pixel per second (ON)
    "shot_noise": {"rate_hz": float},  # random ON and OFF events per pixel per second
    "hot_pixels": {"count": int, "rate_hz": float},  # pixels firing ON events at rate_hz
    "refractory": {"period_us": int},  # events closer than this after one are dropped
    "bandwidth": {"cutoff_hz": float},  # first-order low-pass of the log photocurrent
    "footprint": {"sigma_px": float},  # the pixel's area and the lens's blur (evcap.sim.events)
    "timestamp_jitter": {"sigma_us": float},  # Gaussian jitter of event times
    "dropped": {"probability": float},  # each event is lost with this probability
}


@dataclass(frozen=True)
class SensorSpec:
    color_filter: str = "RGBG"
    threshold_on: float = 0.2  # contrast threshold C of ON events (log units)
    threshold_off: float = 0.2
    dark_level: float = 1e-3  # added to the radiance before the log (the dark current)
    effects: dict = field(default_factory=dict)  # name -> parameters, see EFFECTS
    # a calibrated session (`evcap calibrate`) whose measured sensor this one copies: per-pixel
    # thresholds, hot pixels, noise rates, refractory period (effects listed here win)
    calibration: Path | None = None
    # seed of the sensor's fixed imperfections (per-pixel thresholds, background-activity
    # rates, hot pixels): scenes giving the same seed (and effects) simulate the same physical
    # sensor. None: they are drawn from the scene's seed, as before this key existed
    seed: int | None = None
    profile: str = "ideal"  # the named sensor the thresholds and effects start from


@dataclass(frozen=True)
class ApsSpec:
    fps: float = 25.0
    exposure_us: int = 4000
    gain: float = 200.0  # ADC counts per unit of radiance per millisecond of exposure
    read_noise: float = 2.0  # ADC counts
    shot_noise: bool = True


@dataclass(frozen=True)
class ImuSpec:
    rate_hz: float = 1000.0
    gyro_noise: float = 0.0  # rad/s, white noise standard deviation
    accel_noise: float = 0.0  # m/s^2


# The held-out views' second light, for relighting truth: a dim sky over a dark blue ground and
# a broad warm glow from one low side, so that relit views differ from the scene's own light in
# where the light comes from, not only in its tint (a per-channel correction absorbs a tint)
RELIGHT_SKY = {
    "zenith": [0.3, 0.22, 0.15],
    "horizon": [0.45, 0.35, 0.25],
    "ground": [0.06, 0.08, 0.14],
    "lobe_direction": [-0.5, 0.8, 0.35],
    "lobe_radiance": [2.4, 1.7, 1.0],
    "lobe_width_deg": 35.0,
}


@dataclass(frozen=True)
class GroundTruthSpec:
    fps: float = 20.0  # ground-truth frames per second
    test_views: int = 8  # held-out views off the trajectory
    # the environment the held-out views are rendered under a second time (environment, sky,
    # intensity, rotation_deg as in [lighting]; no sun: the reconstruction is handed it as an
    # image); shadows and bounce as the scene's, point lights off
    relight: Lighting = field(default_factory=lambda: Lighting(sky=RELIGHT_SKY))


@dataclass(frozen=True)
class Scene:
    path: Path
    name: str
    seed: int
    units_per_meter: float  # scene units per meter (for the IMU's accelerations)
    objects: tuple[SceneObject, ...]
    materials: dict[str, Material]
    lighting: Lighting
    camera: CameraSpec
    trajectory: TrajectorySpec
    sensor: SensorSpec
    aps: ApsSpec | None
    imu: ImuSpec | None
    gt: GroundTruthSpec
    max_step_px: float = 0.5  # the simulator's sampling: largest image motion between renders
    max_step_log: float = 0.25  # ...and largest log-radiance change, in thresholds


def _params(t: Table, keys: dict) -> dict:
    """An object's or a path's keys, each of its kind and range (OBJECT_KEYS); unknown keys
    refused."""
    params = {}
    for key, kind in keys.items():
        if key not in t.data:
            continue
        if kind in ("positive", "count"):
            value = t.get(key, float if kind == "positive" else int)
            params[key] = _positive(t.where, key, value)
        elif kind == "zero+":
            params[key] = _at_least_zero(t.where, key, t.get(key, float))
        elif kind in ("size2", "size3"):
            n = int(kind[-1])
            value = t.get(key, list)
            if len(value) != n or not all(
                isinstance(v, int | float) and not isinstance(v, bool) and v > 0 for v in value
            ):
                raise InputError(f"{t.where}: {key} must be {n} positive numbers, got {value!r}")
            params[key] = [float(v) for v in value]
        else:
            value = t.get(key, kind)
            params[key] = list(value) if kind == "vec3" else value
    t.done()
    return params


def _at_least_zero(where: str, key: str, value: float) -> float:
    if not value >= 0:
        raise InputError(f"{where}: {key} must be 0 or more, got {value}")
    return value


def _positive(where: str, key: str, value: float) -> float:
    if not value > 0:
        raise InputError(f"{where}: {key} must be positive, got {value}")
    return value


def _resolve(base: Path, value: str, what: str) -> Path:
    path = Path(value) if Path(value).is_absolute() else base / value
    if not path.exists():
        raise InputNotFoundError(f"{what} {value!r} not found (looked at {path})")
    return path


def _camera(t: Table, base: Path) -> CameraSpec:
    calibration = t.get("calibration", str)
    camera = t.get("calibration_camera", str)
    if camera is not None and calibration is None:
        raise InputError(f"{t.where}: calibration_camera goes with calibration (a file)")
    width = _positive(t.where, "width", t.get("width", int, 346))
    height = _positive(t.where, "height", t.get("height", int, 260))
    if calibration is not None:
        from evcap.sim.camera import load_calibration

        spec = load_calibration(_resolve(base, calibration, f"{t.where}: calibration"), camera)
        t.done()
        return spec
    fx = _positive(t.where, "fx", t.get("fx", float, 250.0))
    spec = CameraSpec(
        width=width,
        height=height,
        fx=fx,
        fy=_positive(t.where, "fy", t.get("fy", float, fx)),
        cx=t.get("cx", float, (width - 1) / 2),
        cy=t.get("cy", float, (height - 1) / 2),
        distortion_model=t.get("distortion_model", str, "none"),
        distortion=tuple(float(v) for v in t.get("distortion", list, [])),
    )
    if spec.distortion_model not in ("none", "radtan", "equidistant"):
        raise InputError(f"{t.where}: distortion_model must be none, radtan or equidistant")
    t.done()
    return spec


def _procedural(t: Table) -> None:
    if t.get("kind", str, required=True) not in ("checker", "stripes", "noise"):
        raise InputError(f"{t.where}: kind must be checker, stripes or noise")
    _positive(t.where, "scale", t.get("scale", float, 8.0))
    colors = t.get("colors", list, [[0.9, 0.9, 0.9], [0.1, 0.1, 0.1]])
    if len(colors) < 2 or not all(
        isinstance(c, list)
        and len(c) == 3
        and all(isinstance(v, int | float) and not isinstance(v, bool) and 0 <= v <= 1 for v in c)
        for c in colors
    ):
        raise InputError(f"{t.where}: colors must be 2 or more [r, g, b] in 0..1, got {colors!r}")
    t.done()


def _material(name: str, t: Table, base: Path) -> Material:
    texture = t.get("texture", str)
    procedural = t.get("procedural", dict)
    if procedural is not None:
        _procedural(Table(procedural, f"{t.where} procedural"))
    m = Material(
        base_color=t.get("base_color", "vec3", (0.7, 0.7, 0.7)),
        roughness=t.get("roughness", float, 0.5),
        texture=_resolve(base, texture, f"{t.where}: texture") if texture else None,
        procedural=procedural,
    )
    if not 0.02 <= m.roughness <= 1.0:
        raise InputError(f"{t.where}: roughness must be in 0.02..1, got {m.roughness}")
    if not all(0.0 <= c <= 1.0 for c in m.base_color):
        raise InputError(f"{t.where}: base_color must be in 0..1 (linear RGB)")
    t.done()
    return m


# each object type's keys: "vec3" 3 numbers, "size2" / "size3" 2 / 3 positive numbers,
# "positive" a number > 0, "count" an integer >= 1, "zero+" a number >= 0
_PLACED = {"center": "vec3", "rotation_deg": "vec3"}
OBJECT_KEYS = {
    "sphere": {**_PLACED, "radius": "positive", "segments": "count", "rings": "count"},
    "box": {**_PLACED, "size": "size3", "subdivisions": "count"},
    "plane": {**_PLACED, "size": "size2", "subdivisions": "count"},
    "mesh": {**_PLACED, "path": str, "scale": "positive", "center_and_fit": bool},
    "charuco": {
        **_PLACED,
        "squares_x": "count",
        "squares_y": "count",
        "square_length": "positive",
        "marker_length": "positive",
        "dictionary": str,
        "margin": float,
        "subdivisions": "count",
    },
}
OBJECT_KINDS = tuple(OBJECT_KEYS)
_AIMED = {"look_at": "vec3"}
TRAJECTORY_KEYS = {
    "orbit": {
        **_AIMED,
        "center": "vec3",
        "radius": "positive",
        "height": float,
        "height_swing": float,
        "swings": "zero+",
        "start_deg": float,
        "degrees": float,
    },
    "handheld": {
        **_AIMED,
        "start": "vec3",
        "end": "vec3",
        "shake_units": "zero+",
        "shake_deg": "zero+",
        "shake_hz": "positive",
    },
    "linear": {**_AIMED, "start": "vec3", "end": "vec3"},
    "static": {**_AIMED, "position": "vec3"},
}


def _environment(t: Table, base: Path, sky: dict | None = None) -> dict:
    """A [lighting] table's environment keys."""
    env = t.get("environment", str, "sky")
    if env != "sky":
        env = str(_resolve(base, env, f"{t.where}: environment"))
    return {
        "environment": env,
        "sky": t.get("sky", dict, {} if sky is None else sky),
        "intensity": _at_least_zero(t.where, "intensity", t.get("intensity", float, 1.0)),
        "rotation_deg": t.get("rotation_deg", float, 0.0),
    }


def _relight(t: Table, base: Path, lighting: Lighting) -> Lighting:
    """[gt] relight: the second environment, with the scene's shadows and bounce."""
    env = _environment(t, base, RELIGHT_SKY)
    t.done()
    if env["environment"] == "sky" and env["sky"].get("sun_irradiance", 0):
        raise InputError(
            f"{t.where}: no sun here (the reconstruction relights with an image); "
            "brighten the sky or give an environment image"
        )
    return dataclasses.replace(lighting, points=(), **env)


EXAMPLES = Path(__file__).resolve().parent / "scenes"  # shipped inside the package


def example_scene(name_or_path: str | os.PathLike) -> Path:
    """A scene file's path: the file itself when it exists, else the example scene so named."""
    path = Path(name_or_path)
    if path.exists() or path.suffix:
        return path
    example = EXAMPLES / f"{path.name}.toml"
    if not example.exists():
        names = ", ".join(sorted(p.stem for p in EXAMPLES.glob("*.toml")))
        raise InputNotFoundError(f"{name_or_path}: no such scene file, nor example ({names})")
    return example


def with_sensor_profile(scene: Scene, name: str | SensorProfile) -> Scene:
    """``scene`` seen by the named sensor (sim/sensor_profiles.py): its thresholds and effects,
    in place of the scene's own (and of a measured sensor the scene copies)."""
    profile = sensor_profile(name)
    sensor = dataclasses.replace(
        scene.sensor,
        threshold_on=profile.threshold_on,
        threshold_off=profile.threshold_off,
        effects={k: dict(v) for k, v in profile.effects.items()},
        calibration=None,
        profile=profile.name,
    )
    return dataclasses.replace(scene, sensor=sensor)


def load_scene(path: str | os.PathLike) -> Scene:
    """Read and check a scene file."""
    path = Path(path)
    doc = read_toml(path, "scene")
    base = path.parent
    top = Table(doc, str(path))
    scene = top.table("scene")
    materials = {
        name: _material(name, Table(value, f"{path} [materials.{name}]"), base)
        for name, value in top.get("materials", dict, {}).items()
    }
    objects = []
    for i, value in enumerate(top.get("objects", list, [])):
        where = f"{path} [[objects]] #{i + 1}"
        if not isinstance(value, dict):
            raise InputError(f"{where}: must be a table")
        kind = value.get("type")
        if kind not in OBJECT_KINDS:
            raise InputError(f"{where}: type must be one of {', '.join(OBJECT_KINDS)}")
        material = value.get("material", "default")
        if material not in materials:
            if material != "default":
                raise InputError(f"{where}: unknown material {material!r}")
            materials.setdefault("default", Material())
        params = _params(
            Table({k: v for k, v in value.items() if k not in ("type", "material")}, where),
            OBJECT_KEYS[kind],
        )
        if kind == "mesh":
            if "path" not in params:
                raise InputError(f"{where}: a mesh needs path")
            params["path"] = _resolve(base, params["path"], f"{where}: mesh")
        objects.append(SceneObject(kind, material, params))
    if not objects:
        raise InputError(f"{path}: the scene has no [[objects]]")

    light = top.table("lighting")
    lighting = Lighting(
        **_environment(light, base),
        points=tuple(light.get("points", list, [])),
        shadows=light.get("shadows", bool, False),
        indirect=light.get("indirect", bool, False),
        samples=_positive(light.where, "samples", light.get("samples", int, 256)),
        specular_side=_positive(
            light.where, "specular_side", light.get("specular_side", int, SPECULAR_SIDE)
        ),
    )
    light.done()

    sensor_t = top.table("sensor")
    profile = sensor_profile(sensor_t.get("profile", str, "ideal"))
    c_on, c_off = profile.threshold_on, profile.threshold_off
    if (c := sensor_t.get("contrast_threshold", float)) is not None:
        c_on = c_off = c
    cal = sensor_t.get("calibration", str)
    effects = {name: dict(params) for name, params in profile.effects.items()}
    for name, params in sensor_t.get("effects", dict, {}).items():
        if name not in EFFECTS:
            raise InputError(
                f"{sensor_t.where}: unknown effect {name!r}; known: {', '.join(EFFECTS)}"
            )
        et = Table(params if isinstance(params, dict) else {}, f"{sensor_t.where} effects.{name}")
        effects[name] = {
            key: _at_least_zero(et.where, key, et.get(key, kind, required=True))
            for key, kind in EFFECTS[name].items()
        }
        et.done()
        if effects[name].get("probability", 0) > 1:
            raise InputError(f"{et.where}: probability must be in 0..1")
    sensor = SensorSpec(
        color_filter=check_color_filter(sensor_t.get("color_filter", str, "RGBG")),
        threshold_on=_positive(
            sensor_t.where, "threshold_on", sensor_t.get("threshold_on", float, c_on)
        ),
        threshold_off=_positive(
            sensor_t.where, "threshold_off", sensor_t.get("threshold_off", float, c_off)
        ),
        dark_level=_positive(sensor_t.where, "dark_level", sensor_t.get("dark_level", float, 1e-3)),
        effects=effects,
        calibration=_resolve(base, cal, f"{sensor_t.where}: calibration") if cal else None,
        seed=sensor_t.get("seed", int),
        profile=profile.name,
    )
    sensor_t.done()

    camera = _camera(top.table("camera"), base)
    traj = top.table("trajectory")
    kind = traj.get("kind", str, "orbit")
    if kind not in ("orbit", "handheld", "linear", "static"):
        raise InputError(f"{traj.where}: kind must be orbit, handheld, linear or static")
    duration = _positive(traj.where, "duration_s", traj.get("duration_s", float, 2.0))
    rest = {k: v for k, v in traj.data.items() if k not in ("kind", "duration_s")}
    traj.used.update(traj.data)
    trajectory = TrajectorySpec(
        kind, duration, _params(Table(rest, traj.where), TRAJECTORY_KEYS[kind])
    )

    aps = None
    if "aps" in doc:
        a = top.table("aps")
        aps = ApsSpec(
            fps=_positive(a.where, "fps", a.get("fps", float, 25.0)),
            exposure_us=_positive(a.where, "exposure_us", a.get("exposure_us", int, 4000)),
            gain=_positive(a.where, "gain", a.get("gain", float, 200.0)),
            read_noise=_at_least_zero(a.where, "read_noise", a.get("read_noise", float, 2.0)),
            shot_noise=a.get("shot_noise", bool, True),
        )
        a.done()
    imu = None
    if "imu" in doc:
        i = top.table("imu")
        imu = ImuSpec(
            rate_hz=_positive(i.where, "rate_hz", i.get("rate_hz", float, 1000.0)),
            gyro_noise=_at_least_zero(i.where, "gyro_noise", i.get("gyro_noise", float, 0.0)),
            accel_noise=_at_least_zero(i.where, "accel_noise", i.get("accel_noise", float, 0.0)),
        )
        i.done()
    g = top.table("gt")
    relight = _relight(Table(g.get("relight", dict, {}), f"{g.where}.relight"), base, lighting)
    gt = GroundTruthSpec(
        fps=_positive(g.where, "fps", g.get("fps", float, 20.0)),
        test_views=_at_least_zero(g.where, "test_views", g.get("test_views", int, 8)),
        relight=relight,
    )
    g.done()
    result = Scene(
        path=path,
        name=scene.get("name", str, path.stem),
        seed=scene.get("seed", int, 0),
        units_per_meter=_positive(
            scene.where, "units_per_meter", scene.get("units_per_meter", float, 1.0)
        ),
        objects=tuple(objects),
        materials=materials,
        lighting=lighting,
        camera=camera,
        trajectory=trajectory,
        sensor=sensor,
        aps=aps,
        imu=imu,
        gt=gt,
        max_step_px=_positive(scene.where, "max_step_px", scene.get("max_step_px", float, 0.5)),
        max_step_log=_positive(scene.where, "max_step_log", scene.get("max_step_log", float, 0.25)),
    )
    scene.done()
    top.used.update(
        {
            "scene",
            "materials",
            "objects",
            "lighting",
            "sensor",
            "camera",
            "trajectory",
            "aps",
            "imu",
            "gt",
        }
    )
    top.done()
    return result
