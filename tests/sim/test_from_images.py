"""Events from posed images (NeRF-Synthetic layout), with flow-interpolated frames."""

import json

import numpy as np

from evcap.session import Session
from evcap.sim.from_images import BLENDER_TO_OPENCV, interpolate, simulate_from_images
from evcap.sim.render import Renderer
from evcap.sim.scene import load_scene
from evcap.sim.sensor import ChannelMap
from evcap.sim.trajectory import Trajectory


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


def write_dataset(folder, tiny_scene, views=9):
    """Renders of a small scene along an orbit, written as a NeRF-Synthetic dataset."""
    import cv2

    scene = load_scene(
        tiny_scene(
            trajectory='kind = "orbit"\nradius = 2.2\nheight = 0.6\n'
            "degrees = 24.0\nduration_s = 1.0"
        )
    )
    r, traj = Renderer(scene), Trajectory(scene.trajectory)
    frames = []
    folder.mkdir()
    for k in range(views):
        T = traj.pose(k / (views - 1))
        full = r.render_full(T)
        img = np.clip(full["radiance"], 0, 1)
        srgb = np.where(img <= 0.0031308, img * 12.92, 1.055 * img ** (1 / 2.4) - 0.055)
        cv2.imwrite(str(folder / f"r_{k}.png"), (srgb[..., ::-1] * 255 + 0.5).astype(np.uint8))
        depth = np.where(np.isfinite(full["depth"]), full["depth"] / 4.0, 1.0)
        cv2.imwrite(
            str(folder / f"r_{k}_depth_0000.png"), (np.clip(depth, 0, 1) * 255).astype(np.uint8)
        )
        frames.append(
            {"file_path": f"./r_{k}", "transform_matrix": (T @ BLENDER_TO_OPENCV).tolist()}
        )
    angle = 2 * np.arctan(48 / 2 / 45.0)
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    return folder / "transforms.json"


def test_events_from_images(tiny_scene, tmp_path):
    transforms = write_dataset(tmp_path / "data", tiny_scene)
    out = tmp_path / "s.h5"
    n = simulate_from_images(transforms, out, fps=10)
    assert n > 200
    with Session.open(out) as s:
        g = s.group("gt")
        assert len(g["t"]) == 8  # every 8th image is held out
        assert g["test_radiance"].shape == (1, 36, 48, 3)
        # the dataset's depth images come along as stored; it has no normal images
        assert g["depth_image"].shape == (8, 36, 48)
        assert g["test_depth_image"].shape == (1, 36, 48)
        assert "normal_image" not in g
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
