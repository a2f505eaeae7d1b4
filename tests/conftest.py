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
