"""The plane the scene stands on, from the events' stereo points: found under a floor's marks
and the objects on it, not in a lone object's painted rings, not where there is no floor."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from evcap.errors import InputError
from evcap.recon.presets import preset
from evcap.recon.radiance.terms import stage_one_terms
from evcap.recon.scene.support_plane import (
    Plane,
    SupportConfig,
    on_plane,
    rays_meet,
    support_plane,
)
from evcap.recon.scene.volume import Ball
from evcap.sim.trajectory import look_at

W, H, F = 96, 72, 80.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]])


def cameras(height: float = 1.2) -> np.ndarray:
    """[20, 4, 4] a level arc of radius 2.5 at ``height``, looking at the origin."""
    angle = np.radians(np.linspace(-30, 30, 20))
    eyes = np.stack([2.5 * np.cos(angle), 2.5 * np.sin(angle), np.full(20, height)], 1)
    T = np.tile(np.eye(4), (20, 1, 1))
    T[:, :3, :3], T[:, :3, 3] = look_at(eyes, np.zeros(3)), eyes
    return T


def floor_scene(rng: np.random.Generator) -> np.ndarray:
    """A floor's marks (contact rings, a shadow's outline, a far edge) at z = 0, a ball's
    outline points above it, and a little noise."""
    u = rng.uniform(0, 2 * np.pi, 600)
    ring = np.stack([0.3 * np.cos(u) - 0.2, 0.3 * np.sin(u), np.zeros(600)], 1)
    edge = np.stack([np.full(300, -1.5), rng.uniform(-1.5, 1.5, 300), np.zeros(300)], 1)
    shadow = np.stack([rng.uniform(-1, 0, 300), np.full(300, 0.6), np.zeros(300)], 1)
    v = rng.normal(size=(1500, 3))
    ball = 0.4 * v / np.linalg.norm(v, axis=1, keepdims=True) + [0.3, -0.2, 0.4]
    points = np.concatenate([ring, edge, shadow, ball])
    return points + rng.normal(0, 0.005, points.shape)


def test_the_floor_under_the_objects_is_found():
    rng = np.random.default_rng(1)
    plane = support_plane(floor_scene(rng), cameras()[:, :3, 3], 2.0, SupportConfig())
    assert plane is not None
    # up, towards the cameras, on the marks: the ball's bottom, the only structure on the
    # cameras' side, does not tilt it (least squares over all it held: 0.69 deg, 1.1 cm)
    assert np.degrees(np.arccos(plane.normal[2])) < 0.2
    assert abs(plane.offset) < 0.005
    # its outline: from the far edge (x = -1.5) past the ball's foot on to under the cameras
    # (x from 2.17 to 2.5): the blank floor between makes no events
    corners = np.array([[-1.49, -1.4, 0], [-1.49, 1.4, 0], [0.7, 0, 0], [2.4, 0, 0]])
    assert plane.inside(corners).all()
    beyond = np.array([[-1.6, 0, 0], [2.6, 0, 0], [-0.2, 1.6, 0], [-0.5, -1.7, 0]])
    assert not plane.inside(beyond).any()
    assert Plane.from_state(plane.state()) == plane


def test_a_table_does_not_run_on_past_its_near_edge():
    """A table top ending at x = 0.5, the floor 0.7 m below it seen between its near edge and
    the cameras: the outline stops at the table's marks."""
    rng = np.random.default_rng(1)
    near = np.stack([np.full(300, 0.5), rng.uniform(-1.5, 1.5, 300), np.zeros(300)], 1)
    floor = np.stack([rng.uniform(0.8, 1.6, 60), rng.uniform(-1, 1, 60), np.full(60, -0.7)], 1)
    points = np.concatenate([floor_scene(rng), near, floor])
    plane = support_plane(points, cameras()[:, :3, 3], 2.0, SupportConfig())
    assert plane is not None and abs(plane.offset) < 0.02
    assert plane.inside(np.array([[-1.4, 0, 0], [0.45, 0, 0]])).all()
    assert not plane.inside(np.array([[0.6, 0, 0], [1.5, 0, 0]])).any()


def test_a_lone_object_stands_on_nothing():
    """A painted sphere's lines of latitude are planes too, with the sphere on both sides."""
    rng = np.random.default_rng(2)
    u = rng.uniform(0, 2 * np.pi, 3000)
    lat = np.radians(rng.choice([-40, -15, 10, 35], 3000))
    sphere = 0.5 * np.stack([np.cos(lat) * np.cos(u), np.cos(lat) * np.sin(u), np.sin(lat)], 1)
    assert support_plane(sphere, cameras()[:, :3, 3], 0.8, SupportConfig()) is None


def test_no_floor_no_plane():
    """The objects alone (the floor's marks left out): nothing to stand on."""
    rng = np.random.default_rng(3)
    points = floor_scene(rng)
    objects = points[points[:, 2] > 0.05]
    assert support_plane(objects, cameras()[:, :3, 3], 2.0, SupportConfig()) is None


