from pathlib import Path

import numpy as np
import pytest

from evcap.errors import InputError, InputNotFoundError
from evcap.sim.camera import Camera, load_calibration
from evcap.sim.scene import load_scene

SCENES = Path(__file__).resolve().parents[2] / "sim" / "scenes"


@pytest.mark.parametrize("name", ["single_object", "multi_object", "charuco_board", "noisy_sensor"])
def test_example_scenes_load(name):
    # the scenes carry their camera's numbers: they load without ../shared (an installed evcap)
    scene = load_scene(SCENES / f"{name}.toml")
    assert scene.camera.width == 346 and scene.camera.distortion_model == "radtan"
    if name == "noisy_sensor":
        assert set(scene.sensor.effects) == {
            "threshold_spread",
            "background_activity",
            "shot_noise",
            "hot_pixels",
            "refractory",
            "bandwidth",
            "timestamp_jitter",
            "dropped",
        }


OBJ = '[[objects]]\ntype = "sphere"\n{}'
EFFECT = "[sensor.effects]\n{}"


@pytest.mark.parametrize(
    "change, message",
    [
        (
            {"effects": "[sensor.effects]\nsparkles = { rate_hz = 1.0 }"},
            "unknown effect 'sparkles'",
        ),
        ({"effects": "[sensor.effects]\nshot_noise = { rate = 1.0 }"}, "missing rate_hz"),
        ({"objects": '[[objects]]\ntype = "cone"'}, "type must be one of"),
        ({"objects": '[[objects]]\ntype = "sphere"\nmaterial = "gold"'}, "unknown material 'gold'"),
        ({"objects": '[[objects]]\ntype = "mesh"\npath = "nope.obj"'}, "not found"),
        ({"trajectory": 'kind = "spiral"'}, "kind must be orbit"),
        ({"trajectory": 'kind = "orbit"\nradius = 2.0\nspeed = 3.0'}, "unknown key.*speed"),
        ({"scene_extra": "colour = 1"}, "unknown key"),
        ({"fx": -3.0}, "fx must be positive"),
        # values of the wrong type or range, and typos, each named (they were tracebacks, or
        # taken silently: a typo'd key fell back to its default)
        ({"width": -64}, "width must be positive"),
        ({"objects": OBJ.format("center = [0.0, 1.0]")}, "center must be 3 numbers"),
        ({"objects": OBJ.format('radius = "big"')}, "radius must be a number"),
        ({"objects": OBJ.format("radiu = 0.5")}, "unknown key.*radiu"),
        ({"objects": OBJ.format("segments = 0")}, "segments must be positive"),
        ({"lighting": "samples = 0"}, "samples must be positive"),
        ({"lighting": "specular_side = 0"}, "specular_side must be positive"),
        ({"effects": EFFECT.format("dropped = { probability = 2.0 }")}, "probability must be"),
        ({"effects": EFFECT.format("threshold_spread = { sigma = -1.0 }")}, "sigma must be 0"),
        ({"scene_extra": "max_step_px = 0.0"}, "max_step_px must be positive"),
        ({"fx": '45.0\ncalibration_camera = "cam1"'}, "calibration_camera goes with calibration"),
        ({"extra": "[gt]\ntest_views = -1"}, "test_views must be 0 or more"),
    ],
)
def test_scene_errors_name_the_problem(tiny_scene, change, message):
    path = tiny_scene(**change)
    with pytest.raises((InputError, InputNotFoundError), match=message):
        load_scene(path)


def test_real_calibrations_and_distortion_round_trip(davis346_calibrations):
    for name in (
        "esvo_hkust_davis346_left.yaml",
        "esvo_upenn_davis346_left.yaml",
        "arclab_esvio_kalibr_camchain-imucam.yaml",
        "arclab_iros2022_davis346.yaml",
    ):
        cam = Camera(load_calibration(davis346_calibrations / name))
        rays = cam.rays()
        uv = cam.project(rays * 2.0)
        v, u = np.mgrid[0 : cam.height, 0 : cam.width]
        np.testing.assert_allclose(uv, np.stack([u.ravel(), v.ravel()], 1), atol=1e-6)
        assert 220 < cam.K[0, 0] < 265 and (cam.width, cam.height) == (346, 260)
    with pytest.raises(InputError, match="Kalibr IMU calibration.*no camera in it"):
        load_calibration(davis346_calibrations / "arclab_esvio_kalibr_imu.yaml")
    right = load_calibration(
        davis346_calibrations / "arclab_esvio_kalibr_stereo_camchain.yaml", "cam1"
    )
    assert right.fx == 258.61441518089174
