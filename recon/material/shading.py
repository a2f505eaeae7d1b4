"""Stage II's light and reflectance: the environment as a cube map, Cook-Torrance GGX (metallic
0) in the split-sum approximation, and the integrals over a fixed set of directions that let
visibility sit inside the diffuse integral.

Why a cube map for the light: it is the representation of the distant background that stage I
already learnt from the events, and what the camera sees of its surroundings is the light that
falls on the scene; so the light starts from it (spherical harmonics would smear a horizon or a
sun into rings). Specular reads a box-filtered mip level whose texels are as wide as the GGX
lobe; diffuse sums the light over 256 fixed directions (the coarse level a texel per direction),
each weighted by the visibility baked for the Gaussian and by the cosine.
"""

from __future__ import annotations

import functools
import itertools
import math

import torch
import torch.nn.functional as F

from evcap.recon.scene.cube_map import bilinear, cube_coordinates, cube_lookup, texels_of

F0 = 0.04  # normal-incidence Fresnel reflectance of a dielectric: the model has no metals
MIN_ROUGHNESS = 0.04
DIFFUSE_DIRECTIONS = 256


def fibonacci_directions(n: int) -> torch.Tensor:
    """[n, 3] nearly uniform unit directions: equal bands of height, golden-angle turns."""
    k = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * k / n
    turn = math.pi * (3 - math.sqrt(5)) * k
    ring = (1 - z * z).sqrt()
    return torch.stack([ring * turn.cos(), ring * turn.sin(), z], 1).float()


def prefiltered(levels: list[torch.Tensor], dirs: torch.Tensor, roughness: torch.Tensor):
    """Light [N, 3] arriving around directions [N, 3] through a GGX lobe of ``roughness`` [N]:
    read at the mip level whose texel is as wide as the lobe (alpha = roughness^2 radians),
    blended between the two nearest levels."""
    size = levels[0].shape[-1]
    alpha = roughness.clamp(min=MIN_ROUGHNESS) ** 2
    level = torch.log2((size * alpha / (math.pi / 2)).clamp(min=1)).clamp(max=len(levels) - 1)
    lo = level.floor().long()
    frac = (level - lo)[:, None]
    hi = (lo + 1).clamp(max=len(levels) - 1)
    sizes, offsets = _level_layout(tuple(f.shape[-1] for f in levels), dirs.device)
    texels = torch.cat([texels_of(f) for f in levels])
    face, uv = cube_coordinates(dirs)
    low = bilinear(texels, face, uv, sizes[lo], offsets[lo])
    high = bilinear(texels, face, uv, sizes[hi], offsets[hi])
    return low * (1 - frac) + high * frac


@functools.cache
def _level_layout(sizes: tuple[int, ...], device: torch.device) -> tuple[torch.Tensor, ...]:
    """Each mip level's size and first texel row in the levels' texels, on ``device`` (made
    once: a copy to a GPU waits for it)."""
    offsets = list(itertools.accumulate((6 * s**2 for s in sizes[:-1]), initial=0))
    return torch.tensor(sizes, device=device), torch.tensor(offsets, device=device)


@functools.cache
def dfg_table(size: int = 32, samples: int = 4096) -> torch.Tensor:
    """The split-sum table [n.v, roughness] -> (A, B): specular = prefiltered * (F0 A + B),
    the GGX BRDF with Schlick's Fresnel integrated over the hemisphere for a white light:
    half vectors drawn from the GGX distribution on a stratified grid (``samples`` per cell)."""
    side = int(math.sqrt(samples))
    u = (torch.arange(side, dtype=torch.float64) + 0.5) / side
    u1, u2 = (g.reshape(-1) for g in torch.meshgrid(u, u, indexing="ij"))
    c = (torch.arange(size, dtype=torch.float64) + 0.5) / size
    ndv, rough = c[:, None, None], c[None, :, None]
    alpha = rough.clamp(min=0.02) ** 2
    a2 = alpha * alpha
    cos_h = ((1 - u2) / (1 + (a2 - 1) * u2)).sqrt()  # [1, R, S]
    sin_h = (1 - cos_h**2).sqrt()
    phi = 2 * math.pi * u1
    sin_v = (1 - ndv * ndv).sqrt()
    # the view in the tangent plane's x-z: v = (sin_v, 0, ndv); light = reflect(v, h)
    vdh = sin_v * sin_h * phi.cos() + ndv * cos_h  # [V, R, S]
    ndl = 2 * vdh * cos_h - ndv
    k = a2  # Smith's separable G with k = alpha^2, as the shading's specular lobe
    g1 = lambda c: 2 * c / (c + (k + (1 - k) * c * c).sqrt())  # noqa: E731
    valid = (ndl > 0) & (vdh > 0)
    weight = torch.where(
        valid, g1(ndv) * g1(ndl.clamp(min=0)) * vdh / (cos_h * ndv).clamp(min=1e-12), 0
    )
    fresnel = (1 - vdh.clamp(0, 1)) ** 5
    a = ((1 - fresnel) * weight).mean(-1)
    b = (fresnel * weight).mean(-1)
    return torch.stack([a, b], -1).float()


