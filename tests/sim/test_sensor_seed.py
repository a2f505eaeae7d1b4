"""[sensor] seed: scenes giving the same one simulate the same physical sensor (per-pixel
thresholds, background-activity rates, hot pixels); without it the sensor comes from the
scene's seed, as it always did."""

import numpy as np
import pytest

from evcap.errors import InputError
from evcap.sim.events import PixelArray
from evcap.sim.scene import load_scene
from evcap.sim.simulate import Simulator

EFFECTS = """[sensor.effects]
threshold_spread = { sigma = 0.03 }
background_activity = { rate_hz = 0.1 }
hot_pixels = { count = 12, rate_hz = 200.0 }"""


def sensor(sim_or_pixels):
    p = getattr(sim_or_pixels, "pixels", sim_or_pixels)
    return p.con, p.coff, p.leak, np.sort(p.hot)


def test_the_same_sensor_seed_makes_the_same_sensor(tiny_scene):
    with_seed = EFFECTS.replace("[sensor.effects]", "seed = 346\n\n[sensor.effects]")
    a = Simulator(load_scene(tiny_scene(seed=3, effects=with_seed)))
    b = Simulator(load_scene(tiny_scene(seed=4, effects=with_seed)))
    for x, y in zip(sensor(a), sensor(b), strict=True):
        np.testing.assert_array_equal(x, y)
    # ...while the noise over time still comes from each scene's seed
    assert a.rng.random() != b.rng.random()
    other = Simulator(load_scene(tiny_scene(seed=3, effects=with_seed.replace("346", "347"))))
    assert not np.array_equal(sensor(a)[0], sensor(other)[0])


def test_without_it_the_sensor_comes_from_the_scene_seed(tiny_scene):
    scene = load_scene(tiny_scene(seed=3, effects=EFFECTS))
    assert scene.sensor.seed is None
    sim = Simulator(scene)
    n = sim.camera.width * sim.camera.height
    before = PixelArray(n, 0.2, 0.2, scene.sensor.effects, np.random.default_rng(3))
    for x, y in zip(sensor(sim), sensor(before), strict=True):
        np.testing.assert_array_equal(x, y)
    assert sim.pixels.rng is sim.rng


def test_a_sensor_seed_must_be_an_integer(tiny_scene):
    with pytest.raises(InputError, match="seed must be a whole number"):
        load_scene(tiny_scene(effects='seed = "a"'))
