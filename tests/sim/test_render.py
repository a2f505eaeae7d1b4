"""The renderer against cases whose answer is known."""

import numpy as np
import pytest

from evcap.sim.render import Renderer
from evcap.sim.scene import load_scene
from evcap.sim.trajectory import Trajectory

UNIFORM_SKY = (
    'environment = "sky"\nsky = { zenith = [1, 1, 1], horizon = [1, 1, 1], ground = [1, 1, 1] }'
)


def test_lambert_sphere_under_a_uniform_sky(tiny_scene):
    path = tiny_scene(
        lighting=UNIFORM_SKY,
        objects=(
            '[[objects]]\ntype = "sphere"\nradius = 0.6\nmaterial = "gray"\n'
            "[materials.gray]\nbase_color = [0.5, 0.3, 0.2]\nroughness = 1.0"
        ),
        trajectory='kind = "static"\nposition = [2.0, 0.0, 0.0]\nlook_at = [0, 0, 0]',
    )
    scene = load_scene(path)
    r = Renderer(scene)
    T = Trajectory(scene.trajectory).pose(0.0)
    out = r.render_full(T)
    h, w = out["depth"].shape
    c = (h // 2, w // 2)
    # albedo times the sky (E = pi, Lambert divides by pi) plus a small GGX specular part
    diffuse = np.array([0.5, 0.3, 0.2])
    assert np.all(out["radiance"][c] >= diffuse) and np.all(out["radiance"][c] < diffuse + 0.1)
    assert out["depth"][c] == pytest.approx(2.0 - 0.6, abs=2e-3)
    np.testing.assert_allclose(out["normal"][c], [0, 0, -1], atol=0.05)  # facing the camera
    np.testing.assert_allclose(out["base_color"][c], diffuse, atol=1e-6)
    assert out["roughness"][c] == pytest.approx(1.0)
    assert out["depth"][0, 0] == 0 and np.all(out["radiance"][0, 0] == pytest.approx(1.0))


SUN = (
    'environment = "sky"\nsky = { zenith = [0.2, 0.2, 0.2], horizon = [0.2, 0.2, 0.2], '
    "ground = [0.2, 0.2, 0.2], sun_direction = [0, 0, 1], sun_irradiance = 3.0 }"
)
FLOOR_AND_BALL = """
[materials.white]
base_color = [0.8, 0.8, 0.8]
roughness = 1.0
[materials.red]
base_color = [0.9, 0.05, 0.05]
roughness = 1.0
[[objects]]
type = "plane"
size = [3.0, 3.0]
subdivisions = 48
material = "white"
[[objects]]
type = "box"
center = [0.0, 0.0, 0.5]
size = [0.6, 0.6, 1.0]
material = "red"
"""
TOP_VIEW = 'kind = "static"\nposition = [0.01, 0.0, 3.0]\nlook_at = [0, 0, 0]'


def test_shadows_and_color_bleeding_only_when_asked(tiny_scene):
    """Looking down at a red post on a white floor lit from above: shadows darken the floor
    next to the post (sky blocked), and light bounced off the post reddens it."""
    images = {}
    for shadows, indirect in ((False, False), (True, False), (True, True)):
        lighting = SUN + f"\nshadows = {str(shadows).lower()}\nindirect = {str(indirect).lower()}"
        scene = load_scene(
            tiny_scene(
                lighting=lighting,
                objects=FLOOR_AND_BALL,
                trajectory=TOP_VIEW,
                width=64,
                height=48,
                fx=40.0,
            )
        )
        r = Renderer(scene)
        images[(shadows, indirect)] = r.render_full(Trajectory(scene.trajectory).pose(0.0))
    # a floor point just beside the post (the camera looks straight down at the origin)
    plain, shadowed, bled = (images[k] for k in [(False, False), (True, False), (True, True)])
    floor = (plain["base_color"][..., 1] > 0.7) & (plain["depth"] > 0)
    post = plain["base_color"][..., 1] < 0.1
    grown = post.copy()
    for _ in range(3):  # the floor within 3 pixels of the post
        grown = (
            grown
            | np.roll(grown, 1, 0)
            | np.roll(grown, -1, 0)
            | np.roll(grown, 1, 1)
            | np.roll(grown, -1, 1)
        )
    near = floor & grown
    assert post.any() and near.sum() > 10
    lum = lambda img: img["radiance"][near].mean(0)  # noqa: E731
    assert lum(shadowed).sum() < lum(plain).sum()  # the post hides part of the sky
    gain = lum(bled) / lum(shadowed) - 1  # light bounced off the post: red, not green/blue
    assert gain[0] > 0.005 and gain[0] > 10 * np.abs(gain[1:]).max(), gain
    np.testing.assert_allclose(plain["base_color"], bled["base_color"])  # truth unchanged


SLANTED_SUN = SUN.replace("sun_direction = [0, 0, 1]", "sun_direction = [1, 0, 1]")


def _floor_and_post(tiny_scene, shadows: bool, indirect: bool) -> tuple[Renderer, np.ndarray]:
    lighting = (
        SLANTED_SUN + f"\nshadows = {str(shadows).lower()}\nindirect = {str(indirect).lower()}"
    )
    path = tiny_scene(
        lighting=lighting, objects=FLOOR_AND_BALL, trajectory=TOP_VIEW, width=64, height=48, fx=40.0
    )
    scene = load_scene(path)
    return Renderer(scene), Trajectory(scene.trajectory).pose(0.0)


def test_visibility_and_indirect_maps(tiny_scene):
    """The red post on the white floor, the sun 45 degrees off the zenith towards +x: the floor
    on the post's -x side is in its shadow, the floor on its +x side gets red bounced light."""
    r, T = _floor_and_post(tiny_scene, shadows=True, indirect=True)
    out = r.render_full(T)
    vis, ind, hit = out["visibility"], out["indirect"], out["depth"] > 0
    assert vis.shape == (48, 64) and vis.dtype == np.float32
    assert ind.shape == (48, 64, 3) and ind.dtype == np.float32
    assert hit.any() and (vis >= 0).all() and (vis <= 1).all() and (ind >= 0).all()
    assert (vis[~hit] == 0).all() and (ind[~hit] == 0).all()
    # straight down onto: the floor away from the sun, the floor towards it, the post's top
    origins = np.array([[-0.45, 0.0, 2.0], [0.45, 0.0, 2.0], [0.0, 0.0, 2.0]])
    dirs = np.broadcast_to([0.0, 0.0, -1.0], (3, 3))
    px = r.render_rays(origins, dirs)
    np.testing.assert_allclose(px.depth, [2.0, 2.0, 1.0], atol=1e-6)
    assert px.visibility[0] < 0.6 and px.visibility[1] > 0.8, px.visibility
    assert px.visibility[2] == pytest.approx(1.0, abs=1e-6)  # nothing above the top
    red = px.indirect[1]
    assert red[0] > 1e-3 and red[0] > 5 * red[1:].max(), red
    assert np.all(px.radiance[1] >= px.indirect[1])  # a part of the light there

    plain, T = _floor_and_post(tiny_scene, shadows=False, indirect=False)
    out = plain.render_full(T)
    hit = out["depth"] > 0
    np.testing.assert_allclose(out["visibility"][hit], 1.0, atol=1e-6)
    assert (out["visibility"][~hit] == 0).all() and (out["indirect"] == 0).all()

    unbounced, T = _floor_and_post(tiny_scene, shadows=True, indirect=False)
    out = unbounced.render_full(T)
    assert (out["indirect"] == 0).all() and out["visibility"][out["depth"] > 0].min() < 0.6


GRADED_SKY = (
    'environment = "sky"\nsky = { zenith = [0.3, 0.45, 0.9], horizon = [0.9, 0.88, 0.8], '
    "ground = [0.25, 0.22, 0.2] }"
)


def test_fewer_specular_samples_stay_close_to_the_full_grid(tiny_scene):
    """``specular_side`` reaches the renderer: a 3 x 3 grid of GGX samples differs from the
    default 12 x 12 on a shiny sphere under a graded sky, by far less than the shading."""
    shiny = (
        '[[objects]]\ntype = "sphere"\nradius = 0.6\nmaterial = "shiny"\n'
        "[materials.shiny]\nbase_color = [0.2, 0.2, 0.2]\nroughness = 0.3"
    )
    static = 'kind = "static"\nposition = [2.0, 0.0, 0.0]\nlook_at = [0, 0, 0]'
    renders = []
    for side in ("", "\nspecular_side = 3"):
        scene = load_scene(tiny_scene(objects=shiny, trajectory=static, lighting=GRADED_SKY + side))
        pose = Trajectory(scene.trajectory).pose(0.0)
        renders.append(Renderer(scene).render_full(pose))
    full, few = renders
    on = full["depth"] > 0
    change = np.abs(few["radiance"] - full["radiance"])[on]
    assert 0 < change.max() < 0.05 * full["radiance"][on].max()
