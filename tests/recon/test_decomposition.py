"""Stage II separates the material from the light: on a sphere of known albedo lit by a warm
sun under a dim blue sky, its base color is nearer the albedo than stage I's radiance is.

Stage I is given the truth's surface (flat opaque Gaussians sampled over the sphere, whose
geometry does not learn) and learns only their radiance from the events: at this size a stage I
that learns the geometry too recovers none of it, and the test is of stage II."""

import numpy as np
import pytest
import torch

from evcap.recon.options import ReconstructOptions
from evcap.recon.radiance import stage as radiance
from evcap.recon.raster.rasterize import gaussian_normals
from evcap.recon.reconstruct import reconstruct
from evcap.recon.scene.gaussians import Background, Gaussians
from evcap.sim.meshes import build_mesh, sample_surface, sphere
from evcap.sim.scene import load_scene
from evcap.sim.simulate import simulate

# the camera swings 60 degrees round the sphere; the sun comes from its left, above the
# horizon, warm; the sky is dim and blue: the shading differs by channel across the sphere, which
# no gain per channel takes out of the radiance
SUNLIT = """
[scene]
name = "sunlit"
seed = 3

[sensor]
color_filter = "RGBG"
contrast_threshold = 0.2

[camera]
width = 64
height = 48
fx = 60.0

[trajectory]
kind = "orbit"
radius = 2.2
height = 0.8
height_swing = 0.4
swings = 1
degrees = 60.0
duration_s = 0.5

[lighting]
environment = "sky"
sky = { zenith = [0.1, 0.15, 0.3], horizon = [0.15, 0.15, 0.2], ground = [0.05, 0.05, 0.05], \
sun_direction = [-0.5, 0.87, 0.4], sun_irradiance = [2.0, 1.3, 0.6] }

[materials.paint]
procedural = { kind = "checker", scale = 4, colors = [[0.8, 0.25, 0.1], [0.9, 0.85, 0.6]] }
roughness = 0.4

[[objects]]
type = "sphere"
center = [0.25, 0.0, 0.0]
radius = 0.6
material = "paint"

[gt]
fps = 10
test_views = 2
"""
SURFACE_GAUSSIANS = 4000


def test_gaussians_on_a_sampled_sphere_lie_on_it_and_face_out():
    points, normals, spacing = sample_surface(sphere(), 2000, seed=1)
    assert np.linalg.norm(points, axis=1) == pytest.approx(1.0, abs=0.01)
    assert (normals * points).sum(1) == pytest.approx(1.0, abs=0.01)
    assert spacing == pytest.approx(np.sqrt(4 * np.pi / 2000), rel=0.02)
    g = Gaussians.on_surface(points, normals, spacing, sh_degree=1)
    with torch.no_grad():
        facing = (gaussian_normals(g.quats, g.scales) * torch.as_tensor(normals).float()).sum(1)
        opacity = float(g.opacities.min())
    assert facing.abs().numpy() == pytest.approx(1.0, abs=1e-5)  # a disc has two sides
    assert opacity == pytest.approx(0.95)


@pytest.fixture(scope="module")
def sunlit_result(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sunlit")
    (folder / "scene.toml").write_text(SUNLIT)
    scene = load_scene(folder / "scene.toml")
    simulate(scene, folder / "s.h5")
    points, normals, spacing = sample_surface(build_mesh(scene)[0], SURFACE_GAUSSIANS)

    def on_the_surface(data, config, seed, device, backend):
        g = Gaussians.on_surface(points, normals, spacing, config.sh_degree)
        for name in ("means", "log_scales", "quats", "opacity_logits"):
            getattr(g, name).requires_grad_(False)
        return radiance.RadianceField(g, Background(config.background.size), backend)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(radiance, "new_field", on_the_surface)
        settings = {
            "stage1.resolution": 1.0,
            "stage1.iterations": 400,
            "stage2.iterations": 200,
            "stage1.densify.start": 0.0,  # no densification (it stops before it starts)
            "stage1.densify.stop": 0.0,
            "stage1.background.first": 0.0,
        }
        options = ReconstructOptions(preset="tiny", settings=settings)
        return reconstruct(folder / "s.h5", folder / "recon", options)


def test_the_base_color_beats_the_radiance_it_starts_from(sunlit_result):
    f = sunlit_result.figures
    assert f.normal_mae_deg < 8  # the truth's surface, as given
    # stage I learnt the radiance's pattern; after one gain it is hazy (measured: 18.4 dB on
    # the object against a constant's 17.2; 22.4 after 1,500 steps, where the base color
    # falls to 18.0), and the base color below is what is tested
    assert f.object_psnr_affine_per_view > f.object_psnr_constant + 3
    assert f.base_color_psnr_gain > f.base_color_psnr_gain_baseline + 1.0
    assert f.base_color_psnr_gain > f.base_color_psnr_constant + 3


def test_the_relit_object_beats_the_radiance_under_the_first_light(sunlit_result):
    f = sunlit_result.figures
    assert f.relit_object_psnr_gain > f.relit_object_psnr_gain_baseline + 1.5
    assert np.isfinite(f.relit_object_psnr)
