"""The compiled CPU rasterizer against the PyTorch one and the per-pixel reference: each stage
(projection; compositing) and end to end, values and the gradients of every input, over
channel counts, image sizes that are not multiples of the tile, and the hard cases."""

import math

import numpy as np
import pytest
import torch

from evcap.recon.raster import _cpu as _raster_cpu
from evcap.recon.raster import _torch as _raster_torch
from evcap.recon.raster._reference import composite_reference
from evcap.recon.raster.rasterize import Camera, camera_normals, rasterize

F64 = torch.float64


def camera(width, height, dtype=F64):
    view = torch.eye(4, dtype=dtype)
    view[:3, :3] = torch.tensor([[0.96, 0.0, -0.28], [0.0, 1.0, 0.0], [0.28, 0.0, 0.96]])
    view[:3, 3] = torch.tensor([0.1, -0.05, 2.5])
    f = 0.9 * width
    K = torch.tensor(
        [[f, 0, (width - 1) / 2 + 0.3], [0, f * 1.02, (height - 1) / 2 - 0.2], [0, 0, 1]]
    )
    return Camera(view.to(dtype), K.to(dtype), width, height)


def scene(case, n=40, channels=3, seed=0, dtype=F64):
    """Gaussians in front of ``camera``: a cloud, with some of them made hard."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 1.2
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    log_scales = math.log(0.06) + 0.5 * torch.randn(n, 3, generator=g, dtype=dtype)
    opac = 0.2 + 0.75 * torch.rand(n, generator=g, dtype=dtype)
    features = torch.rand(n, channels, generator=g, dtype=dtype)
    some = slice(0, n // 4)
    # the camera's centre in the world: -R^T t
    centre = torch.tensor([-0.1, 0.05, -2.4], dtype=dtype) @ torch.tensor(
        [[0.96, 0.0, -0.28], [0.0, 1.0, 0.0], [0.28, 0.0, 0.96]], dtype=dtype
    )
    if case == "behind":  # behind the camera, and straddling its near plane
        means[some] = centre + (means[some] - centre) * torch.tensor([1.0, 1.0, -1.0], dtype=dtype)
        means[n // 4] = centre + torch.tensor([0.0, 0.0, 0.005], dtype=dtype)
    elif case == "off_screen":  # far to the sides: the clamped Jacobian
        means[some, 0] += torch.linspace(-6, 6, n // 4, dtype=dtype)
        means[some, 1] -= 3
    elif case == "degenerate":  # collapsed to a line or a point, or flat
        log_scales[some] = -25.0
        log_scales[n // 4 : n // 2, 0] = -25.0
    elif case == "huge":
        log_scales[some] = math.log(30.0)
    elif case == "inside":  # the camera inside a few large Gaussians
        means[some] = centre + 0.05 * torch.randn(n // 4, 3, generator=g, dtype=dtype)
        log_scales[some] = math.log(0.6)
    elif case == "dense":  # opaque layers: transmittance runs out, alpha clamps at 0.99
        opac[:] = 0.999
        log_scales += 0.8
    return [t.requires_grad_(True) for t in (means, quats, log_scales, opac, features)]


CASES = ["cloud", "behind", "off_screen", "degenerate", "huge", "inside", "dense"]


def render_all(params, cam, backend, background):
    means, quats, log_scales, opac, features = params
    r = rasterize(
        means, quats, log_scales.exp(), opac, features, cam, background=background, backend=backend
    )
    return r, torch.cat([r.color, r.depth[..., None], r.alpha[..., None], r.normal], -1)


def compare(case, channels, width, height, rtol=1e-7, atol=1e-9):
    params = scene(case, channels=channels)
    background = torch.rand(channels, dtype=F64, generator=torch.Generator().manual_seed(7))
    background.requires_grad_(True)
    outs = {}
    for backend in ("torch", "cpu"):
        cam = camera(width, height)
        cam.viewmat.requires_grad_(True)
        r, maps = render_all(params, cam, backend, background)
        weights = torch.rand(maps.shape, generator=torch.Generator().manual_seed(1), dtype=F64)
        inputs = [*params, cam.viewmat, background, r.means2d]
        grads = torch.autograd.grad((maps * weights).sum(), inputs, allow_unused=True)
        outs[backend] = (r, maps, grads)
    (r_t, maps_t, grads_t), (r_c, maps_c, grads_c) = outs["torch"], outs["cpu"]
    torch.testing.assert_close(maps_c, maps_t, rtol=rtol, atol=atol)
    assert torch.equal(r_c.visible, r_t.visible)
    torch.testing.assert_close(r_c.peak, r_t.peak, rtol=rtol, atol=atol)
    names = ["means", "quats", "log_scales", "opacities", "features", "viewmat", "background"]
    for name, a, b in zip(names + ["means2d"], grads_c, grads_t, strict=True):
        assert a is not None and torch.isfinite(a).all(), name
        torch.testing.assert_close(a, b, rtol=rtol, atol=atol * max(1.0, b.abs().max()), msg=name)
    return r_t


@pytest.mark.parametrize("case", CASES)
def test_end_to_end_matches_torch_in_the_hard_cases(case):
    r = compare(case, 3, 37, 29)
    assert r.alpha.max() > 0.3  # something in view
    if case == "dense":
        assert r.alpha.max() > 1 - 2e-4  # transmittance ran out


@pytest.mark.parametrize("channels", [1, 3, 10])
@pytest.mark.parametrize("size", [(16, 16), (50, 17), (23, 41)], ids=lambda s: f"{s[0]}x{s[1]}")
def test_end_to_end_matches_torch_over_channels_and_sizes(channels, size):
    compare("cloud", channels, *size)


def test_float32_at_the_fast_size_matches_torch():
    """What training runs: float32, 173 x 130, thousands of Gaussians."""
    params = scene("cloud", n=3000, channels=3, seed=2, dtype=torch.float32)
    with torch.no_grad():
        params[2] -= 0.7
    background = torch.full((3,), 0.4)
    out = {}
    for backend in ("torch", "cpu"):
        cam = camera(173, 130, torch.float32)
        r, maps = render_all(params, cam, backend, background)
        grads = torch.autograd.grad(maps.sum(), params)
        out[backend] = (maps, grads)
    (maps_t, grads_t), (maps_c, grads_c) = out["torch"], out["cpu"]
    assert (maps_t[..., 4] > 0.5).float().mean() > 0.3  # alpha: a busy image
    torch.testing.assert_close(maps_c, maps_t, rtol=1e-4, atol=1e-4)
    for a, b in zip(grads_c, grads_t, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-4 * b.abs().max())


@pytest.mark.parametrize("case", CASES)
def test_projection_matches_torch(case):
    """The compiled projection and its hand-written backward pass against autograd through
    the torch backend's projection."""
    means, quats, log_scales, _, _ = scene(case)
    cam = camera(37, 29)
    cam.viewmat.requires_grad_(True)
    scales = log_scales.exp()
    ref = _raster_torch.project(means, quats, scales, cam, 0.01)
    ref_normals = camera_normals(quats, scales, means, cam)
    view = _raster_cpu.camera_arrays(cam, 0.01)
    arrays = [t.detach().numpy() for t in (means, quats, scales)]
    p = _raster_cpu.project(*arrays, view)
    assert (p.valid == ref.valid.numpy()).all()
    if case == "behind":
        assert not p.valid.all()
    v = torch.from_numpy(p.valid[:, None])
    for a, b in ((p.means2d, ref.means2d), (p.depths, ref.depths), (p.normals, ref_normals)):
        torch.testing.assert_close(torch.from_numpy(a), b.detach(), rtol=1e-12, atol=1e-12)
    for a, b in ((p.conics, ref.conics), (p.cov2d, ref.cov2d)):
        torch.testing.assert_close(torch.from_numpy(a) * v, b.detach() * v, rtol=1e-9, atol=1e-12)
    g = torch.Generator().manual_seed(3)
    w = [torch.randn(t.shape, generator=g, dtype=F64) for t in (p.means2d, p.conics, p.depths)]
    w[1] = w[1] * v  # the conics of invalid Gaussians are never used
    w.append(torch.randn(p.normals.shape, generator=g, dtype=F64))
    outs = (ref.means2d, ref.conics, ref.depths, ref_normals)
    loss = sum((o * wi).sum() for o, wi in zip(outs, w, strict=True))
    expected = torch.autograd.grad(loss, [means, quats, scales, cam.viewmat])
    got = list(_raster_cpu.project_backward(*arrays, view, p, *(wi.numpy() for wi in w)))
    got[3] = _raster_cpu.view_gradient(got[3])
    for name, a, b in zip(("means", "quats", "scales", "viewmat"), got, expected, strict=True):
        tol = 1e-10 * max(1.0, b.abs().max())
        torch.testing.assert_close(torch.from_numpy(a), b, rtol=1e-8, atol=tol, msg=name)


