"""The background as a cube map (+x, -x, +y, -y, +z, -z faces): bilinear reads in world
directions, its texels' directions and its box-filtered mip chain. Stage I's background and stage
II's light are such maps."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def cube_lookup(faces: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Bilinear values [..., C] of a cube map ``faces`` [6, C, S, S] (+x, -x, +y, -y, +z, -z)
    in world directions [..., 3] (as grid_sample with align_corners=False and border padding
    on the face each ray lands on). On the CPU, for directions that take no gradient, one
    compiled pass (recon/scene/_cube_cpu.py)."""
    if faces.device.type == "cpu" and not dirs.requires_grad:
        from evcap.recon.scene._cube_cpu import cube_lookup_cpu

        return cube_lookup_cpu(faces, dirs)
    shape = dirs.shape[:-1]
    face, uv = cube_coordinates(dirs.reshape(-1, 3))
    out = bilinear(texels_of(faces), face, uv, faces.shape[-1], 0)
    return out.reshape(*shape, faces.shape[1])


def cube_coordinates(d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The face [N] each direction [N, 3] lands on, and where on it [N, 2] in [-1, 1]: the two
    other coordinates over the major one."""
    axis = d.abs().argmax(1)
    major = d.gather(1, axis[:, None]).squeeze(1)
    face = axis * 2 + (major < 0)
    # the two other axes: [1, 2], [0, 2] or [0, 1] (made from the axis, not copied from the
    # host: a copy to a GPU waits for it)
    others = torch.stack([(axis == 0).long(), 2 - (axis == 2).long()], 1)
    return face, d.gather(1, others) / major.abs().clamp_min(1e-12)[:, None]


def texels_of(faces: torch.Tensor) -> torch.Tensor:
    """[6 S S, C] a cube map's texels, face by face, row by row."""
    return faces.permute(0, 2, 3, 1).reshape(-1, faces.shape[1])


def bilinear(
    texels: torch.Tensor,
    face: torch.Tensor,
    uv: torch.Tensor,
    size: int | torch.Tensor,
    offset: int | torch.Tensor,
) -> torch.Tensor:
    """[N, C] bilinear reads of faces of ``size`` texels a side (an int, or one per read [N])
    starting at row ``offset`` of ``texels``, at ``uv`` [N, 2] of ``face`` [N]: four gathers and
    their weights, so that no step waits on the device (grid_sample needs the reads of each face
    picked out first)."""
    if isinstance(size, int):
        size = torch.full_like(face, size)
    s = size[:, None].to(uv.dtype)
    p = (((uv + 1) * s - 1) / 2).clamp(min=0)
    p = torch.minimum(p, s - 1)  # border: the edge texels continue outwards
    corner = torch.minimum(p.floor(), (s - 2).clamp(min=0))
    frac = p - corner
    x, y = corner.long().unbind(1)
    row = offset + (face * size + y) * size
    step_x = (size > 1).long()
    step_y = step_x * size
    top = row + x
    fx, fy = frac[:, :1], frac[:, 1:]

    def read(index: torch.Tensor) -> torch.Tensor:
        return texels.index_select(0, index)

    upper = read(top) * (1 - fx) + read(top + step_x) * fx
    lower = read(top + step_y) * (1 - fx) + read(top + step_y + step_x) * fx
    return upper * (1 - fy) + lower * fy


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
