"""Stage I's terms for surfaces: the depth-spread loss, and the settings that turn them on."""

import math

import pytest
import torch

from evcap.errors import InputError
from evcap.recon import config as cfg
from evcap.recon.losses import depth_spread_loss
from evcap.recon.rasterize import Camera, rasterize


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
    expected = ((w * d * d).sum() / w.sum() - mean**2) / mean**2
    assert far == pytest.approx(float(expected), rel=1e-3)


def test_transparent_pixels_do_not_count_and_stay_finite():
    second, depth, alpha = layers([2.0, 3.0], 0.2)  # alpha 0.36: below the half it needs
    second.requires_grad_(True)
    loss = depth_spread_loss(second, depth, alpha)
    loss.backward()
    assert float(loss.detach()) == 0.0 and torch.isfinite(second.grad).all()


def test_unknown_settings_are_named():
    with pytest.raises(InputError, match="spread_wieght"):
        cfg.preset("tiny", spread_wieght=1.0)
    assert cfg.preset("tiny", spread_weight=10.0).spread_weight == 10.0
