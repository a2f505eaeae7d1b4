import functools
import json
import os
import textwrap
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
# Compiled loops check their indexing under test: a bug raises IndexError, not a segfault.
# numba's cache does not tell such builds from the normal ones: keep them apart.
os.environ.setdefault("NUMBA_BOUNDSCHECK", "1")
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-test-cache"))

SHARED = Path(os.environ.get("EVCAP_SHARED", ROOT.parent / "shared"))
SAMPLE_AEDAT4 = SHARED / "data" / "davis346-sample" / "davis346_test_data.aedat4"

# The default run's longest test files (over half a minute each, measured with --durations),
# longest first. scripts/test.sh deals whole files to two workers in collection order: with
# the longest dealt first, the two finish together.
LONGEST_FILES = (
    "tests/test_bench.py",
    "tests/test_batch.py",
    "tests/recon/test_reconstruct.py",
    "tests/test_demo.py",
    "tests/recon/test_decomposition.py",
    "tests/recon/test_resume_threads.py",
    "tests/acquire/test_recorder.py",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    rank = {name: i for i, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.relative_to(ROOT).as_posix(), len(rank)))


CHROMIUM = Path("/usr/bin/chromium")  # Debian's (scripts/setup.sh installs it where it can)


@pytest.fixture
def screenshot(tmp_path):
    """shoot(page, width, height) -> the page as headless Chromium draws it (BGR), its scripts
    and WebGL (software) run; skips where no browser is installed."""
    import subprocess

    import cv2

    if not CHROMIUM.exists():
        pytest.skip(f"no browser at {CHROMIUM} (apt-get install chromium) to load the page")

    def shoot(page: Path, width: int, height: int) -> np.ndarray:
        shot = tmp_path / f"{page.stem}.png"
        flags = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run"]
        flags += ["--disable-background-networking", "--disable-component-update"]
        flags += ["--disable-sync", f"--user-data-dir={tmp_path / 'profile'}"]
        # WebGL on the CPU (SwiftShader); the page's scripts and image loads given time
        flags += ["--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
        flags += ["--virtual-time-budget=10000"]
        flags += [f"--screenshot={shot}", f"--window-size={width},{height}"]
        run = subprocess.run(
            [str(CHROMIUM), *flags, page.resolve().as_uri()],
            capture_output=True,
            text=True,
            timeout=180,
            check=False,
        )
        image = cv2.imread(str(shot))
        assert image is not None, f"no screenshot: {run.stderr[-2000:]}"
        return image

    return shoot


@pytest.fixture(scope="session")
def interrupt_at():
    """interrupt_at(step, stage) -> a reconstruction's progress callback that presses Ctrl-C
    once ``stage``'s ("radiance" or "material") step ``step`` is done."""

    def at(step: int, stage: str):
        def progress(done: int, total: int, status: str = "") -> None:
            if done == step and status.startswith("material") == (stage == "material"):
                raise KeyboardInterrupt

        return progress

    return at


@pytest.fixture(scope="session")
def metrics_without_times():
    """read(OUT) -> OUT/metrics.json without the times it took: what repeats bit for bit."""

    def drop(x):
        if isinstance(x, dict):
            return {k: drop(v) for k, v in x.items() if "seconds" not in k}
        return [drop(v) for v in x] if isinstance(x, list) else x

    return lambda out: drop(json.loads((Path(out) / "metrics.json").read_text()))


@pytest.fixture(scope="session")
def davis346_calibrations() -> Path:
    """Real DAVIS346 calibrations (ROS camera_info, Kalibr and VINS files; tests/data has
    copies and where they come from)."""
    return Path(__file__).resolve().parent / "data" / "davis346-calibrations"


@pytest.fixture(scope="session")
def nerf_synthetic_mic() -> Path:
    """NeRF-Synthetic's mic as its release lays it out (Blender renders, CC-0)."""
    folder = SHARED / "data" / "nerf-synthetic-mic"
    if not (folder / "transforms_train.json").exists():
        pytest.skip(f"NeRF-Synthetic mic is not at {folder} (set EVCAP_SHARED)")
    return folder


@pytest.fixture(scope="session")
def method_summary() -> str:
    """reference/method.md (the reconstruction method's equations and constants), its lines
    joined."""
    path = SHARED / "reference" / "method.md"
    if not path.exists():
        pytest.skip(f"the method's summary is not at {path} (set EVCAP_SHARED)")
    return " ".join(path.read_text().split())


@pytest.fixture(scope="session")
def sample_aedat4() -> Path:
    if not SAMPLE_AEDAT4.exists():
        pytest.skip(f"the real DAVIS346 sample is not at {SAMPLE_AEDAT4} (set EVCAP_SHARED)")
    return SAMPLE_AEDAT4


TINY = """
[scene]
name = "tiny"
seed = {seed}
{scene_extra}

[sensor]
color_filter = "{color_filter}"
contrast_threshold = 0.2
{effects}

[camera]
width = {width}
height = {height}
fx = {fx}

[trajectory]
{trajectory}

[lighting]
{lighting}

[materials.paint]
procedural = {{ kind = "checker", scale = 6, colors = [[0.8, 0.25, 0.1], [0.9, 0.85, 0.6]] }}
roughness = 0.4

{objects}

{extra}
"""

ORBIT = """kind = "orbit"
radius = 2.2
height = 0.6
degrees = 40.0
duration_s = 0.3"""

SPHERE = """[[objects]]
type = "sphere"
radius = 0.6
material = "paint"
"""


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """Write a small scene file; keyword arguments replace parts of it."""

    def make(**kw) -> Path:
        values = {
            "seed": 3,
            "scene_extra": "",
            "color_filter": "RGBG",
            "effects": "",
            "width": 48,
            "height": 36,
            "fx": 45.0,
            "trajectory": ORBIT,
            "lighting": 'environment = "sky"',
            "objects": SPHERE,
            "extra": "[gt]\nfps = 10\ntest_views = 2",
        }
        values.update(kw)
        path = tmp_path_factory.mktemp("scene") / "scene.toml"
        path.write_text(textwrap.dedent(TINY.format(**values)))
        return path

    return make


def _write_nerf_dataset(
    tiny_scene,
    folder,
    views=9,
    degrees=24.0,
    height=0.6,
    name="transforms",
    depth=True,
    images=None,
):
    """Renders of a small scene along an orbit, written as a NeRF-Synthetic dataset: RGBA
    images (alpha: the sphere), depth renders in the release's encoding (1 - distance / 8).
    ``images``: the images' path under ``folder`` without the view's number (``test/r_``)."""
    import cv2

    from evcap.sim.from_images import BLENDER_TO_OPENCV
    from evcap.sim.render import Renderer
    from evcap.sim.scene import load_scene
    from evcap.sim.trajectory import Trajectory

    scene = load_scene(
        tiny_scene(
            trajectory=f'kind = "orbit"\nradius = 2.2\nheight = {height}\n'
            f"degrees = {degrees}\nduration_s = 1.0"
        )
    )
    r, traj = Renderer(scene), Trajectory(scene.trajectory)
    frames = []
    images = images or f"{name}_"
    (folder / images).parent.mkdir(parents=True, exist_ok=True)
    truth = []
    for k in range(views):
        T = traj.pose(k / (views - 1))
        full = r.render_full(T)
        truth.append(full)
        img = np.clip(full["radiance"], 0, 1)
        srgb = np.where(img <= 0.0031308, img * 12.92, 1.055 * img ** (1 / 2.4) - 0.055)
        alpha = (full["depth"] > 0)[..., None]
        rgba = np.concatenate([srgb[..., ::-1], alpha], -1)
        cv2.imwrite(str(folder / f"{images}{k}.png"), (rgba * 255 + 0.5).astype(np.uint8))
        yy, xx = np.mgrid[0:36, 0:48]
        ray = np.sqrt(((xx - 23.5) / 45.0) ** 2 + ((yy - 17.5) / 45.0) ** 2 + 1)
        v = np.where(full["depth"] > 0, 1 - full["depth"] * ray / 8, 0)
        if depth:
            cv2.imwrite(
                str(folder / f"{images}{k}_depth_0186.png"), np.round(v * 255).astype(np.uint8)
            )
        frames.append(
            {"file_path": f"./{images}{k}", "transform_matrix": (T @ BLENDER_TO_OPENCV).tolist()}
        )
    angle = 2 * np.arctan(48 / 2 / 45.0)
    path = folder / f"{name}.json"
    path.write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    return path, truth


@pytest.fixture(scope="session")
def write_nerf_dataset(tiny_scene):
    """write_nerf_dataset(folder, ...): renders of the tiny scene along an orbit, written as a
    NeRF-Synthetic dataset; (the transforms file, each view's truth)."""
    return functools.partial(_write_nerf_dataset, tiny_scene)


@pytest.fixture(scope="session")
def nerf_scene(write_nerf_dataset, tmp_path_factory) -> Path:
    """A tiny scene laid out as the NeRF-Synthetic release: an orbit in transforms_test.json
    (test/r_*.png with depth renders), ten other views in transforms_train.json."""
    data = tmp_path_factory.mktemp("nerf") / "nerf-synthetic-sphere"
    write_nerf_dataset(data, name="transforms_test", images="test/r_")
    write_nerf_dataset(
        data, views=10, height=0.9, name="transforms_train", depth=False, images="train/r_"
    )
    return data


# A calibration recording (tests/calib, tests/poses): a 5 x 4 ChArUco board,
# "charuco:5x4:0.04:0.03:DICT_4X4_50" on the command line.
BOARD_OBJECTS = """[[objects]]
type = "charuco"
center = [0.0, 0.0, 0.0]
rotation_deg = [90.0, 0.0, 0.0]
squares_x = 5
squares_y = 4
square_length = 0.04
marker_length = 0.03
dictionary = "DICT_4X4_50"
"""
BOARD_PATH = """kind = "handheld"
start = [-0.12, -0.24, 0.08]
end = [0.12, -0.22, -0.06]
look_at = [0.0, 0.0, 0.0]
shake_units = 0.005
shake_deg = 3.0
shake_hz = 1.0
duration_s = 1.2"""
BOARD_EFFECTS = """[sensor.effects]
threshold_spread = { sigma = 0.03 }
background_activity = { rate_hz = 0.2 }
hot_pixels = { count = 8, rate_hz = 300.0 }
refractory = { period_us = 100 }"""
# the board's shading is not graded: one specular sample per pixel, not 12 x 12, makes the
# fixture's simulation several times faster (from 4 x 4: 110 -> 69 s, the tests unchanged)
BOARD_LIGHT = (
    'environment = "sky"\nsky = { zenith = [0.8, 0.8, 0.8], horizon = [0.8, 0.8, 0.8], '
    "ground = [0.6, 0.6, 0.6] }\nspecular_side = 1"
)


@pytest.fixture(scope="session")
def board_session(tiny_scene, tmp_path_factory):
    """A 1.2 s hand-held pass over a 5 x 4 board, 200 x 150 pixels, with frames and noise."""
    scene = tiny_scene(
        objects=BOARD_OBJECTS,
        width=200,
        height=150,
        fx=160.0,
        trajectory=BOARD_PATH,
        lighting=BOARD_LIGHT,
        effects=BOARD_EFFECTS,
        extra="[aps]\nfps = 25\nexposure_us = 3000\n[gt]\nfps = 5\ntest_views = 0",
    )
    from evcap.sim.scene import load_scene
    from evcap.sim.simulate import simulate

    path = tmp_path_factory.mktemp("calib") / "board.h5"
    simulate(load_scene(scene), path)
    return path


# a reconstruction folder whose fields are the truth's (tests/recon/test_mesh_export.py, the
# mesh bench's tiny run): Gaussians sampled over tiny_scene's sphere (radius 0.6 at the origin)
# as stage I, with a base color and roughness known at every point as stage II
def surface_base_color(points: np.ndarray) -> np.ndarray:
    """A smooth color over the sphere."""
    d = points / 0.6
    return np.stack([0.5 + 0.4 * d[..., 0], 0.5 + 0.4 * d[..., 2], 0.3 + 0.2 * d[..., 1]], -1)


def surface_roughness(points: np.ndarray) -> np.ndarray:
    return 0.5 + 0.3 * points[..., 2] / 0.6


@pytest.fixture(scope="session")
def surface_material():
    """(base color, roughness) of surface_reconstruction at points on its sphere."""
    return surface_base_color, surface_roughness


@pytest.fixture(scope="session")
def surface_reconstruction(tiny_scene, tmp_path_factory) -> Path:
    import torch

    from evcap.recon.export import save_checkpoint, save_material_checkpoint
    from evcap.recon.material.shading import MIN_ROUGHNESS
    from evcap.recon.material.stage import MaterialField
    from evcap.recon.radiance.stage import RadianceField
    from evcap.recon.scene.gaussians import Background, Gaussians
    from evcap.records.reconstruction_folder import ReconstructionFolder
    from evcap.sim.meshes import build_mesh, sample_surface
    from evcap.sim.scene import load_scene
    from evcap.sim.simulate import simulate

    folder = tmp_path_factory.mktemp("surface")
    scene = load_scene(tiny_scene())
    simulate(scene, folder / "s.h5")
    points, normals, spacing = sample_surface(build_mesh(scene)[0], 6000)
    g = Gaussians.on_surface(points, normals, spacing, sh_degree=0)
    out = ReconstructionFolder(folder / "recon")
    out.checkpoint("radiance").parent.mkdir(parents=True)
    save_checkpoint(RadianceField(g, Background(8)), {}, out.checkpoint("radiance"))
    field = MaterialField(g, Background(8), torch.as_tensor(normals).float(), None, False)
    with torch.no_grad():
        field.base_logits.copy_(torch.logit(torch.as_tensor(surface_base_color(points)).float()))
        r = torch.as_tensor(surface_roughness(points)).float()
        field.roughness_logits.copy_(torch.logit((r - MIN_ROUGHNESS) / (1 - MIN_ROUGHNESS)))
    save_material_checkpoint(field, out.checkpoint("material"))
    out.write_config({"reconstruct": {"session": str(folder / "s.h5")}})
    return out.root
