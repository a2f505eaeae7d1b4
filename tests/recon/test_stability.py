"""The hard cases of stage I: each must leave losses, parameters and renders finite."""

import math

import numpy as np
import pytest
import torch

from evcap.recon.events.loss import log_radiance, window_loss
from evcap.recon.events.windows import EventWindows
from evcap.recon.radiance.losses import anchor_loss, normal_loss
from evcap.recon.raster.rasterize import Camera, rasterize
from evcap.records import Poses


def camera(width=24, height=18):
    view = torch.eye(4)
    view[2, 3] = 3.0  # the world origin 3 m in front
    K = torch.tensor([[20.0, 0, 11.5], [0, 20.0, 8.5], [0, 0, 1]])
    return Camera(view, K, width, height)


def gaussians(n=40, seed=0, log_scale=-2.3, spread=0.8):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * spread
    params = [
        means,
        torch.randn(n, 4, generator=g),
        torch.full((n, 3), float(log_scale)) + 0.1 * torch.randn(n, 3, generator=g),
        torch.full((n,), 0.0),
        torch.rand(n, 3, generator=g),
    ]
    return [p.requires_grad_(True) for p in params]


@pytest.fixture(params=["cpu", "torch"])
def backend(request) -> str:
    """The hard cases of rendering run on both CPU rasterizers."""
    return request.param


def render_and_backward(means, quats, log_scales, logits, colors, cam, backend, background=0.3):
    out = rasterize(
        means,
        quats,
        log_scales.exp(),
        torch.sigmoid(logits),
        colors,
        cam,
        background=torch.full((3,), background),
        backend=backend,
    )
    lum = out.color.mean(-1).ravel()
    loss = (
        log_radiance(lum, 1e-3).mean()
        + anchor_loss(out.color, 0.5)
        + normal_loss(out.normal, out.depth, out.alpha, cam.K)
        + out.depth.mean()
    )
    loss.backward()
    return out, loss


def assert_all_finite(out, loss, params):
    assert torch.isfinite(loss)
    for name in ("color", "depth", "alpha", "normal"):
        assert torch.isfinite(getattr(out, name)).all(), name
    for p in params:
        assert torch.isfinite(p).all()
        assert p.grad is None or torch.isfinite(p.grad).all()


@pytest.mark.parametrize(
    "log_scale", [-30.0, -12.0, 4.0, 12.0], ids=["zero", "tiny", "big", "huge"]
)
def test_collapsed_and_huge_gaussians(log_scale, backend):
    params = gaussians(log_scale=log_scale)
    out, loss = render_and_backward(*params, camera(), backend)
    assert_all_finite(out, loss, params)
    assert (out.alpha >= 0).all() and (out.alpha <= 1).all()


def test_camera_inside_a_gaussian(backend):
    params = gaussians(n=5, log_scale=math.log(2.0))
    with torch.no_grad():
        params[0][0] = torch.tensor([0.0, 0.0, -3.0])  # at the camera centre
        params[0][1] = torch.tensor([0.1, 0.0, -2.995])  # just in front of it
        params[0][2] = torch.tensor([0.0, 0.2, -3.2])  # just behind it
    out, loss = render_and_backward(*params, camera(), backend)
    assert_all_finite(out, loss, params)


def test_a_view_with_nothing_in_it(backend):
    params = gaussians()
    with torch.no_grad():
        params[0][:, 2] -= 10  # all behind the camera
    out, loss = render_and_backward(*params, camera(), backend, background=0.0)
    assert_all_finite(out, loss, params)
    assert out.alpha.abs().max() == 0 and out.color.abs().max() == 0
    assert (out.depth == 0).all()


@pytest.mark.parametrize("level", [0.0, 1e6], ids=["black", "saturated"])
def test_black_and_saturated_pixels(level, backend):
    means, quats, log_scales, logits, colors = gaussians()
    colors = torch.full_like(colors, level).requires_grad_(True)
    params = [means, quats, log_scales, logits, colors]
    out, loss = render_and_backward(*params, camera(), backend, background=level)
    assert_all_finite(out, loss, params)