def test_discs_lie_on_the_plane_inside_the_ball_in_view():
    plane, ball = Plane((0.0, 0.0, 1.0), 0.0), Ball((0.0, 0.0, 0.3), 2.0)
    T = cameras()
    points = on_plane(plane, ball, T, K, W, H, 400, np.random.default_rng(0))
    assert len(points) == 400
    assert np.abs(points[:, 2]).max() < 1e-9
    assert (np.linalg.norm(points - ball.center, axis=1) <= ball.radius).all()
    seen = np.zeros(len(points), bool)
    for pose in T:
        cam = (points - pose[:3, 3]) @ pose[:3, :3]
        x, y = F * cam[:, 0] / cam[:, 2] + W / 2, F * cam[:, 1] / cam[:, 2] + H / 2
        seen |= (cam[:, 2] > 0) & (x >= 0) & (x < W) & (y >= 0) & (y < H)
    assert seen.all()
    square = Plane((0.0, 0.0, 1.0), 0.0, ((-1.0, -1.0), (0.0, -1.0), (0.0, 0.0), (-1.0, 0.0)))
    within = on_plane(square, ball, T, K, W, H, 100, np.random.default_rng(0))
    assert len(within) == 100 and square.inside(within).all()
    missed = Plane((0.0, 0.0, 1.0), 5.0)  # above the ball
    assert len(on_plane(missed, ball, T, K, W, H, 10, np.random.default_rng(0))) == 0


def test_rays_meet_the_plane_only_inside_the_ball():
    plane, ball = Plane((0.0, 0.0, 1.0), 0.0), Ball((0.0, 0.0, 0.0), 1.0)
    origin = torch.tensor([0.0, 0.0, 2.0])
    directions = torch.nn.functional.normalize(
        torch.tensor([[[0.0, 0.0, -1.0], [0.49, 0.0, -1.0], [0.6, 0.0, -1.0], [0.0, 0.0, 1.0]]]),
        dim=-1,
    )
    # straight down, to 0.98 from the centre, to 1.2, and away from the plane
    assert rays_meet(plane, ball, directions, origin).tolist() == [[True, True, False, False]]
    # a support that reaches only to x = 0.5: the ray to 0.98 meets the plane beyond it
    u, v = plane.axes()
    square = np.array([[-1, -1, 0], [0.5, -1, 0], [0.5, 1, 0], [-1, 1, 0]], float)
    uv = np.stack([square @ u, square @ v], 1)
    around = np.arctan2(*(uv - uv.mean(0)).T[::-1])  # counter-clockwise in the plane's axes
    edged = Plane(plane.normal, plane.offset, tuple(map(tuple, uv[np.argsort(around)].tolist())))
    assert rays_meet(edged, ball, directions, origin).tolist() == [[True, False, False, False]]


def test_the_mean_alpha_asks_the_support_to_be_opaque_and_the_rest_clear():
    """init.on_support: the pixels whose rays meet the support inside its outline are asked
    for alpha 1, the others for alpha 0."""
    config = preset("tiny", {"stage1.init.on_support": 0.3, "stage1.loss.alpha.weight": 1}).stage1
    term = next(t for t in stage_one_terms(config, False) if t.name == "alpha")
    square = ((-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0))  # counter-clockwise
    viewmat = torch.eye(4)
    viewmat[2, 3] = -2.0  # a camera at z = 2, its axes the world's
    # straight down, down to x = 0.9 (on the support), to x = 1.5 (beyond it), upwards
    rays = torch.nn.functional.normalize(
        torch.tensor([[[0.0, 0, -2], [0.9, 0, -2], [1.5, 0, -2], [0.0, 0, 1]]]), dim=-1
    )
    data = SimpleNamespace(
        support=Plane((0.0, 0.0, 1.0), 0.0, square),
        bound=Ball((0.0, 0.0, 0.0), 3.0),
        viewmats=lambda: viewmat[None],
    )

    def loss(alpha: list[float]) -> float:
        x = SimpleNamespace(
            data=data,
            grid=SimpleNamespace(directions=lambda v: rays),
            frames=np.array([0]),
            renders=[SimpleNamespace(alpha=torch.tensor([alpha], dtype=torch.float32))],
        )
        return float(term.value(x))

    assert loss([1, 1, 0, 0]) == 0 and loss([0, 0, 1, 1]) == 1
    assert loss([0, 0, 0, 0]) == loss([1, 1, 1, 1]) == 0.5


def test_its_settings_are_checked():
    with pytest.raises(InputError, match="init.support"):
        SupportConfig(holds=0)
    with pytest.raises(InputError, match="init.support"):
        SupportConfig(tries=0)
    with pytest.raises(InputError, match="init.support"):
        SupportConfig(below_weight=-1)
