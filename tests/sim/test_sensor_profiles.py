"""Named sensors: a scene's [sensor] profile and `evcap simulate --sensor`."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from evcap.errors import InputError
from evcap.records import Calibration
from evcap.session import Session
from evcap.sim.scene import load_scene, with_sensor_profile
from evcap.sim.sensor_profiles import PROFILES, sensor_profile

DAVIS346 = PROFILES["davis346"]


def test_the_davis346_profile_holds_the_datasheet_thresholds():
    assert DAVIS346.threshold_on == pytest.approx(math.log(1.143))
    assert DAVIS346.threshold_off == pytest.approx(math.log(1.225))
    assert set(DAVIS346.effects) == {
        "threshold_spread",
        "background_activity",
        "shot_noise",
        "refractory",
        "bandwidth",
        "footprint",
    }


def test_a_scene_takes_a_profile_and_its_own_keys_win(tiny_scene):
    effects = 'profile = "davis346"\n[sensor.effects]\nrefractory = { period_us = 100 }'
    scene = load_scene(tiny_scene(effects=effects))
    s = scene.sensor
    assert s.profile == "davis346"
    assert s.threshold_on == s.threshold_off == 0.2  # the scene's contrast_threshold
    assert s.effects["refractory"] == {"period_us": 100}  # the scene's
    assert s.effects["bandwidth"] == DAVIS346.effects["bandwidth"]  # the profile's
    assert DAVIS346.effects["refractory"] == {"period_us": 500}  # not changed by the scene


def test_a_profile_replaces_a_scenes_sensor(tiny_scene):
    scene = load_scene(tiny_scene(effects="[sensor.effects]\ndropped = { probability = 0.5 }"))
    seen = with_sensor_profile(scene, "davis346").sensor
    assert (seen.threshold_on, seen.threshold_off) == (
        DAVIS346.threshold_on,
        DAVIS346.threshold_off,
    )
    assert seen.effects == DAVIS346.effects and seen.profile == "davis346"
    assert seen.color_filter == scene.sensor.color_filter
    ideal = with_sensor_profile(scene, "ideal").sensor
    assert ideal.effects == {} and ideal.threshold_on == 0.2


def test_an_unknown_profile_names_the_known_ones(tiny_scene):
    with pytest.raises(InputError, match="davis346"):
        sensor_profile("davis347")
    with pytest.raises(InputError, match="unknown sensor profile 'x'"):
        load_scene(tiny_scene(effects='profile = "x"'))


def test_simulate_with_the_davis346_sensor(tiny_scene, tmp_path):
    """`evcap simulate --sensor davis346`: the profile's thresholds, spread over the pixels,
    and effects, in the session's calibration and attributes."""
    out = tmp_path / "s.h5"
    command = [sys.executable, "-m", "evcap", "simulate", str(tiny_scene()), "-o", str(out)]
    done = subprocess.run([*command, "--sensor", "davis346"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    with Session.open(out) as s:
        cal = Calibration.read(s)
        assert s.attrs["sensor_profile"] == "davis346"
        assert json.loads(s.attrs["effects"]) == DAVIS346.effects
        assert s.n_events > 100
    on, off = cal.thresholds()
    assert np.mean(on) == pytest.approx(DAVIS346.threshold_on, abs=0.004)
    assert np.mean(off) == pytest.approx(DAVIS346.threshold_off, abs=0.004)
    assert np.std(on) == pytest.approx(0.03, rel=0.15)
    assert cal.background_activity_hz == 0.1 and cal.refractory_period_us == 500
    bad = subprocess.run([*command, "--sensor", "nope", "-f"], capture_output=True, text=True)
    assert bad.returncode != 0 and "known: ideal, davis346" in bad.stderr
