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
import math

import torch
import torch.nn.functional as F

F0 = 0.04  # normal-incidence Fresnel reflectance of a dielectric
MIN_ROUGHNESS = 0.04
DIFFUSE_DIRECTIONS = 256


def fibonacci_directions(n: int) -> torch.Tensor:
    """[n, 3] nearly uniform unit directions."""
    k = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * k / n
    phi = math.pi * (1 + 5**0.5) * k
    r = torch.sqrt(1 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], 1).float()


def cube_lookup(faces: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Bilinear values [..., C] of a cube map ``faces`` [6, C, S, S] (+x, -x, +y, -y, +z, -z)
    in world directions [..., 3]."""
    shape = dirs.shape[:-1]
    d = dirs.reshape(-1, 3)
    axis = d.abs().argmax(1)
    major = d.gather(1, axis[:, None]).squeeze(1)
    face = axis * 2 + (major < 0)
    # the two other coordinates over the major one: where on that face the ray lands
    others = torch.tensor([[1, 2], [0, 2], [0, 1]], device=d.device)[axis]
    uv = d.gather(1, others) / major.abs().clamp_min(1e-12)[:, None]
    out = torch.zeros(len(d), faces.shape[1], dtype=faces.dtype, device=d.device)
    for f in range(6):
        sel = face == f
        if sel.any():
            grid = uv[sel].reshape(1, 1, -1, 2)
            texels = F.grid_sample(
                faces[f : f + 1], grid, align_corners=False, padding_mode="border"
            )
            out[sel] = texels[0, :, 0].T
    return out.reshape(*shape, faces.shape[1])


def cube_directions(size: int) -> torch.Tensor:
    """[6, size, size, 3] unit directions of the texel centres of a cube map (cube_lookup's
    layout)."""
    c = (torch.arange(size, dtype=torch.float32) + 0.5) / size * 2 - 1
    v, u = torch.meshgrid(c, c, indexing="ij")
    one = torch.ones_like(u)
    out = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            cols = [None, None, None]
            cols[axis] = sign * one
            a, b = [i for i in range(3) if i != axis]
            cols[a], cols[b] = u, v
            out.append(F.normalize(torch.stack(cols, -1), dim=-1))
    return torch.stack(out)


def mip_chain(faces: torch.Tensor) -> list[torch.Tensor]:
    """The cube map and its box-filtered halvings down to 2 x 2."""
    levels = [faces]
    while levels[-1].shape[-1] > 2:
        levels.append(F.avg_pool2d(levels[-1], 2))
    return levels


def prefiltered(levels: list[torch.Tensor], dirs: torch.Tensor, roughness: torch.Tensor):
    """Light [N, 3] arriving around directions [N, 3] through a GGX lobe of ``roughness`` [N]:
    read at the mip level whose texel is as wide as the lobe (alpha = roughness^2 radians),
    blended between the two nearest levels."""
    size = levels[0].shape[-1]
    alpha = roughness.clamp(min=MIN_ROUGHNESS) ** 2
    level = torch.log2((size * alpha / (math.pi / 2)).clamp(min=1)).clamp(max=len(levels) - 1)
    lo = level.floor().long()
    frac = (level - lo)[:, None]
    out = torch.zeros(len(dirs), 3, dtype=dirs.dtype, device=dirs.device)
    for i, faces in enumerate(levels):
        w = torch.where(lo[:, None] == i, 1 - frac, 0) + torch.where(lo[:, None] == i - 1, frac, 0)
        sel = (w > 0).squeeze(1)
        if sel.any():
            out[sel] = out[sel] + w[sel] * cube_lookup(faces, dirs[sel])
    return out


@functools.cache
def dfg_table(size: int = 32, samples: int = 512) -> torch.Tensor:
    """The split-sum table [n.v, roughness] -> (A, B): specular = prefiltered * (F0 A + B),
    integrated by GGX importance sampling on a fixed Hammersley set."""
    i = torch.arange(samples, dtype=torch.float64)
    bits = i.to(torch.int64)
    radical = torch.zeros(samples, dtype=torch.float64)
    for b in range(16):
        radical += ((bits >> b) & 1).double() * 2.0 ** (-b - 1)
    xi1, xi2 = (i + 0.5) / samples, radical
    grid = (torch.arange(size, dtype=torch.float64) + 0.5) / size
    table = torch.zeros(size, size, 2, dtype=torch.float64)
    for a_i, ndv in enumerate(grid):
        v = torch.tensor([math.sqrt(1 - ndv * ndv), 0.0, float(ndv)], dtype=torch.float64)
        for r_i, rough in enumerate(grid):
            a = max(float(rough), MIN_ROUGHNESS) ** 2
            cos_h = torch.sqrt((1 - xi2) / (1 + (a * a - 1) * xi2))
            sin_h = torch.sqrt(1 - cos_h**2)
            phi = 2 * math.pi * xi1
            h = torch.stack([sin_h * torch.cos(phi), sin_h * torch.sin(phi), cos_h], 1)
            vdh = h @ v
            light = 2 * vdh[:, None] * h - v
            ndl = light[:, 2].clamp(0, 1)
            ok = ndl > 0
            g = smith_g(float(ndv), ndl[ok], a)
            g_vis = g * vdh[ok] / (h[ok, 2] * ndv).clamp(min=1e-12)
            fc = (1 - vdh[ok]) ** 5
            table[a_i, r_i, 0] = ((1 - fc) * g_vis).sum() / samples
            table[a_i, r_i, 1] = (fc * g_vis).sum() / samples
    return table.float()


def smith_g(ndv, ndl, alpha: float):
    k = alpha * alpha
    gv = 2 * ndv / (ndv + math.sqrt(k + (1 - k) * ndv * ndv))
    gl = 2 * ndl / (ndl + torch.sqrt(k + (1 - k) * ndl * ndl))
    return gv * gl


def split_sum(ndv: torch.Tensor, roughness: torch.Tensor) -> torch.Tensor:
    """F0 A + B [N] from the DFG table, bilinear in (n.v, roughness)."""
    table = dfg_table().to(ndv.device).permute(2, 0, 1)[None]  # [1, 2, n.v, roughness]
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
) -> torch.Tensor:
    """Outgoing radiance [N, 3] of points with base color [N, 3], roughness [N], unit normals
    [N, 3] facing the viewer and unit directions to the viewer ``view`` [N, 3], under the light
    ``light`` (mip_chain of the environment's radiance):

        diffuse  = base / pi * sum_k L(w_k) V(w_k) max(n.w_k, 0) 4 pi / K   (+ indirect)
        specular = prefiltered(reflect(v, n), roughness) (F0 A + B) * (cos-weighted V)

    ``visibility`` [N, K] in [0, 1] at ``directions`` [K, 3] (None: nothing blocks the light);
    ``indirect`` [N, 3] irradiance from other surfaces, added to the diffuse light in the share
    of the hemisphere that the visibility says is blocked."""
    coarse = next(f for f in light if f.shape[-1] <= 8)
    sky = cube_lookup(coarse, directions)  # [K, 3]
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
    ndv = (normals * view).sum(1).clamp(1e-4, 1)
    reflected = F.normalize(2 * ndv[:, None] * normals - view, dim=1)
    specular = prefiltered(light, reflected, roughness) * split_sum(ndv, roughness)[:, None]
    return base_color / math.pi * irradiance + specular * spec_vis[:, None]
