"""Whole simulations of tiny scenes: the events obey the model, the effects show their
statistics, the session holds its ground truth, and the fixture replays through the driver."""

import json
import subprocess
import sys

import numpy as np
import pytest

from evcap.session import Session
from evcap.sim.scene import load_scene
from evcap.sim.sensor import ChannelMap
from evcap.sim.simulate import simulate

STATIC = 'kind = "static"\nposition = [2.2, 0.0, 0.6]\nlookat = [0, 0, 0]'.replace(
    "lookat", "look_at"
)


def residuals(path, use_pixel_thresholds=True):
    """Per pixel, between consecutive ground-truth frames: the change of its log signal minus
    what its events add up to."""
    out = []
    with Session.open(path) as s:
        g = s.group("gt")
        t, rad = g["t"][:], g["radiance"][:].astype(np.float64)
        h, w = rad.shape[1:3]
        cm = ChannelMap(w, h, s.sensor.color_filter)
        con = g["threshold_on"][:].ravel() if use_pixel_thresholds else 0.2
        coff = g["threshold_off"][:].ravel() if use_pixel_thresholds else 0.2
        ev = s.events()
        for a in range(len(t) - 1):
            la, lb = (cm.log(rad[k].reshape(-1, 3), 1e-3) for k in (a, a + 1))
            e = ev.time_slice(int(t[a]), int(t[a + 1]))
            px = e.y.astype(np.int64) * w + e.x
            on = np.bincount(px[e.p == 1], minlength=h * w)
            off = np.bincount(px[e.p == 0], minlength=h * w)
            out.append((lb - la) - (con * on - coff * off))
    return np.array(out)


def test_events_obey_the_model(tiny_scene, tmp_path):
    out = tmp_path / "s.h5"
    stats = simulate(load_scene(tiny_scene()), out)
    assert stats.events > 500
    r = residuals(out)
    assert np.abs(r).max() < 2 * 0.2  # the sub-threshold residual at each end
    assert np.abs(r).mean() < 0.1


def test_threshold_noise_within_its_spread(tiny_scene, tmp_path):
    out = tmp_path / "s.h5"
    effects = "[sensor.effects]\nthreshold_spread = { sigma = 0.03 }"
    simulate(load_scene(tiny_scene(effects=effects)), out)
    with Session.open(out) as s:
        con, coff = s.group("gt")["threshold_on"][:], s.group("gt")["threshold_off"][:]
    assert np.abs(residuals(out)).max() < (con + coff).max()  # each pixel its own thresholds
    nominal = np.abs(residuals(out, use_pixel_thresholds=False))
    assert nominal.max() > 0.4  # with the nominal C the spread shows


def test_a_still_camera_without_noise_makes_no_events(tiny_scene, tmp_path):
    out = tmp_path / "s.h5"
    stats = simulate(load_scene(tiny_scene(trajectory=STATIC + "\nduration_s = 0.5")), out)
    assert stats.events == 0
    assert stats.key_renders <= 0.5e6 / 10_000 + 2  # the longest steps: nothing moves


def test_noise_effects_on_a_still_scene(tiny_scene, tmp_path):
    effects = (
        "[sensor.effects]\nshot_noise = { rate_hz = 20.0 }\n"
        "hot_pixels = { count = 3, rate_hz = 400.0 }\n"
        "background_activity = { rate_hz = 4.0 }"
    )
    out = tmp_path / "s.h5"
    simulate(load_scene(tiny_scene(effects=effects, trajectory=STATIC + "\nduration_s = 1.0")), out)
    with Session.open(out) as s:
        ev = s.events()
        hot = np.flatnonzero(s.group("calibration")["hot_pixels"][:].ravel())
    n_pix = 48 * 36
    px = ev.y.astype(np.int64) * 48 + ev.x
    counts = np.bincount(px, minlength=n_pix)
    assert len(hot) == 3 and (counts[hot] > 300).all()
    others = np.setdiff1d(np.arange(n_pix), hot)
    # shot noise (ON and OFF, 20 Hz) plus leak (ON, about 4 Hz) per pixel, over 1 s
    off = np.bincount(px[ev.p == 0], minlength=n_pix)[others].sum()
    on = np.bincount(px[ev.p == 1], minlength=n_pix)[others].sum()
    assert off == pytest.approx(10.0 * len(others), rel=0.1)
    assert on - off == pytest.approx(4.0 * 1.027 * len(others), rel=0.15)


