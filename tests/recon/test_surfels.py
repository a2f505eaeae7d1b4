"""Surfels (recon/raster/surfels.py): the torch backend against the per-pixel reference, the
compiled CPU compositing against the torch backend (values and every input's gradient), and
what makes them surfels: a tilted disc's depth is its plane's along every ray, its alpha at
its centre its opacity, and the screen-space gradient densification reads."""

import math

import pytest
import torch
from test_raster_cpu import camera  # the camera its cases are in front of

from evcap.errors import InputError
from evcap.recon.raster._reference import rasterize_surfels_reference
from evcap.recon.raster.rasterize import Camera, rasterize

F64 = torch.float64


def discs(n: int = 30, channels: int = 3, seed: int = 0, case: str = "cloud") -> list:
    """Discs in front of ``camera`` (log scales; the third is unused), some edge-on."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=F64) - 0.5) * 1.2
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    log_scales = math.log(0.08) + 0.4 * torch.randn(n, 3, generator=g, dtype=F64)
    opac = 0.2 + 0.75 * torch.rand(n, generator=g, dtype=F64)
    features = torch.rand(n, channels, generator=g, dtype=F64)
    if case == "edge_on":  # the disc's normal across the view: the screen-space filter shows
        quats[: n // 3] = torch.tensor([0.7071, 0.7071, 0.0, 0.0], dtype=F64)
    elif case == "dense":
        opac[:] = 0.999
        log_scales += 0.7
    return [t.requires_grad_(True) for t in (means, quats, log_scales, opac, features)]


def render(params, cam, backend, depth_squared=False):
    means, quats, log_scales, opac, features = params
    return rasterize(
        means,
        quats,
        log_scales.exp(),
        opac,
        features,
        cam,
        backend=backend,
        surfels=True,
        depth_squared=depth_squared,
    )


def outputs(r) -> torch.Tensor:
    return torch.cat(
        [r.color, r.depth[..., None] * r.alpha[..., None], r.alpha[..., None], r.normal], -1
    )


def gradients(params, cam, backend, weights, depth_squared=False):
    out = render(params, cam, backend, depth_squared)
    (outputs(out) * weights).sum().backward()
    grads = [p.grad.clone() for p in params] + [out.means2d.grad.clone()]
    for p in params:
        p.grad = None
    return outputs(out).detach(), grads


@pytest.mark.parametrize("case", ["cloud", "edge_on"])
def test_torch_matches_the_per_pixel_reference(case):
    params = discs(12, case=case)
    cam = camera(14, 11)
    means, quats, log_scales, opac, features = params
    ref = rasterize_surfels_reference(means, quats, log_scales.exp(), opac, features, cam, 0.01)
    out = render(params, cam, "torch")
    # the boxes (EWA's, widened for the filter) hold all but alpha at the 1/255 cut-off's edge
    assert torch.allclose(outputs(out), outputs(ref), atol=5e-3)
    assert (outputs(out) - outputs(ref)).abs().mean() < 1e-4


@pytest.mark.parametrize("case", ["cloud", "edge_on", "dense", "depth_squared"])
def test_cpu_matches_torch_in_values_and_gradients(case):
    cam = camera(70, 23)
    weights = torch.rand(23, 70, 3 + 1 + 1 + 3, generator=torch.Generator().manual_seed(1))
    weights = weights.to(F64)
    a = discs(40, case=case)
    b = [p.detach().clone().requires_grad_(True) for p in a]
    squared = case == "depth_squared"
    out_t, grads_t = gradients(a, cam, "torch", weights, squared)
    out_c, grads_c = gradients(b, cam, "cpu", weights, squared)
    assert torch.allclose(out_c, out_t, rtol=1e-7, atol=1e-9)
    names = ["means", "quats", "scales", "opacities", "features", "means2d"]
    for name, gt, gc in zip(names, grads_t, grads_c, strict=True):
        assert torch.allclose(gc, gt, rtol=1e-6, atol=1e-8), name


def test_camera_gradient_matches_torch():
    cam = camera(40, 30)
    for backend in ("torch", "cpu"):
        view = cam.viewmat.clone().requires_grad_(True)
        params = discs(20)
        r = render(params, Camera(view, cam.K, 40, 30), backend)
        outputs(r).sum().backward()
        if backend == "torch":
            expected = view.grad.clone()
    assert torch.allclose(view.grad, expected, rtol=1e-6, atol=1e-8)


def test_a_tilted_disc_gives_its_planes_depth_along_every_ray():
    # one large opaque disc tilted 50 degrees about the x axis, 2 units ahead
    cam = Camera(
        torch.eye(4, dtype=F64),
        torch.tensor([[40.0, 0, 20], [0, 40.0, 20], [0, 0, 1]], dtype=F64),
        41,
        41,
    )
    angle = math.radians(50)
    quat = torch.tensor([[math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0]], dtype=F64)
    means = torch.tensor([[0.0, 0.0, 2.0]], dtype=F64)
    scales = torch.tensor([[0.5, 0.5, 1.0]], dtype=F64)
    r_args = (means, quat, scales, torch.tensor([0.99], dtype=F64), torch.ones(1, 1, dtype=F64))
    r_args += (cam,)
    for backend in ("torch", "cpu"):
        r = rasterize(*r_args, backend=backend, surfels=True)
        normal = torch.tensor([0.0, -math.sin(angle), math.cos(angle)], dtype=F64)
        ys, xs = torch.meshgrid(
            torch.arange(41.0, dtype=F64), torch.arange(41.0, dtype=F64), indexing="ij"
        )
        rays = torch.stack([(xs - 20) / 40, (ys - 20) / 40, torch.ones_like(xs)], -1)
        truth = (means[0] @ normal) / (rays @ normal)  # camera z where the ray meets the plane
        opaque = r.alpha > 0.05
        assert opaque.sum() > 200
        assert torch.allclose(r.depth[opaque], truth[opaque], rtol=1e-9)
        assert r.alpha[20, 20] == pytest.approx(0.99)
        squared = rasterize(*r_args, backend=backend, surfels=True, depth_squared=True)
        assert torch.allclose(squared.color[opaque][:, 0], r.depth[opaque] ** 2 * r.alpha[opaque])
        # the normal turned to face the camera
        assert torch.allclose(r.normal[20, 20] / r.alpha[20, 20], -normal, atol=1e-9)


def test_gsplat_refuses_surfels():
    params = discs(3)
    with pytest.raises(InputError, match="surfels"):
        means, quats, log_scales, opac, features = params
        rasterize(
            means,
            quats,
            log_scales.exp(),
            opac,
            features,
            camera(8, 8),
            backend="gsplat",
            surfels=True,
        )
