import os
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# Compiled loops check their indexing under test: a bug raises IndexError, not a segfault.
# numba's cache does not tell such builds from the normal ones: keep them apart.
os.environ.setdefault("NUMBA_BOUNDSCHECK", "1")
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-test-cache"))

SHARED = Path(os.environ.get("EVCAP_SHARED", ROOT.parent / "shared"))
SAMPLE_AEDAT4 = SHARED / "data" / "davis346-sample" / "davis346_test_data.aedat4"


@pytest.fixture(scope="session")
def davis346_calibrations() -> Path:
    """Real DAVIS346 calibrations (ROS camera_info and Kalibr files)."""
    folder = SHARED / "data" / "davis346-calibrations"
    if not folder.exists():
        pytest.skip(f"the real DAVIS346 calibrations are not at {folder} (set EVCAP_SHARED)")
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