def test_refractory_period_holds_in_a_simulation(tiny_scene, tmp_path):
    out = tmp_path / "s.h5"
    effects = "[sensor.effects]\nrefractory = { period_us = 2000 }"
    simulate(load_scene(tiny_scene(effects=effects)), out)
    with Session.open(out) as s:
        ev = s.events()
    px = ev.y.astype(np.int64) * 48 + ev.x
    order = np.lexsort((ev.t, px))
    gaps = np.diff(ev.t[order])[np.diff(px[order]) == 0]
    assert len(gaps) > 10 and gaps.min() >= 2000 - 1  # times are floored to whole us


def test_numerically_hard_scene(tiny_scene, tmp_path):
    """A black object in a black sky with a blinding sun, turning very fast."""
    lighting = (
        'environment = "sky"\nsky = { zenith = [0, 0, 0], horizon = [0, 0, 0], '
        "ground = [0, 0, 0], sun_direction = [1, 0, 1], sun_irradiance = 5000.0 }"
    )
    objects = (
        '[[objects]]\ntype = "sphere"\nradius = 0.6\nmaterial = "half"\n'
        '[materials.half]\nprocedural = { kind = "stripes", scale = 4, '
        "colors = [[0, 0, 0], [0.9, 0.9, 0.9]] }\nroughness = 0.3"
    )
    fast = 'kind = "orbit"\nradius = 2.2\nheight = 0.3\ndegrees = 90.0\nduration_s = 0.02'
    out = tmp_path / "s.h5"
    stats = simulate(
        load_scene(
            tiny_scene(
                lighting=lighting,
                objects=objects,
                trajectory=fast,
                extra="[gt]\nfps = 200\ntest_views = 0",
            )
        ),
        out,
    )
    assert stats.events > 100
    r = residuals(out)
    assert np.isfinite(r).all() and np.abs(r).max() < 2 * 0.2