def splats(n, width, height, seed, dense=False):
    """Random 2D Gaussians over (and a little beyond) a width x height image."""
    g = torch.Generator().manual_seed(seed)
    means2d = (
        torch.rand(n, 2, generator=g, dtype=F64) * torch.tensor([width + 6.0, height + 6.0]) - 3
    )
    angle = torch.rand(n, generator=g, dtype=F64) * math.pi
    sx, sy = (0.4 + 3 * torch.rand(2, n, generator=g, dtype=F64)).unbind(0)
    if dense:  # opaque and overlapping: transmittance runs out, alpha clamps at 0.99
        sx, sy = 3 * sx, 3 * sy
    c, s = torch.cos(angle), torch.sin(angle)
    cxx, cyy = c * c * sx * sx + s * s * sy * sy, s * s * sx * sx + c * c * sy * sy
    cxy = c * s * (sx * sx - sy * sy)
    det = cxx * cyy - cxy * cxy
    conics = torch.stack([cyy / det, -cxy / det, cxx / det], 1)
    opac = (
        0.999 * torch.ones(n, dtype=F64)
        if dense
        else 0.05 + 0.9 * torch.rand(n, dtype=F64, generator=g)
    )
    depths = torch.rand(n, generator=g, dtype=F64)
    cov2d = torch.stack([cxx, cxy, cyy], 1)
    return means2d, conics, opac, depths, cov2d


