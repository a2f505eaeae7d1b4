"""The events' multi-view stereo: the structure a moving camera's events show, from its poses
alone; nothing where no event was, nothing at infinity."""

import numpy as np
import pytest

from evcap.events import Events
from evcap.recon.scene.event_stereo import StereoConfig, event_stereo
from evcap.recon.scene.optics import SensorOptics
from evcap.recon.scene.volume import foreground_ball, scene_volume
from evcap.records import Poses
from evcap.sim.trajectory import look_at

W, H, F = 96, 72, 80.0
RADIUS = 0.4  # the sphere's, at the origin
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]])


def optics() -> SensorOptics:
    thresholds = np.full((H, W), 0.2, np.float32)
    return SensorOptics(
        W, H, K, "none", np.zeros(4), "MONO", thresholds, thresholds, np.zeros((H, W), bool)
    )


def orbit(duration_us: int = 400_000) -> Poses:
    """A quarter turn at a distance of 2, rising as it goes, looking at the sphere."""
    t = np.linspace(0, duration_us, 41).astype(np.int64)
    angle = np.linspace(0, np.pi / 2, len(t))
    eyes = np.stack([2 * np.cos(angle), 2 * np.sin(angle), np.linspace(0.3, 0.8, len(t))], 1)
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, :3], T[:, :3, 3] = look_at(eyes, np.zeros(3)), eyes
    return Poses(t, T, "ground truth")


def edges() -> np.ndarray:
    """Points along the sphere's lines of latitude and longitude (a painted grid)."""
    u = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    out = []
    for lat in np.radians([-40, -15, 10, 35]):
        ring = [np.cos(lat) * np.cos(u), np.cos(lat) * np.sin(u), np.full_like(u, np.sin(lat))]
        out.append(np.stack(ring, 1))
    for lon in np.radians(np.arange(0, 360, 30)):
        v = u / 2 - np.pi / 2
        out.append(np.stack([np.cos(v) * np.cos(lon), np.cos(v) * np.sin(lon), np.sin(v)], 1))
    return RADIUS * np.concatenate(out)


def events_of(track: Poses, horizon: bool) -> Events:
    """An event wherever a grid point's image (the near side of the sphere) falls, every
    0.5 ms; with ``horizon``, also along a ring of directions at infinity (a horizon)."""
    rng = np.random.default_rng(0)
    points = edges()
    xs, ys, ts = [], [], []
    for t in range(0, int(track.end), 500):
        T = track.at(t)
        eye = T[:3, 3]
        facing = ((points - eye) * points).sum(1) < 0  # the near side
        cam = (points[facing] - eye) @ T[:3, :3]
        if horizon:
            az = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
            far = 1e6 * np.stack([np.cos(az), np.sin(az), np.full_like(az, -0.1)], 1)
            cam = np.concatenate([cam, far @ T[:3, :3]])
        cam = cam[cam[:, 2] > 0]
        u, v = cam[:, 0] / cam[:, 2] * F + W / 2, cam[:, 1] / cam[:, 2] * F + H / 2
        inside = (u >= 0) & (u < W - 0.5) & (v >= 0) & (v < H - 0.5)
        keep = inside & (rng.random(len(u)) < 0.3)  # an edge fires now and then
        xs.append(np.round(u[keep]))
        ys.append(np.round(v[keep]))
        ts.append(np.full(keep.sum(), t))
    x, y, t = (np.concatenate(a) for a in (xs, ys, ts))
    return Events(x.astype(np.int64), y.astype(np.int64), t, np.ones(len(t), np.uint8), W, H)


def stereo(horizon: bool):
    track = orbit()
    ev = events_of(track, horizon)
    volume = scene_volume(track.T_world_cam, K, W, H)
    found = event_stereo(ev.time_slice, (0, track.end), track, optics(), volume, StereoConfig())
    return found, volume


@pytest.mark.parametrize("horizon", [False, True])
def test_the_points_lie_on_the_painted_sphere(horizon):
    found, volume = stereo(horizon)
    off = np.abs(np.linalg.norm(found.points, axis=1) - RADIUS) / RADIUS
    assert found.views == StereoConfig().references
    assert len(found.points) > 500
    assert np.median(off) < 0.03
    assert np.percentile(off, 95) < 0.15
    # the horizon lies at infinity: none of it is taken for structure (one stray point in
    # several hundred, with it or without it)
    assert (np.linalg.norm(found.points, axis=1) > 1.25 * RADIUS).mean() < 0.01


def test_the_foreground_holds_the_sphere_and_not_the_horizon():
    """The ball the Gaussians are confined to, from the stereo's points: about where the
    cameras look (the sphere's centre), a little wider than the sphere, the horizon left out;
    with no structure, the ball the cameras converge on."""
    found, volume = stereo(horizon=True)
    ball = foreground_ball(volume, found.points)
    assert np.linalg.norm(ball.center) < 0.05 * RADIUS
    assert RADIUS <= ball.radius < 1.25 * RADIUS
    assert foreground_ball(volume, None).radius == volume.radius


def test_no_events_no_points():
    track = orbit()
    volume = scene_volume(track.T_world_cam, K, W, H)
    empty = Events.empty(W, H)
    found = event_stereo(empty.time_slice, (0, track.end), track, optics(), volume)
    assert len(found.points) == 0


def test_its_settings_are_checked():
    from evcap.errors import InputError

    with pytest.raises(InputError, match="references"):
        StereoConfig(references=1)
    with pytest.raises(InputError, match="witnesses"):
        StereoConfig(witnesses=0)
    with pytest.raises(InputError, match="aperture"):
        StereoConfig(aperture=1.0)


def test_an_edge_along_the_cameras_motion_is_left_out():
    """The aperture problem: with the camera moving sideways (along x), a horizontal edge moves
    along itself and says nothing of its depth; a vertical edge crosses the motion. A slanted
    edge is kept or not by the angle the setting names. A path that turns within the stretch
    (sideways, then up) crosses both."""
    from evcap.recon.scene.event_stereo import _across_the_motion

    peak = np.zeros((H, W), np.float32)
    peak[20, 10:40] = 1.0  # horizontal
    peak[10:60, 70] = 1.0  # vertical
    for i in range(30):  # 30 degrees off the horizontal
        peak[50 - round(i * np.tan(np.radians(30))), 10 + i] = 1.0
    sideways = np.linspace(-0.1, 0.1, 21)[:, None] * [1.0, 0, 0]
    kept = _across_the_motion(peak, sideways, K, 0.2)
    assert not kept[20, 15:35].any()
    assert kept[15:55, 70].all()
    assert kept[45, 20] and not _across_the_motion(peak, sideways, K, 0.6)[45, 20]
    # the camera moving up instead: the horizontal edge is the one kept
    upwards = _across_the_motion(peak, sideways[:, [1, 0, 2]], K, 0.2)
    assert upwards[20, 15:35].all() and not upwards[15:55, 70].any()
    turning = np.concatenate([sideways[:11], sideways[10:, [1, 0, 2]]])
    both = _across_the_motion(peak, turning, K, 0.2)
    assert both[20, 15:35].all() and both[15:55, 70].all()
