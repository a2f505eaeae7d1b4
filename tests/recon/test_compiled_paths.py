"""The CPU's compiled paths against the PyTorch references they stand in for (what runs on a
GPU): the surface terms, the cube map lookup, the read at the sensor's pixels, and the event
table's two searches against a plain count of the events (the event loss's compiled pass:
test_event_loss.py)."""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from evcap.recon.events.windows import EventWindows
from evcap.recon.material.shading import prefiltered
from evcap.recon.radiance import losses
from evcap.recon.radiance._surface_terms_cpu import surface_terms_cpu
from evcap.recon.scene._sample_cpu import Sampler, _rows_times, _rows_times_few
from evcap.recon.scene.cube_map import cube_lookup, mip_chain


def surface_maps(seed: int = 0) -> list[torch.Tensor]:
    """A render's normal, depth, alpha and second moment with what the terms treat apart: a
    depth jump, an empty band (depth 0), pixels under half opaque, a band of no spread."""
    g = torch.Generator().manual_seed(seed)
    H, W = 40, 52
    yy, xx = torch.meshgrid(torch.arange(H).float(), torch.arange(W).float(), indexing="ij")
    depth = (
        2 + 0.3 * torch.sin(xx / 7) + 0.2 * torch.cos(yy / 5) + 0.05 * torch.rand(H, W, generator=g)
    )
    depth[5:9, 10:20] += 1.0
    depth[0:3] = 0
    alpha = torch.rand(H, W, generator=g) * 0.6 + 0.45
    normal = torch.randn(H, W, 3, generator=g)
    moment = depth**2 * alpha * (1 + 0.1 * torch.rand(H, W, generator=g))
    moment[10:12] = 0.5 * depth[10:12] ** 2 * alpha[10:12]
    return [t.requires_grad_(True) for t in (normal, depth, alpha, moment)]


K = torch.tensor([[50.0, 0, 25.3], [0, 48.0, 19.7], [0, 0, 1]])


@pytest.mark.parametrize(
    "which", [(True, True, True), (True, False, False), (False, True, False), (False, False, True)]
)
def test_surface_terms_match_the_losses(which):
    ref, fast = surface_maps(), surface_maps()
    zero = torch.zeros(())
    expected = torch.stack(
        [
            losses.normal_loss(ref[0], ref[1], ref[2], K) if which[0] else zero,
            losses.depth_spread_loss(ref[3], ref[1], ref[2]) if which[1] else zero,
            losses.normal_smoothness_loss(ref[0], ref[1], ref[2], 0.02) if which[2] else zero,
        ]
    )
    got = surface_terms_cpu(*fast, K, 0.02, which)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)
    weights = torch.tensor([0.7, 1.3, -0.4])
    (expected * weights).sum().backward()
    (got * weights).sum().backward()
    for name, a, b in zip(("normal", "depth", "alpha", "moment"), ref, fast, strict=True):
        want = a.grad if a.grad is not None else torch.zeros_like(a)
        torch.testing.assert_close(b.grad, want, rtol=1e-4, atol=1e-7, msg=name)
    assert got[0] > 0 if which[0] else got[0] == 0


def test_surface_terms_of_an_empty_render_are_zero_and_finite():
    maps = [torch.zeros(6, 5, 3), torch.zeros(6, 5), torch.zeros(6, 5), torch.zeros(6, 5)]
    maps = [m.requires_grad_(True) for m in maps]
    out = surface_terms_cpu(*maps, K, 0.02, (True, True, True))
    out.sum().backward()
    assert (out == 0).all() and all(torch.isfinite(m.grad).all() for m in maps)


