"""Stage I's terms for surfaces (depth spread, depth curvature, normal smoothness, the
background learnt first) and the settings that turn them on."""

import math

import pytest
import torch

from evcap.errors import InputError
from evcap.recon.presets import preset
from evcap.recon.radiance.losses import (
    depth_curvature_loss,
    depth_spread_loss,
    normal_smoothness_loss,
    quiet_variation_loss,
    structure_block_loss,
)
from evcap.recon.radiance.stage import RadianceField
from evcap.recon.raster.rasterize import Camera, rasterize
from evcap.recon.scene.gaussians import Background, Gaussians
from evcap.recon.scene.optics import RenderGrid


def layers(depths: list[float], opacity: float) -> tuple[torch.Tensor, ...]:
    """Large flat Gaussians filling a 12 x 10 view, one per depth; (second moment, depth,
    alpha) as stage I renders them."""
    n = len(depths)
    means = torch.tensor([[0.0, 0.0, d] for d in depths])
    log_scales = torch.tensor([[math.log(100.0), math.log(100.0), math.log(1e-3)]] * n)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n)
    opacities = torch.full((n,), opacity)
    z = means[:, 2:3]
    K = torch.tensor([[10.0, 0, 5.5], [0, 10.0, 4.5], [0, 0, 1]])
    r = rasterize(means, quats, log_scales.exp(), opacities, z * z, Camera(torch.eye(4), K, 12, 10))
    return r.color[..., 0], r.depth, r.alpha


def test_a_thin_surface_has_no_spread():
    assert float(depth_spread_loss(*layers([2.0], 0.99))) == pytest.approx(0.0, abs=1e-6)


def test_fog_spread_in_depth_costs_more_the_wider_it_is():
    near = float(depth_spread_loss(*layers([2.0, 2.2], 0.6)))
    far = float(depth_spread_loss(*layers([2.0, 3.0], 0.6)))
    assert 0 < near < far
    # two layers of weights 0.6 and 0.24 at 2 and 3: Var / E^2 by hand
    w = torch.tensor([0.6, 0.4 * 0.6])
    d = torch.tensor([2.0, 3.0])
    mean = (w * d).sum() / w.sum()
    relative = ((w * d * d).sum() / w.sum() - mean**2) / mean**2
    assert far == pytest.approx(float(relative / (1 + relative)), rel=1e-3)


def test_a_floater_near_the_camera_costs_at_most_one():
    assert 0.5 < float(depth_spread_loss(*layers([0.05, 3.0], 0.6))) < 1.0


def test_transparent_pixels_do_not_count_and_stay_finite():
    second, depth, alpha = layers([2.0, 3.0], 0.2)  # alpha 0.36: below the half it needs
    second.requires_grad_(True)
    loss = depth_spread_loss(second, depth, alpha)
    loss.backward()
    assert float(loss.detach()) == 0.0 and torch.isfinite(second.grad).all()


def test_unknown_settings_are_named():
    with pytest.raises(InputError, match="spread.wieght"):
        preset("tiny", {"stage1.loss.spread.wieght": 1.0})
    assert preset("tiny", {"stage1.loss.spread.weight": 10.0}).stage1.loss.spread.weight == 10.0