@functools.cache
def _dfg_image(device: torch.device) -> torch.Tensor:
    """The DFG table [1, 2, n.v, roughness] on ``device``, copied there once (a copy a call
    would make the GPU wait for the host)."""
    return dfg_table().permute(2, 0, 1)[None].contiguous().to(device)


def split_sum(ndv: torch.Tensor, roughness: torch.Tensor) -> torch.Tensor:
    """F0 A + B [N] from the DFG table, bilinear in (n.v, roughness)."""
    table = _dfg_image(ndv.device)
    grid = torch.stack([roughness * 2 - 1, ndv * 2 - 1], -1).reshape(1, 1, -1, 2)
    ab = F.grid_sample(table, grid, align_corners=False, padding_mode="border")[0, :, 0]
    return F0 * ab[0] + ab[1]


def shade(
    base_color: torch.Tensor,
    roughness: torch.Tensor,
    normals: torch.Tensor,
    view: torch.Tensor,
    light: list[torch.Tensor],
    directions: torch.Tensor,
    visibility: torch.Tensor | None = None,
    indirect: torch.Tensor | None = None,
    bounce: torch.Tensor | None = None,
) -> torch.Tensor:
    """Outgoing radiance [N, 3] of points with base color [N, 3], roughness [N], unit normals
    [N, 3] facing the viewer and unit directions to the viewer ``view`` [N, 3], under the light
    ``light`` (mip_chain of the environment's radiance):

        diffuse  = base / pi * sum_k L(w_k) V(w_k) max(n.w_k, 0) 4 pi / K   (+ indirect, bounce)
        specular = prefiltered(reflect(v, n), roughness) (F0 A + B) * (cos-weighted V)

    ``visibility`` [N, K] in [0, 1] at ``directions`` [K, 3] (None: nothing blocks the light);
    ``indirect`` [N, 3] irradiance from other surfaces, added to the diffuse light in the share
    of the hemisphere that the visibility says is blocked; ``bounce`` [N, 3] irradiance from
    the surfaces that block it, added as it is."""
    sky = _coarse_sky(light, directions)  # [K, 3]
    cos = (normals @ directions.T).clamp(min=0)  # [N, K]
    weight = 4 * math.pi / len(directions)
    if visibility is not None:
        open_cos = cos * visibility
        spec_vis = open_cos.sum(1) / cos.sum(1).clamp(min=1e-8)
    else:
        open_cos, spec_vis = cos, torch.ones_like(roughness)
    irradiance = open_cos @ sky * weight
    if indirect is not None:
        irradiance = irradiance + indirect * (1 - spec_vis)[:, None]
    if bounce is not None:
        irradiance = irradiance + bounce
    ndv = (normals * view).sum(1).clamp(1e-4, 1)
    reflected = F.normalize(2 * ndv[:, None] * normals - view, dim=1)
    specular = prefiltered(light, reflected, roughness) * split_sum(ndv, roughness)[:, None]
    return base_color / math.pi * irradiance + specular * spec_vis[:, None]


def diffuse_both_sides(
    base_color: torch.Tensor,
    normals: torch.Tensor,
    light: list[torch.Tensor],
    directions: torch.Tensor,
    visibility: torch.Tensor,
) -> torch.Tensor:
    """[2N, 3] the diffuse radiance leaving each surface (base color [N, 3], unit normals
    [N, 3]) from its front (row 2 i: the side its normal points to) and its back (2 i + 1),
    lit by the light where ``visibility`` [N, K] lets it through."""
    front = irradiance(light, normals, directions, visibility)
    back = irradiance(light, -normals, directions, visibility)
    return (base_color[:, None] / math.pi * torch.stack([front, back], 1)).reshape(-1, 3)


def irradiance(
    light: list[torch.Tensor],
    normals: torch.Tensor,
    directions: torch.Tensor,
    visibility: torch.Tensor | None = None,
) -> torch.Tensor:
    """[N, 3] irradiance at unit normals [N, 3] from the light, where ``visibility`` [N, K]
    lets it through (None: nothing blocks it)."""
    cos = (normals @ directions.T).clamp(min=0)
    if visibility is not None:
        cos = cos * visibility
    return cos @ _coarse_sky(light, directions) * (4 * math.pi / len(directions))


def _coarse_sky(light: list[torch.Tensor], directions: torch.Tensor) -> torch.Tensor:
    """[K, 3] the light at ``directions``, read from its first mip level of at most 8 texels."""
    return cube_lookup(next(f for f in light if f.shape[-1] <= 8), directions)