def cube_reference(faces: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """The cube map read with grid_sample, face by face."""
    d = dirs.reshape(-1, 3)
    axis = d.abs().argmax(1)
    major = d.gather(1, axis[:, None]).squeeze(1)
    face = axis * 2 + (major < 0)
    others = torch.tensor([[1, 2], [0, 2], [0, 1]])[axis]
    uv = d.gather(1, others) / major.abs()[:, None]
    out = torch.zeros(len(d), faces.shape[1])
    for f in range(6):
        sel = face == f
        grid = uv[sel].reshape(1, 1, -1, 2)
        texels = F.grid_sample(faces[f : f + 1], grid, align_corners=False, padding_mode="border")
        out[sel] = texels[0, :, 0].T
    return out


def directions(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    d = F.normalize(torch.randn(n, 3, generator=g), dim=1)
    edges = torch.tensor([[1.0, 1, 1], [1, -1, 0], [0, 1, -1], [0, 0, -1], [1e-9, 1, 0]])
    return torch.cat([d, F.normalize(edges, dim=1)])


@pytest.mark.parametrize("size", [1, 2, 5, 16])
def test_cube_lookups_match_grid_sample(size):
    g = torch.Generator().manual_seed(size)
    faces = torch.randn(6, 3, size, size, generator=g, requires_grad=True)
    d = directions(3000)
    reference = cube_reference(faces, d)
    gathered = cube_lookup(faces, d.clone().requires_grad_(True))  # PyTorch's gathers
    compiled = cube_lookup(faces, d)  # no gradient to the directions: the compiled pass
    grad = torch.randn(reference.shape, generator=g)
    want = torch.autograd.grad(reference, faces, grad)[0]
    for out in (gathered, compiled):
        torch.testing.assert_close(out, reference, rtol=1e-5, atol=2e-5)
        torch.testing.assert_close(
            torch.autograd.grad(out, faces, grad)[0], want, atol=2e-4, rtol=1e-4
        )


def test_prefiltered_blends_the_two_nearest_levels():
    g = torch.Generator().manual_seed(0)
    levels = mip_chain(torch.rand(6, 3, 16, 16, generator=g))
    d = directions(500)
    rough = torch.rand(len(d), generator=g)
    size = 16
    level = torch.log2((size * rough.clamp(min=0.04) ** 2 / (math.pi / 2)).clamp(min=1))
    level = level.clamp(max=len(levels) - 1)
    lo = level.floor().long()
    frac = (level - lo)[:, None]
    expected = torch.stack(
        [
            cube_reference(levels[int(a)], d[i : i + 1])[0] * (1 - frac[i])
            + cube_reference(levels[min(int(a) + 1, len(levels) - 1)], d[i : i + 1])[0] * frac[i]
            for i, a in enumerate(lo)
        ]
    )
    torch.testing.assert_close(prefiltered(levels, d, rough), expected, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("channels", [1, 3, 4, 6])
def test_sensor_sampling_matches_grid_sample(channels):
    g = torch.Generator().manual_seed(0)
    h, w, sensor = 30, 41, 700
    # inside the render and a little past its border (a lens's corners)
    grid = torch.rand(1, 1, sensor, 2, generator=g) * 2.1 - 1.05
    image = torch.rand(h, w, channels, generator=g, requires_grad=True)
    expected = F.grid_sample(
        image.permute(2, 0, 1)[None], grid, padding_mode="border", align_corners=True
    )[0, :, 0].T
    got = Sampler.of_grid(grid, w, h)(image)
    torch.testing.assert_close(got, expected, atol=1e-6, rtol=1e-5)
    grad = torch.randn(expected.shape, generator=g)
    torch.testing.assert_close(
        torch.autograd.grad(got, image, grad)[0],
        torch.autograd.grad(expected, image, grad)[0],
        atol=1e-5,
        rtol=1e-5,
    )


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_sensor_sampling_of_few_channels_sums_as_the_general_product(channels):
    g = torch.Generator().manual_seed(channels)
    sampler = Sampler.of_grid(torch.rand(1, 1, 500, 2, generator=g) * 2 - 1, 23, 17)
    render = torch.randn(23 * 17, 5, generator=g).numpy()[:, :channels]  # strided, as it comes
    sensor = torch.randn(500, channels, generator=g).numpy()
    for rows, x in ((sampler.forward, render), (sampler.backward, sensor)):
        few, general = (np.empty((len(rows.start) - 1, channels), np.float32) for _ in "ab")
        _rows_times_few(rows.start, rows.column, rows.weight, x, few)
        _rows_times(rows.start, rows.column, rows.weight, x, general)
        np.testing.assert_array_equal(few, general)


@pytest.mark.parametrize("seed", [0, 1])
def test_event_counts_from_the_table_match_a_plain_count(random_events, seed):
    width, height, times, t, codes, starts = random_events(seed)
    c = torch.full((width * height,), 0.2)
    windows = EventWindows.from_codes(width, height, times, codes, starts, c, c)
    rng = np.random.default_rng(seed + 10)
    frames = np.sort(rng.integers(0, len(times), 5))
    frames[0] = 0
    frames[-1] = len(times) - 1
    by_rows = windows.before_by_rows(frames)
    by_search = windows.before_by_search(frames)
    assert torch.equal(by_rows, by_search)
    for a, b in zip(frames[:-1], frames[1:], strict=True):
        inside = codes[starts[a] : starts[b]]
        plain = np.bincount(inside, minlength=2 * width * height).reshape(-1, 2)
        on, off = windows.between(by_rows[list(frames).index(a)], by_rows[list(frames).index(b)])
        np.testing.assert_array_equal(on.numpy(), plain[:, 1])
        np.testing.assert_array_equal(off.numpy(), plain[:, 0])
    assert windows.events == starts[-1] - starts[0]
    # 16 bytes a distinct (pixel, polarity, interval), and a row start a pixel and polarity
    distinct = len(windows.keys)
    assert distinct < len(t) and windows.nbytes() == 16 * distinct + 8 + 8 * (
        2 * width * height + 1
    )