def test_log_of_zero_and_negative_radiance_is_finite():
    x = torch.tensor([0.0, -1e-4, 1e-30, 5.0], requires_grad=True)
    y = log_radiance(x, 1e-3)
    y.sum().backward()
    assert torch.isfinite(y).all() and torch.isfinite(x.grad).all()


def windows_from_codes(codes, times, starts, width=4, height=3, c=0.2):
    n = width * height
    return EventWindows.from_codes(
        width, height, times, codes, starts, torch.full((n,), c), torch.full((n,), c)
    )


@pytest.mark.parametrize("zero_events", ["target", "bound"])
@pytest.mark.parametrize("silent_weight", [None, 0.1])
def test_a_window_with_no_events(zero_events, silent_weight):
    w = windows_from_codes([], [0, 5000, 10000], [0, 0, 0])
    target, counts = w.log_change(0, 2)
    assert counts.sum() == 0
    predicted = torch.zeros(12, requires_grad=True)
    loss = window_loss(
        predicted,
        target,
        counts,
        w.threshold_on,
        w.threshold_off,
        torch.ones(12, dtype=torch.bool),
        zero_events,
        silent_weight,
    )
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(predicted.grad).all()
    assert loss == 0


def test_every_pixel_masked_out_is_finite():
    predicted = torch.ones(12, requires_grad=True)
    z = torch.zeros(12)
    loss = window_loss(predicted, z, z, z + 0.2, z + 0.2, torch.zeros(12, dtype=torch.bool))
    loss.backward()
    assert loss == 0 and torch.isfinite(predicted.grad).all()


def test_millions_of_events_in_one_window():
    width, height = 346, 260
    n_events = 3_000_000
    rng = np.random.default_rng(0)
    pixels = rng.integers(0, width * height, n_events)
    on = rng.random(n_events) < 0.7
    codes = pixels * 2 + on
    w = windows_from_codes(codes, [0, 1000], [0, n_events], width, height)
    target, counts = w.log_change(0, 1)
    assert counts.sum() == n_events
    expected = 0.2 * (
        np.bincount(pixels[on], minlength=width * height)
        - np.bincount(pixels[~on], minlength=width * height)
    )
    np.testing.assert_allclose(target.numpy(), expected, atol=1e-3)
    predicted = torch.zeros(width * height, requires_grad=True)
    mask = torch.ones(width * height, dtype=torch.bool)
    loss = window_loss(predicted, target, counts, w.threshold_on, w.threshold_off, mask)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(predicted.grad).all()


def test_microsecond_times_far_from_zero_stay_exact():
    """Two days in, float32 time would be off by seconds; int64 keeps every microsecond."""
    t0 = 2 * 86_400 * 1_000_000 + 123_457
    times = np.array([t0, t0 + 10_000], np.int64)
    assert abs(int(np.float32(t0)) - t0) > 1000  # float32 would be off by milliseconds
    poses = np.repeat(np.eye(4)[None], 2, 0)
    poses[1, 0, 3] = 1.0  # 1 m along x in 10 ms
    track = Poses(times, poses)
    at = track.at(np.array([t0 + 1, t0 + 5_000, t0 + 9_999], np.int64))
    np.testing.assert_allclose(at[:, 0, 3], [1e-4, 0.5, 0.9999], rtol=0, atol=1e-12)
    w = windows_from_codes([2, 3, 5], [t0, t0 + 5_000, t0 + 10_000], [0, 1, 3])
    assert w.frame_times.dtype == np.int64
    on, off = w.counts(1, 2)
    assert on.sum() == 2 and off.sum() == 0


def test_background_is_finite_in_every_direction():
    from evcap.recon.scene.gaussians import Background

    bg = Background(8)
    axes = torch.eye(3)
    dirs = torch.cat([axes, -axes, torch.randn(500, 3, generator=torch.Generator().manual_seed(0))])
    dirs = torch.nn.functional.normalize(dirs, dim=1)
    out = bg(dirs.reshape(2, -1, 3))
    out.sum().backward()
    assert out.shape == (2, 253, 3) and torch.isfinite(out).all()
    assert torch.isfinite(bg.faces.grad).all() and (bg.faces.grad != 0).any()
    torch.testing.assert_close(out, torch.full_like(out, 0.5))  # starts at the anchor level
