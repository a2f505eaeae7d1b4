"""Stage II: shading against independent references, the visibility bake, and its hard cases
(roughness at its bounds, a black environment, normals facing away) staying finite."""

import math

import numpy as np
import pytest
import torch

from evcap.errors import InputError
from evcap.recon.config import ABLATIONS
from evcap.recon.material import stage as material
from evcap.recon.material.shading import fibonacci_directions, shade
from evcap.recon.material.stage import edge_tv, light_from_image
from evcap.recon.material.visibility import bake_occlusion, bake_visibility
from evcap.recon.presets import preset
from evcap.recon.radiance.stage import load_training_data, new_field
from evcap.recon.radiance.terms import total_loss
from evcap.recon.scene.cube_map import cube_directions, cube_lookup, mip_chain
from evcap.recon.scene.gaussians import Gaussians
from evcap.session import Session


def uniform_light(value: float, size: int = 16) -> list[torch.Tensor]:
    return mip_chain(torch.full((6, 3, size, size), value))


def test_white_lambertian_under_a_uniform_sky_shows_the_sky():
    n = 64
    normals = torch.nn.functional.normalize(
        torch.randn(n, 3, generator=torch.Generator().manual_seed(0)), dim=1
    )
    base = torch.full((n, 3), 0.6)
    rough = torch.ones(n)
    out = shade(base, rough, normals, normals, uniform_light(0.7), fibonacci_directions(256))
    # diffuse: base / pi * (pi L); specular of a rough dielectric adds about F0 * L
    assert out.numpy() == pytest.approx(0.6 * 0.7 + 0.04 * 0.7, abs=0.03)


def test_blocked_light_darkens_the_diffuse():
    n = torch.tensor([[0.0, 0.0, 1.0]])
    dirs = fibonacci_directions(256)
    args = (torch.full((1, 3), 0.5), torch.ones(1), n, n, uniform_light(1.0), dirs)
    open_sky = shade(*args)
    half = shade(*args, visibility=(dirs[:, 0] > 0).float()[None])
    dark = shade(*args, visibility=torch.zeros(1, len(dirs)))
    assert float(dark.max()) < 1e-6
    assert float(half.mean()) == pytest.approx(float(open_sky.mean()) / 2, rel=0.1)
    bounced = shade(*args, visibility=torch.zeros(1, len(dirs)), indirect=torch.ones(1, 3))
    assert float(bounced.min()) > 0  # light from other surfaces reaches the shadowed point


def test_light_from_an_image_reads_the_right_directions():
    image = np.zeros((32, 64, 3))
    image[:16] = [1.0, 0.5, 0.25]  # the upper half: z > 0
    light = light_from_image(image, 16)
    up = cube_lookup(light[0], torch.tensor([[0.0, 0.0, 1.0], [0.3, 0.2, -0.9]]))
    assert up[0].numpy() == pytest.approx([1.0, 0.5, 0.25], abs=1e-3)
    assert up[1].numpy() == pytest.approx([0.0, 0.0, 0.0], abs=1e-3)
    assert cube_directions(4).norm(dim=-1).numpy() == pytest.approx(1.0)


UP = torch.tensor([[0.0, 0.0, 1.0]])


def plane_and_point(z_point: float) -> Gaussians:
    """A wide opaque plane of flat Gaussians at z = 1 and one small Gaussian at z_point."""
    xs, ys = np.meshgrid(np.linspace(-1, 1, 21), np.linspace(-1, 1, 21))
    plane = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)], 1)
    means = torch.tensor(np.concatenate([plane, [[0, 0, z_point]]]), dtype=torch.float32)
    n = len(means)
    log_scales = torch.log(torch.tensor([0.08, 0.08, 0.005])).repeat(n, 1)
    quats = torch.tensor([1.0, 0, 0, 0]).repeat(n, 1)
    return Gaussians(
        means, log_scales, quats, torch.full((n,), 6.0), torch.zeros(n, 1, 3), torch.zeros(n, 0, 3)
    )