def grid(h: int = 12, w: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.meshgrid(
        torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij"
    )


def test_curvature_is_zero_on_a_plane_and_counts_a_patch_out_of_it():
    ys, xs = grid()
    plane = 2.0 + 0.05 * xs - 0.02 * ys
    opaque = torch.ones_like(plane)
    assert float(depth_curvature_loss(plane, opaque)) == pytest.approx(0.0, abs=1e-6)
    patch = plane.clone()
    patch[4:8, 5:10] += 0.2  # one square of a checker behind its neighbours
    deeper = plane.clone()
    deeper[4:8, 5:10] += 0.4
    assert (
        0.005
        < float(depth_curvature_loss(patch, opaque))
        < float(depth_curvature_loss(deeper, opaque))
    )
    # where the render is transparent (the background), nothing counts
    assert float(depth_curvature_loss(patch, (patch == plane).float())) == pytest.approx(
        0, abs=1e-6
    )


def test_normals_are_smoothed_across_a_texture_edge_not_across_an_outline():
    ys, xs = grid()
    opaque = torch.ones_like(xs)
    normals = torch.zeros(12, 16, 3)
    normals[..., 2] = -1
    normals[:, 8:] = torch.tensor([0.5, 0.0, -0.8])  # a crease at column 8
    one_surface = torch.full_like(xs, 2.0)
    outline = torch.where(xs < 8, 2.0, 3.0)  # the right half far behind
    flat = normals.clone()
    flat[:, 8:] = normals[0, 0]
    assert float(normal_smoothness_loss(flat, one_surface, opaque, 0.02)) == 0.0
    crease = float(normal_smoothness_loss(normals, one_surface, opaque, 0.02))
    assert crease > 0.01
    assert float(normal_smoothness_loss(normals, outline, opaque, 0.02)) < 1e-3 * crease


def test_variation_counts_where_no_event_fired_only():
    _, xs = grid()
    flat = torch.zeros(12, 16, 3)
    none = torch.zeros(12, 16, dtype=torch.bool)
    assert float(quiet_variation_loss(flat, none)) == 0.0
    halo = flat.clone()
    halo[:, 8:] = (0.1 * (xs[:, 8:] - 7))[..., None]  # brightening away from an edge
    assert float(quiet_variation_loss(halo, none)) > 0.05
    # the same ramp where events fired (within a pixel) is the events' to judge
    loud = xs >= 7
    assert float(quiet_variation_loss(halo, loud)) == 0.0
    step = flat.clone()
    step[:, 8:] = 1.0
    assert float(quiet_variation_loss(step, (xs == 8) | (xs == 7))) == 0.0


def test_a_stereo_point_is_not_seen_through():
    """A faint layer at the point's depth before an opaque one behind it (a pale sphere on a
    floor) costs, and more opacity there lowers it; an occluder in front of the point passes."""
    K = torch.tensor([[10.0, 0, 5.5], [0, 10.0, 4.5], [0, 0, 1]])
    camera = Camera(torch.eye(4), K, 12, 10)
    points = torch.tensor([[0.0, 0.0, 2.0], [0.1, -0.1, 2.0]])

    def cost(depths: list[float], opacity: torch.Tensor, opaque: float = 1.0) -> torch.Tensor:
        n = len(depths)
        means = torch.tensor([[0.0, 0.0, d] for d in depths])
        scales = torch.tensor([[100.0, 100.0, 1e-3]] * n)
        quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n)
        r = rasterize(means, quats, scales, opacity, means[:, 2:3] ** 2, camera)
        return structure_block_loss(r.depth, r.alpha, points, torch.eye(4), K, 0.03, opaque)

    faint = torch.tensor([0.1, 0.99], requires_grad=True)
    seen_through = cost([2.0, 4.0], faint)
    seen_through.backward()
    assert float(seen_through.detach()) > 0.5  # the floor's depth 4 where the point is at 2
    assert float(faint.grad[0]) < 0  # more opacity at the point: less cost
    solid = float(cost([2.0, 4.0], torch.tensor([0.99, 0.99])))
    assert solid < 0.02
    assert float(cost([1.0, 4.0], torch.tensor([0.99, 0.99]))) < 0.02  # an occluder
    assert float(cost([2.0], torch.tensor([0.2]))) > 0.7  # nothing behind: the alpha missing
    assert float(cost([2.0], torch.tensor([0.2]), opaque=0.0)) < 1e-6  # ... unless not asked
    assert float(cost([2.0, 4.0], torch.tensor([0.1, 0.99]), opaque=0.0)) > 0.5
    # a point behind the camera or off the image is not counted
    away = torch.tensor([[0.0, 0.0, -2.0], [50.0, 0.0, 2.0]])
    means, scales = torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[100.0, 100.0, 1e-3]])
    r = rasterize(
        means,
        torch.tensor([[1.0, 0, 0, 0]]),
        scales,
        torch.tensor([0.1]),
        means[:, 2:] ** 2,
        camera,
    )
    assert float(structure_block_loss(r.depth, r.alpha, away, torch.eye(4), K, 0.03)) == 0.0


def test_hidden_gaussians_leave_the_background_alone():
    gaussians = Gaussians.random(torch.randn(50, 3).numpy() + [0, 0, 4], 0, torch.Generator(), 0.3)
    field = RadianceField(gaussians, Background(8), backend="torch")
    K = torch.tensor([[20.0, 0, 12], [0, 20.0, 9], [0, 0, 1]])
    g = RenderGrid(K, 24, 18, torch.zeros(1, 1, 1, 2))
    T = torch.eye(4).numpy()
    assert float(field.render(T, g).alpha.detach().max()) > 0.1
    assert float(field.render(T, g, hidden=True).alpha.detach().max()) == 0.0


def test_a_plain_background_has_no_variation_and_a_patch_some():
    bg = Background(8)
    assert bg.log_variation().item() == 0.0
    with torch.no_grad():
        bg.faces[2, :, 2:4, 2:4] += 2.0
    variation = bg.log_variation()
    assert variation.item() > 0
    variation.backward()
    assert bg.faces.grad[2].abs().sum() > 0 and bg.faces.grad[0].abs().sum() == 0
