"""Events from posed images (NeRF-Synthetic layout), with flow-interpolated frames."""

import json
import subprocess
import sys

import numpy as np

from evcap.session import Session
from evcap.sim.from_images import interpolate, simulate_from_images
from evcap.sim.sensor import ChannelMap


def test_flow_interpolation_follows_the_motion():
    rng = np.random.default_rng(0)
    base = np.kron(rng.random((12, 16)), np.ones((8, 8)))  # 96 x 128 blocks
    base = np.stack([base, base * 0.8, base * 0.5], -1) * 0.8 + 0.1
    a, b = base, np.roll(base, 6, axis=1)  # everything moves 6 px right
    frames = interpolate(a, b, max_step_px=1.0)
    assert 5 <= len(frames) <= 7  # 6 px in steps of at most 1 px (the flow's tail: a little more)
    s, mid = min(frames, key=lambda f: abs(f[0] - 0.5))
    truth = np.roll(base, 3, axis=1) if s == 0.5 else None
    if truth is None:  # compare with the shift the fraction calls for
        shift = 6 * s
        lo = np.roll(base, int(np.floor(shift)), axis=1)
        truth = lo + (np.roll(base, int(np.floor(shift)) + 1, axis=1) - lo) * (shift % 1)
    inner = (slice(10, -10), slice(16, -16))
    assert np.abs(mid[inner] - truth[inner]).mean() < 0.02


def test_events_from_images(write_nerf_dataset, tmp_path):
    transforms, truth = write_nerf_dataset(tmp_path / "data")
    out = tmp_path / "s.h5"
    n = simulate_from_images(transforms, out, fps=10)
    assert n > 200
    with Session.open(out) as s:
        g = s.group("gt")
        assert len(g["t"]) == 8  # every 8th image is held out
        assert g["test_radiance"].shape == (1, 36, 48, 3)
        # the object's mask from the alpha, depth decoded from the depth renders
        held = truth[7]
        np.testing.assert_array_equal(g["test_mask"][0], held["depth"] > 0)
        depth = g["test_depth"][0]
        assert ((depth > 0) == (held["depth"] > 0)).all()
        err = np.abs(depth - held["depth"])[depth > 0]
        assert err.max() < 0.6 * 8 / 255  # half an 8-bit step, and the PNG's rounding
        np.testing.assert_allclose(g["K"][0, 0], 45.0, rtol=1e-6)
        # camera poses back in OpenCV axes: looking at the object at the origin
        T = g["T_world_cam"][0]
        assert (T[:3, :3].T @ -T[:3, 3])[2] > 0
        cm = ChannelMap(48, 36, "RGBG")
        t, rad = g["t"][:], g["radiance"][:].astype(np.float64)
        ev = s.events()
        for a in range(len(t) - 1):
            e = ev.time_slice(int(t[a]), int(t[a + 1]))
            px = e.y.astype(np.int64) * 48 + e.x
            change = cm.log(rad[a + 1].reshape(-1, 3), 1e-3) - cm.log(rad[a].reshape(-1, 3), 1e-3)
            counted = 0.2 * (
                np.bincount(px[e.p == 1], minlength=48 * 36)
                - np.bincount(px[e.p == 0], minlength=48 * 36)
            )
            assert np.abs(change - counted).max() < 0.4


def angle_deg(a, b, where):
    cos = (a[where] * b[where]).sum(-1) / np.linalg.norm(b[where], axis=-1)
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def test_normals_from_the_depth_renders(write_nerf_dataset, tmp_path):
    transforms, truth = write_nerf_dataset(tmp_path / "data")
    simulate_from_images(transforms, tmp_path / "s.h5", fps=10)
    with Session.open(tmp_path / "s.h5") as s:
        g = s.group("gt")
        normal = g["normal"][0]
    known = np.linalg.norm(normal, axis=-1) > 0.5
    assert known.sum() > 0.3 * (truth[0]["depth"] > 0).sum()  # all but the rim
    err = angle_deg(normal, truth[0]["normal"], known)
    assert np.median(err) < 8  # 8-bit depth over a 48-pixel sphere


def test_held_out_views_from_another_file(write_nerf_dataset, tmp_path):
    path, _ = write_nerf_dataset(tmp_path / "data")
    other, truth = write_nerf_dataset(
        tmp_path / "data", views=3, degrees=20.0, height=0.9, name="other", depth=False
    )
    out = tmp_path / "s.h5"
    simulate_from_images(path, out, held_out=other, fps=10, background=0.0)
    with Session.open(out) as s:
        g = s.group("gt")
        assert len(g["t"]) == 9  # every view of the path makes events
        assert g["test_radiance"].shape == (3, 36, 48, 3)
        assert (g["test_radiance"][0][~g["test_mask"][0]] == 0).all()  # over black
        # the held-out views have no depth renders: their depth and normals come from the
        # path's, where the path saw the surface
        depth, normal = g["test_depth"][1], g["test_normal"][1]
    known = depth > 0
    assert known.sum() > 0.5 * (truth[1]["depth"] > 0).sum()
    rel = (np.abs(depth - truth[1]["depth"]) / truth[1]["depth"].clip(1e-6))[known]
    assert np.median(rel) < 0.025  # about a pixel's slope: 48 pixels span 1 m here
    known = np.linalg.norm(normal, axis=-1) > 0.5
    assert known.sum() > 0.2 * (truth[1]["depth"] > 0).sum()  # not within 3 px of an edge
    assert np.median(angle_deg(normal, truth[1]["normal"], known)) < 10


def test_a_scene_laid_out_as_the_release_through_the_commands(write_nerf_dataset, tmp_path):
    """What a user runs on any NeRF-Synthetic scene: the orbit of transforms_test.json as the
    path, views of transforms_train.json held out, then stage I scored on the object."""
    data = tmp_path / "nerf-synthetic-sphere"
    write_nerf_dataset(data, name="transforms_test", images="test/r_")
    write_nerf_dataset(
        data,
        views=2,
        height=0.9,
        name="transforms_train",
        depth=False,
        images="train/r_",
    )
    run = [sys.executable, "-m", "evcap"]
    session, out = tmp_path / "s.h5", tmp_path / "out"
    simulate = [*run, "simulate", "--from-images", str(data / "transforms_test.json")]
    simulate += ["--held-out", str(data / "transforms_train.json"), "-o", str(session)]
    r = subprocess.run(simulate, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    reconstruct = [*run, "reconstruct", str(session), "-o", str(out), "--preset", "tiny"]
    reconstruct += ["--stage", "radiance", "--iterations", "20"]
    r = subprocess.run(reconstruct, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["views"] == "held-out test views"
    for key in ("object_psnr_gain", "object_psnr_constant", "normal_mae_deg", "depth_rel_err"):
        assert np.isfinite(metrics[key]), key