def test_session_ground_truth_and_fixture(tiny_scene, tmp_path):
    extra = (
        "[aps]\nfps = 20\nexposure_us = 2000\n[imu]\nrate_hz = 400\n[gt]\nfps = 10\ntest_views = 3"
    )
    out, fixture = tmp_path / "s.h5", tmp_path / "fixture"
    simulate(load_scene(tiny_scene(extra=extra)), out, fixture=fixture)
    with Session.open(out) as s:
        g = s.group("gt")
        n = len(g["t"])
        assert n == 4  # 0, 0.1, 0.2, 0.3 s
        assert g["radiance"].shape == (n, 36, 48, 3) and g["radiance"].dtype == np.float32
        assert g["T_world_cam"].shape == (n, 4, 4) and g["K"].shape == (3, 3)
        for key in ("depth", "roughness"):
            assert g[key].shape == (n, 36, 48)
        assert g["normal"].shape == g["base_color"].shape == (n, 36, 48, 3)
        assert g["test_radiance"].shape == (3, 36, 48, 3)
        assert g["visibility"].shape == (n, 36, 48) and g["test_visibility"].shape == (3, 36, 48)
        assert g["indirect"].shape == (n, 36, 48, 3) and g["test_indirect"].shape == (3, 36, 48, 3)
        assert "shadow" in g.attrs["visibility"] and "bounce" in g.attrs["indirect"]
        hit = g["depth"][0] > 0
        np.testing.assert_allclose(np.linalg.norm(g["normal"][0][hit], axis=1), 1, atol=1e-4)
        assert (g["normal"][0][hit][:, 2] < 0.2).all()  # camera frame: facing the camera
        poses = s.group("poses")
        assert poses["T_world_cam"].shape[0] == len(poses["t"]) > 100
        c = s.group("calibration")
        np.testing.assert_allclose(c["K"][:], g["K"][:])
        assert c.attrs["source"] == "ground truth"
        frames, imu = s.frames(), s.imu()
        assert len(frames) == 6 and frames.data.max() <= 1023 and frames.exposure_us[0] == 2000
        assert len(imu) == 121
        # the orbit: 40 degrees in 0.3 s at radius 2.2 m, level: centripetal and gravity
        omega = np.deg2rad(40) / 0.3
        np.testing.assert_allclose(np.linalg.norm(imu.gyro, axis=1), omega, rtol=1e-3)
        expected = np.hypot(omega**2 * 2.2, 9.80665)
        np.testing.assert_allclose(np.linalg.norm(imu.accel, axis=1), expected, rtol=1e-3)
    assert json.loads((fixture / "expected.json").read_text())["events"] > 0
    rec = tmp_path / "rec.h5"
    r = subprocess.run(
        [sys.executable, "-m", "evcap", "record", "--device", f"replay:{fixture}", "-o", str(rec)],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    with Session.open(out) as a, Session.open(rec) as b:
        for k in "xytp":
            np.testing.assert_array_equal(getattr(a.events(), k), getattr(b.events(), k))
        np.testing.assert_array_equal(a.frames().data, b.frames().data)


def test_cli_simulate(tiny_scene, tmp_path):
    out = tmp_path / "s.h5"
    scene = tiny_scene()
    r = subprocess.run(
        [sys.executable, "-m", "evcap", "simulate", str(scene), "-o", str(out), "--seed", "9"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert "events" in r.stdout
    r = subprocess.run(
        [sys.executable, "-m", "evcap", "simulate", str(scene), "-o", str(out)],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "exists" in r.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text("[scene]\nname = 1\n")
    r = subprocess.run(
        [sys.executable, "-m", "evcap", "simulate", str(bad), "-o", str(tmp_path / "x.h5")],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr


def test_an_interrupted_simulation_leaves_nothing_half_made(tiny_scene, tmp_path):
    out = tmp_path / "s.h5"
    out.write_bytes(b"what was there")

    def ctrl_c(done, total):
        if done > 0.2 * total:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        simulate(load_scene(tiny_scene()), out, overwrite=True, progress=ctrl_c)
    assert out.read_bytes() == b"what was there"
    assert list(tmp_path.iterdir()) == [out]
    simulate(load_scene(tiny_scene()), out, overwrite=True)
    with Session.open(out) as s:
        assert {"gt", "poses", "calibration"} <= set(s.groups)


def test_image_speed_of_the_environment_and_of_the_orbited_object(tiny_scene):
    from evcap.sim.simulate import Simulator

    sim = Simulator(load_scene(tiny_scene()))
    a, b = sim._first_key(100_000.0), sim._first_key(102_000.0)
    speed = sim._image_speed(a, b).reshape(36, 48) * 1e6  # px/s
    turn = np.radians(40.0) / 0.3  # the orbit turns the camera this fast (rad/s)
    sky = a.depth.reshape(36, 48) == 0
    assert sky[0].all()  # the top row sees the sky: it moves with the camera's turn
    assert np.median(speed[0]) == pytest.approx(45.0 * turn, rel=0.15)
    # the sphere's point under the image centre, 0.6 in front of the point the orbit turns
    # about (its centre), moves as the camera's turn carries it
    across = turn * np.cos(np.arctan2(0.6, 2.2))  # the turn about an axis across the view
    distance = np.hypot(2.2, 0.6) - 0.6
    assert not sky[18, 24]
    assert np.median(speed[17:20, 23:26]) == pytest.approx(45.0 * across * 0.6 / distance, rel=0.1)


def test_a_footprint_spreads_the_events_of_an_edge(tiny_scene, tmp_path):
    """A point pixel fires an edge's events at once; with a footprint they spread (and the
    events stay in time order, though moved back by the footprint's delay)."""

    def bursts(effects: str) -> tuple[int, float]:
        out = tmp_path / f"{len(effects)}.h5"
        simulate(load_scene(tiny_scene(effects=effects)), out)
        with Session.open(out) as s:
            ev = s.events()
        assert (np.diff(ev.t) >= 0).all()
        px = ev.y.astype(np.int64) * 48 + ev.x
        order = np.lexsort((ev.t, px))
        same = (np.diff(px[order]) == 0) & (np.diff(ev.p[order].astype(int)) == 0)
        gaps = np.diff(ev.t[order])[same]
        return len(ev.t), float(np.mean(gaps < 20))

    n_point, close_point = bursts("")
    n_wide, close_wide = bursts("[sensor.effects]\nfootprint = { sigma_px = 0.3 }")
    # about the same changes (the footprint smooths the finest texture a little), spread
    assert n_wide == pytest.approx(n_point, rel=0.15)
    assert close_point > 0.3 and close_wide < 0.3 * close_point