def ball_on_floor(
    radius: float, spacing: float, half: float, floor_z: float = 0.0
) -> tuple[Gaussians, torch.Tensor, int]:
    """Flat opaque discs on a square floor (``half`` its half width, at ``floor_z``) and on a
    ball of ``radius`` resting on it at the middle, about ``spacing`` apart; their normals
    [N, 3]; how many are the floor's (they come first)."""
    xs, ys = np.meshgrid(np.arange(-half, half, spacing), np.arange(-half, half, spacing))
    floor = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, floor_z)], 1)
    ball_normals = fibonacci_directions(int(4 * math.pi * radius**2 / spacing**2)).numpy()
    centre = np.array([0.0, 0.0, floor_z + radius])
    means = np.concatenate([floor, centre + radius * ball_normals])
    normals = np.concatenate([np.tile([0.0, 0.0, 1.0], (len(floor), 1)), ball_normals])
    # the rotation taking +z to each normal: (w, x, y, z) = normalise(1 + n.z, -n.y, n.x, 0)
    quats = np.stack([1 + normals[:, 2], -normals[:, 1], normals[:, 0], 0 * normals[:, 0]], 1)
    quats[normals[:, 2] < -0.999] = [0.0, 1.0, 0.0, 0.0]
    n = len(means)
    g = Gaussians(
        torch.tensor(means, dtype=torch.float32),
        torch.log(torch.tensor([0.6 * spacing, 0.6 * spacing, 0.01 * spacing])).repeat(n, 1),
        torch.nn.functional.normalize(torch.tensor(quats, dtype=torch.float32), dim=1),
        torch.full((n,), 4.0),
        torch.zeros(n, 1, 3),
        torch.zeros(n, 0, 3),
    )
    return g, torch.tensor(normals, dtype=torch.float32), len(floor)


def test_visibility_is_blocked_under_a_roof_and_open_beside_it():
    g = plane_and_point(0.0)
    dirs = torch.tensor([[0.0, 0, 1], [0.0, 0.3, 0.95], [0.0, 0, -1]])
    v = bake_visibility(g, UP.repeat(len(g), 1), dirs).float()
    point = v[-1]
    assert float(point[0]) < 0.2 and float(point[1]) < 0.2  # the roof overhead
    assert float(point[2]) > 0.8
    assert torch.isfinite(v).all()


