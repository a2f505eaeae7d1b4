"""How `evcap export` makes a mesh from a reconstruction (export.py): its settings, without
torch (the command line reads their defaults to show them)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class MeshConfig:
    """How the mesh is made from a reconstruction."""

    voxel: float | None = None
    """The fusion's voxel, scene units; None: the surface's extent over voxels_across."""
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    """(min corner, max corner) of the box kept, scene units; None: all the views see."""
    voxels_across: int = 192
    """Voxels across the surface's extent, when no voxel is given."""
    views: int = 60
    """Views along the camera path, fused and baked."""
    render_scale: float = 1.0
    """The views' focal length, relative to the sensor's."""
    truncation_voxels: float = 4.0
    """The signed distance's truncation, in voxels."""
    min_alpha: float = 0.5
    """Less opaque pixels see the background: empty space."""
    keep_share: float = 0.05
    """Parts with less of the largest part's area are floaters, dropped."""
    max_triangles: int = 40_000
    """The mesh simplified to about this many triangles."""
    texture_size: int = 1024
    """The texture atlas's side, pixels."""
    depth_tolerance_voxels: float = 3.0
    """A texel takes what a view sees within this many voxels of it."""