@pytest.mark.parametrize(
    "channels, width, height, dense",
    [(1, 19, 13, False), (3, 33, 17, False), (10, 17, 18, False), (4, 21, 9, True)],
)
def test_compositing_matches_the_per_pixel_reference(channels, width, height, dense):
    """The compiled compositing and its hand-written backward pass against autograd through
    the per-pixel reference, on random 2D splats."""
    means2d, conics, opac, depths, cov2d = splats(24, width, height, channels, dense)
    values = torch.rand(24, channels, dtype=F64, generator=torch.Generator().manual_seed(5))
    p = _raster_cpu.Projection(
        means2d.numpy(), conics.numpy(), cov2d.numpy(), depths.numpy(), None, np.ones(24, bool)
    )
    tiles = _raster_cpu.intersect(p, opac.numpy(), width, height)
    result = _raster_cpu.composite(tiles, p.means2d, p.conics, opac.numpy(), values.numpy())
    out = torch.from_numpy(result.out[:, :channels]).reshape(height, width, channels)
    alpha = torch.from_numpy(1 - result.final_t).reshape(height, width)
    leaves = [t.requires_grad_(True) for t in (means2d, conics, opac, values)]
    order = [int(i) for i in torch.argsort(depths)]
    ref_out, ref_alpha = composite_reference(*leaves, order, width, height)
    torch.testing.assert_close(out, ref_out.detach(), rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(alpha, ref_alpha.detach(), rtol=1e-9, atol=1e-12)
    if dense:
        assert ref_alpha.max() > 1 - 2e-4
    g = torch.Generator().manual_seed(6)
    w_out = torch.randn(ref_out.shape, generator=g, dtype=F64)
    w_alpha = torch.randn(ref_alpha.shape, generator=g, dtype=F64)
    expected = torch.autograd.grad((ref_out * w_out).sum() + (ref_alpha * w_alpha).sum(), leaves)
    per = _raster_cpu.composite_backward(
        tiles, result, w_out.reshape(-1, channels).numpy(), w_alpha.ravel().numpy()
    )
    got = (per[:, 0:2], per[:, 2:5], per[:, 5], per[:, 6:])
    for a, b in zip(got, expected, strict=True):
        tol = 1e-10 * max(1.0, b.abs().max())
        torch.testing.assert_close(torch.from_numpy(a), b, rtol=1e-8, atol=tol)


def test_any_number_of_threads_gives_the_same_bits():
    params = scene("cloud", n=400, channels=3, seed=4, dtype=torch.float32)
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            cam = camera(61, 47, torch.float32)
            _, maps = render_all(params, cam, "cpu", None)
            results.append([maps, *torch.autograd.grad(maps.square().sum(), params)])
    finally:
        torch.set_num_threads(before)
    for other in results[1:]:
        for a, b in zip(results[0], other, strict=True):
            assert torch.equal(a, b)


def test_means2d_gradient_reaches_densification():
    params = scene("cloud", n=60, channels=3)
    cam = camera(37, 29)
    r, maps = render_all(params, cam, "cpu", None)
    maps.sum().backward()
    assert r.means2d.grad is not None and r.means2d.grad.shape == (60, 2)
    assert (r.means2d.grad[r.visible].abs().sum(1) > 0).any()
    assert (r.means2d.grad[~r.visible] == 0).all()


def test_torch_threads_are_left_as_set():
    """numba's OpenMP pool, started by the first render, must not change torch's setting."""
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        render_all(scene("cloud", n=10), camera(20, 10), "cpu", None)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