def test_a_floor_alone_sees_its_whole_sky_down_to_the_horizon():
    """A plane does not shadow itself: from the middle of a wide floor the sky is open at
    every elevation, the low ones included (rays lifted along the ray alone grazed the floor's
    own cells and saw it as a wall)."""
    g = plane_and_point(1.0)  # the point lies in the plane
    elevations = torch.deg2rad(torch.tensor([10.0, 20.0, 45.0, 90.0]))
    for azimuth in torch.deg2rad(torch.tensor([0.0, 60.0, 135.0])):
        d = torch.stack(
            [
                elevations.cos() * azimuth.cos(),
                elevations.cos() * azimuth.sin(),
                elevations.sin(),
            ],
            1,
        )
        middle = bake_visibility(g, UP.repeat(len(g), 1), d)[len(g) // 2]  # the plane's centre
        assert float(middle.min()) > 0.8


def test_a_floor_beside_a_resting_sphere_sees_what_the_sphere_leaves_open():
    """Flat discs on a floor and on a ball resting on it: the floor's baked visibility close to
    the ball's foot, direction by direction, against the ball's exact shadow (a ray is blocked
    where it passes within the radius of the centre). Rays marched through a grid started
    inside the ball there and saw a tenth of the sky the floor sees."""
    radius, spacing = 0.4, 0.04
    g, normals, on_floor = ball_on_floor(radius, spacing, 1.6)
    floor = g.means[:on_floor].detach().numpy()
    centre = np.array([0.0, 0.0, radius])
    dirs = fibonacci_directions(256)
    baked = bake_visibility(g, normals, dirs).float().numpy()
    near = np.flatnonzero(np.abs(np.linalg.norm(floor[:, :2], axis=1) - 0.55) < 0.1)
    to_centre = centre - floor[near]  # [M, 3]
    along = to_centre @ dirs.numpy().T  # [M, K]
    miss = (to_centre**2).sum(1)[:, None] - along**2
    exact = ~((along > 0) & (miss < radius**2))
    up = dirs.numpy()[:, 2] > 0.05
    error = np.abs(baked[near][:, up] - exact[:, up])
    assert exact[:, up].mean() < 0.9  # the ball hides a good part of the sky there
    assert error.mean() < 0.05


def test_the_light_a_roof_blocks_is_found_coming_off_its_underside():
    """Under a roof, every blocked direction meets the roof: the cosine-weighted sky left open
    and the bounce's weights make up the whole hemisphere (pi), and the light comes off the
    roof's underside (the back of its upward normals)."""
    g = plane_and_point(0.0)
    dirs = fibonacci_directions(256)
    baked = bake_occlusion(g, UP.repeat(len(g), 1), dirs, bounce=True)
    point = len(g) - 1
    mine = baked.bounce.receivers == point
    cos = (dirs @ UP[0]).clamp(min=0)
    open_sky = float((baked.visibility[point].float() * cos).sum()) * 4 * math.pi / len(dirs)
    blocked = float(baked.bounce.weights[mine].sum())
    assert blocked > 1.5  # most of its sky is the roof
    assert open_sky + blocked == pytest.approx(math.pi, rel=0.05)
    assert bool((baked.bounce.sources[mine] % 2 == 1).all())  # the back sides
    assert (baked.bounce.sources[mine] // 2 < point).all()  # the roof's Gaussians
    # the roof sees nothing above it that blocks its light
    assert not (baked.bounce.receivers < point).any()


def test_a_red_roof_bleeds_red_onto_what_lies_under_it():
    """The diffuse light leaving the roof's underside (its base color times the light from
    below) arrives at the white point under it, weighted as the bake says."""
    from evcap.recon.scene.gaussians import Background

    g = plane_and_point(0.0)
    up = UP.repeat(len(g), 1)
    dirs = fibonacci_directions(material.DIFFUSE_DIRECTIONS)
    baked = bake_occlusion(g, up, dirs, bounce=True)
    light = Background.from_faces(torch.full((6, 3, 8, 8), 0.5413))  # softplus: radiance 1
    field = material.MaterialField(
        g, light, up, baked.visibility, indirect=False, bounce=baked.bounce
    )
    center = torch.tensor([0.0, 0.0, -2.0])
    colors = {}
    for name, roof in (("black", [-12.0, -12.0, -12.0]), ("red", [1.386, -1.386, -1.386])):
        with torch.no_grad():
            field.base_logits.fill_(12.0)  # white
            field.base_logits[:-1] = torch.tensor(roof)  # red: 0.8, 0.2, 0.2
            colors[name], _ = field.shaded(center)
    gained = (colors["red"] - colors["black"])[-1]
    # under a light of radiance 1 the underside leaves base / pi * pi = base: the point gains
    # base_point / pi * (the blocked share's weight) * roof's base color
    mine = baked.bounce.receivers == len(g) - 1
    blocked = float(baked.bounce.weights[mine].sum())
    expected = torch.tensor([0.8, 0.2, 0.2]) * blocked / math.pi
    assert gained.numpy() == pytest.approx(expected.numpy(), rel=0.1)


def test_visibility_of_nothing_is_open():
    g = plane_and_point(0.0)
    with torch.no_grad():
        g.opacity_logits.fill_(-10.0)  # all transparent: nothing blocks
    v = bake_visibility(g, UP.repeat(len(g), 1), fibonacci_directions(64)).float()
    assert v.numpy() == pytest.approx(1.0, abs=1e-5)


def test_edge_tv_relaxes_at_edges():
    maps = torch.zeros(8, 8, 10)
    maps[:, 4:, 3:6] = 1.0  # a base-color edge down the middle
    flat = torch.ones(8, 8)
    edged = flat.clone()
    edged[:, 3:5] = math.exp(-10)
    assert float(edge_tv(maps, edged, 0.1)) < 0.01 * float(edge_tv(maps, flat, 0.1))


@pytest.fixture(scope="module")
def stage_one(tiny_scene, tmp_path_factory):
    from evcap.sim.scene import load_scene
    from evcap.sim.simulate import simulate

    scene = tiny_scene(color_filter="RGBG")
    path = tmp_path_factory.mktemp("material") / "s.h5"
    simulate(load_scene(scene), path)
    config = preset("tiny", {"stage1.iterations": 2}).stage1
    with Session.open(path) as s:
        data = load_training_data(s, config, "cpu")
    return path, data, config


@pytest.mark.parametrize(
    "case",
    ["rough_bounds", "black_environment", "normals_away", "all_effects"],
)
def test_hard_cases_stay_finite(stage_one, case, monkeypatch):
    path, data, config = stage_one
    field = new_field(data, config, 0, "cpu", "torch")
    settings = {"stage2.iterations": 3, "stage2.edges.frames": 4}
    if case == "all_effects":
        settings |= {"stage2.visibility": "on", "stage2.indirect": "on"}
    mconfig = preset("tiny", settings).stage2
    if case == "black_environment":
        with torch.no_grad():
            field.background.faces.fill_(-40.0)  # softplus -> ~4e-18: black light
    original = material.new_material_field

    def forced(*args, **kwargs):
        """The start of a hard case, forced after the usual initialisation."""
        m = original(*args, **kwargs)
        with torch.no_grad():
            if case == "rough_bounds":
                bounds = torch.where(torch.rand(len(m.gaussians)) < 0.5, -60.0, 60.0)
                m.roughness_logits.copy_(bounds)
            if case == "normals_away":
                m.normals.mul_(-1)
                m.normals[::7] = 0.0  # and some of no length at all
        return m

    monkeypatch.setattr(material, "new_material_field", forced)
    with Session.open(path) as s:
        fit = material.train_material(field, data, s, config, mconfig)
    m = fit.field
    for p in m.parameters():
        assert torch.isfinite(p).all()
    assert all(math.isfinite(x.loss) for x in fit.log)
    T = data.track.at(data.windows.frame_times[:1])[0]
    with torch.no_grad():
        assert torch.isfinite(m.render(T, data.grid).color).all()


def test_stage_two_losses_leave_out_the_ablated_terms(stage_one):
    _, data, config = stage_one
    radiance = new_field(data, config, 0, "cpu", "torch")
    mconfig = preset("tiny", {"stage2.edges.frames": 4}).stage2
    field = material.new_material_field(radiance, data, mconfig)
    frames = np.array([0, 3, 9])
    weights = {int(f): torch.ones(data.grid.height, data.grid.width) for f in frames}
    with torch.no_grad():
        targets = {
            int(f): radiance.render_view(data.viewmats()[f], data.grid).color for f in frames
        }

    def losses(ablate: frozenset) -> tuple[float, dict[str, float]]:
        terms = material.stage_two_terms(config, mconfig, ablate)
        renders = [field.render_view(data.viewmats()[int(f)], data.grid) for f in frames]
        seen = [data.grid.sample(r.color[..., :3]) for r in renders]
        inputs = material.StepInputs(data, frames, renders, seen, targets, weights)
        total = total_loss(terms, inputs, 1, background_alone=False)
        # each term as the training's log shows it (0: not computed)
        return total.item(), {k: float(inputs.logged.get(k, 0.0)) for k in material.LOGGED}

    total, terms = losses(frozenset())
    weighted = {k: getattr(mconfig.loss, k) for k in ("distill", "anchor", "tv")}
    assert terms["distill"] > 0 and terms["tv"] > 0
    expected = terms["event"] + sum(w * terms[k] for k, w in weighted.items())
    assert total == pytest.approx(expected, rel=1e-5)
    alone, left = losses(frozenset(ABLATIONS))
    assert alone == pytest.approx(terms["event"], rel=1e-6)
    assert left == {"event": terms["event"], "distill": 0.0, "anchor": 0.0, "tv": 0.0}


@pytest.mark.parametrize("made_with", [(False, False), (True, True)])
def test_auto_models_the_effects_that_made_the_radiance(stage_one, made_with):
    """A red ball resting on a white floor, its stage-I radiance made by the shading under a
    uniform sky with neither effect or with visibility and its bounce (the ball's shadow and
    its red on the floor): `auto` chooses the effects that explain it, and only those. (With
    visibility alone the start also varies least under visibility alone; `auto` does not
    offer it, see effect_choices.)"""
    from evcap.recon.radiance.stage import RadianceField
    from evcap.recon.scene.gaussians import Background
    from evcap.recon.scene.sh import C0

    _, data, config = stage_one
    g, normals, floor = ball_on_floor(0.35, 0.07, 1.0, floor_z=-0.6)  # where the orbit looks
    light = Background.from_faces(torch.full((6, 3, 8, 8), 0.5413))  # softplus: radiance 1
    visibility, indirect = made_with
    baked = bake_occlusion(
        g, normals, fibonacci_directions(material.DIFFUSE_DIRECTIONS), bounce=indirect
    )
    truth = material.MaterialField(
        g,
        light,
        normals,
        baked.visibility if visibility else None,
        indirect=False,
        bounce=baked.bounce if indirect else None,
    )
    cams = torch.as_tensor(
        data.track.at(data.windows.frame_times)[:, :3, 3].mean(0), dtype=torch.float32
    )
    with torch.no_grad():
        truth.base_logits[:floor] = 2.0  # white 0.88
        truth.base_logits[floor:] = torch.tensor([1.5, -1.5, -1.5])  # red 0.82, 0.18, 0.18
        truth.roughness_logits.fill_(2.0)
        radiance, _ = truth.shaded(cams)
        # stage I's Gaussians: the truth's radiance as their view-independent color
        g.sh_dc[:, 0] = torch.log(torch.expm1(radiance.clamp(min=1e-4))) / C0
    field = RadianceField(g, light, "torch")
    chosen = material.new_material_field(field, data, preset("tiny").stage2)
    assert set(chosen.start_variation) == {"neither", "visibility+indirect"}
    assert chosen.effects == {"visibility": visibility, "indirect": indirect}


def test_relighting_scales_the_light_from_other_surfaces_with_the_light():
    """Twice the light gives twice the radiance, the part that bounced off other surfaces
    included (learnt under the first light, it must not stay as it was); the learnt light
    itself gives the views as they were."""
    from evcap.recon.scene.gaussians import Background

    g = plane_and_point(0.0)  # the point lies under the plane: most of its light bounced
    up = torch.tensor([0.0, 0.0, 1.0]).repeat(len(g), 1)
    light = Background.from_faces(torch.linspace(-1, 1, 6)[:, None, None, None].expand(6, 3, 8, 8))
    dirs = fibonacci_directions(material.DIFFUSE_DIRECTIONS)
    field = material.MaterialField(g, light, up, bake_visibility(g, up, dirs), indirect=True)
    with torch.no_grad():
        field.indirect_sh.fill_(0.5)
        learnt = mip_chain(light.radiance_faces())
        center = torch.tensor([0.3, 0.2, -2.0])
        before, _ = field.shaded(center)
        same, _ = field.shaded(center, learnt)
        doubled, _ = field.shaded(center, [2 * level for level in learnt])
    assert torch.allclose(same, before, rtol=1e-5)
    assert torch.allclose(doubled, 2 * before, rtol=1e-4)


def test_stage_two_settings_are_checked():
    with pytest.raises(InputError, match="normals_form"):
        preset("fast", {"stage2.normals_form": "planes"})
    with pytest.raises(InputError, match="normals_from"):
        preset("fast", {"stage2.normals_from": "depth"})
