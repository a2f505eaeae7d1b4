"""The CPU and PyTorch rasterizers against the per-pixel reference (forward and gradients), and
the gsplat backend against the PyTorch one where a GPU is present. The compiled CPU backend's
own stages and hard cases are in test_raster_cpu.py."""

import math

import pytest
import torch

from evcap.errors import NumericalError
from evcap.recon.raster import _torch as _raster_torch
from evcap.recon.raster._reference import rasterize_reference
from evcap.recon.raster.rasterize import Camera, camera_normals, rasterize


def tiny_gaussians(n=7, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g, dtype=dtype) * torch.tensor([1.0, 0.8, 1.0]) - 0.5
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    log_scales = math.log(0.12) + 0.5 * torch.randn(n, 3, generator=g, dtype=dtype)
    opac = 0.3 + 0.69 * torch.rand(n, generator=g, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    return [t.requires_grad_(True) for t in (means, quats, log_scales, opac, colors)]


def tiny_camera(width=14, height=11, dtype=torch.float64):
    view = torch.eye(4, dtype=dtype)
    view[2, 3] = 2.0
    K = torch.tensor([[16.0, 0, 6.5], [0, 15.0, 5.2], [0, 0, 1]], dtype=dtype)
    return Camera(view, K, width, height)


def maps(r):
    return torch.cat(
        [r.color, r.depth[..., None] * r.alpha[..., None], r.alpha[..., None], r.normal], -1
    )


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_backend_matches_the_per_pixel_reference(backend):
    params = tiny_gaussians()
    means, quats, log_scales, opac, colors = params
    cam = tiny_camera()
    cam.viewmat.requires_grad_(True)
    params.append(cam.viewmat)
    out = rasterize(means, quats, log_scales.exp(), opac, colors, cam, backend=backend)
    normals = camera_normals(quats, log_scales.exp(), means, cam)
    ref = rasterize_reference(means, quats, log_scales.exp(), opac, colors, normals, cam, 0.01)
    assert out.alpha.max() > 0.5  # the Gaussians are in view, several overlapping
    torch.testing.assert_close(maps(out), maps(ref), rtol=1e-9, atol=1e-9)
    weights = torch.rand(
        maps(out).shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64
    )
    g_out = torch.autograd.grad((maps(out) * weights).sum(), params)
    g_ref = torch.autograd.grad((maps(ref) * weights).sum(), params)
    for a, b in zip(g_out, g_ref, strict=True):
        assert torch.isfinite(a).all()
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-9)


def test_tiles_give_the_same_image(monkeypatch):
    means, quats, log_scales, opac, colors = tiny_gaussians(n=20, seed=3)
    cam = tiny_camera(31, 23)
    one = rasterize(means, quats, log_scales.exp(), opac, colors, cam, backend="torch")
    monkeypatch.setattr(_raster_torch, "PAIR_BUDGET", 200)
    assert (
        len(
            _raster_torch._bands(
                _raster_torch.project(means, quats, log_scales.exp(), cam, 0.01), opac, 31, 23
            )
        )
        > 3
    )
    tiled = rasterize(means, quats, log_scales.exp(), opac, colors, cam, backend="torch")
    torch.testing.assert_close(maps(tiled), maps(one))


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_pixel_centres_follow_opencv(backend):
    """A small opaque Gaussian on the axis lands on the pixel at (cx, cy)."""
    cam = tiny_camera()
    cam.K[0, 2], cam.K[1, 2] = 4.0, 7.0
    means = torch.tensor([[0.0, 0.0, 0.0]], dtype=torch.float64)
    r = rasterize(
        means,
        torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
        torch.full((1, 3), 0.01, dtype=torch.float64),
        torch.tensor([0.9], dtype=torch.float64),
        torch.ones(1, 3, dtype=torch.float64),
        cam,
        backend=backend,
    )
    y, x = divmod(int(r.alpha.argmax()), cam.width)
    assert (x, y) == (4, 7)
    assert r.depth[7, 4] == pytest.approx(2.0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_gsplat_agrees_with_torch():
    from evcap.recon.raster import _gsplat as _raster_gsplat

    if not _raster_gsplat.available():
        pytest.skip("gsplat is not installed or cannot build its kernels")
    torch.manual_seed(0)
    n = 300
    means = (torch.rand(n, 3) - 0.5) * torch.tensor([1.2, 0.9, 1.0])
    quats = torch.randn(n, 4)
    log_scales = math.log(0.05) + 0.4 * torch.randn(n, 3)
    opac = 0.2 + 0.7 * torch.rand(n)
    colors = torch.rand(n, 3)
    cam = tiny_camera(64, 48, torch.float32)
    cam.K = torch.tensor([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    outs, grads = [], []
    for backend, device in (("torch", "cpu"), ("gsplat", "cuda")):
        params = [
            t.to(device).requires_grad_(True) for t in (means, quats, log_scales, opac, colors)
        ]
        c = Camera(cam.viewmat.to(device), cam.K.to(device), cam.width, cam.height)
        r = rasterize(
            params[0], params[1], params[2].exp(), params[3], params[4], c, backend=backend
        )
        m = maps(r)
        outs.append(m.detach().cpu())
        grads.append([g.cpu() for g in torch.autograd.grad(m.sum(), params)])
    # gsplat cuts splats at 3 sigma in 16-pixel tiles, the torch backend at alpha = 1/255:
    # the images differ only in faint tails
    assert (outs[0] - outs[1]).abs().mean() < 2e-3
    assert (outs[0] - outs[1]).abs().max() < 0.05
    for a, b in zip(grads[0], grads[1], strict=True):
        cos = torch.nn.functional.cosine_similarity(a.flatten(), b.flatten(), dim=0)
        assert cos > 0.98


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_a_non_finite_gaussian_is_refused_not_rendered(backend):
    # a NaN mean rendered a finite image whose gradients were NaN, and nothing said so
    means, quats, log_scales, opac, colors = tiny_gaussians()
    bad = means.detach().clone()
    bad[3, 1] = float("nan")
    with pytest.raises(
        NumericalError, match=r"means not finite \(NaN or infinite\) for 1 of 7 Gaussians"
    ):
        rasterize(bad, quats, log_scales.exp(), opac, colors, tiny_camera(), backend=backend)
    with pytest.raises(ValueError, match=r"quats must be \[7, 4\], not \[7, 3\]"):
        rasterize(means, quats[:, :3], log_scales.exp(), opac, colors, tiny_camera())


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_each_gaussians_largest_blending_weight(backend):
    """Its peak: alpha times the light the Gaussians in front leave, at its best pixel; a
    Gaussian out of view has none."""
    cam = tiny_camera()
    cam.K = torch.tensor([[16.0, 0, 7.0], [0, 16.0, 5.0], [0, 0, 1]], dtype=torch.float64)
    # on the optical axis at depths 2 and 3 (the back one narrower on screen), one far aside
    means = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [9.0, 0.0, 0.0]], dtype=torch.float64)
    scales = torch.tensor([[0.2] * 3, [0.1] * 3, [0.1] * 3], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=torch.float64)
    opac = torch.tensor([0.4, 0.5, 0.9], dtype=torch.float64)
    r = rasterize(means, quats, scales, opac, torch.ones(3, 3, dtype=torch.float64), cam,
                  backend=backend)  # fmt: skip
    torch.testing.assert_close(r.peak, torch.tensor([0.4, 0.5 * 0.6, 0.0], dtype=torch.float64))
