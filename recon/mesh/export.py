"""`evcap export`: a reconstruction as a textured mesh, the asset a digitization team keeps.

The depth of stage I's Gaussians, rendered along the camera path, is fused into a truncated
signed distance volume (recon/mesh/tsdf.py) whose zero level is the mesh, cleaned of floaters; stage
II's base color and roughness, rendered from the same views, are baked into textures
(recon/mesh/bake.py). glTF 2.0's metallic-roughness material is the method's BRDF (GGX, metallic 0),
so the textures are its base color and roughness as they are.

Formats: .glb (glTF 2.0, binary: baseColorTexture in sRGB, metallicRoughnessTexture with
roughness in G and metallic 0 in B); .obj (with its .mtl and two PNGs beside it, named after it:
the base color as map_Kd, the roughness as map_Pr, the MTL's PBR extension that Blender reads);
.ply (vertex colors: the base color at each vertex, and a roughness property). Positions are in
the session's units (metres where its poses are metric). The world's z is up; glTF's y is up
by definition, so the .glb holds the world turned about x (x, y, z) -> (x, z, -y), which
importers (Blender's among them) turn back; .obj and .ply hold the world's axes as they are.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from evcap.atomic_write import atomic_path
from evcap.errors import InputError
from evcap.images import srgb
from evcap.recon.mesh.bake import View, atlas, bake, sample, texels, texture
from evcap.recon.mesh.config import MeshConfig
from evcap.recon.mesh.tsdf import Grid, Tsdf, largest_parts, simplified
from evcap.records import Poses
from evcap.records.reconstruction_folder import ReconstructionFolder

FORMATS = (".glb", ".obj", ".ply")
LOOK = "is stage I's object recovered? its report shows it (`evcap report OUT`)"
# the world (z up) as glTF's frame (y up): x stays, y <- z, z <- -y
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])


@dataclass
class MeshAsset:
    """A textured mesh in the world's frame."""

    vertices: np.ndarray  # [V, 3]
    faces: np.ndarray  # [F, 3]
    normals: np.ndarray  # [V, 3] unit, smooth across the atlas's seams
    uv: np.ndarray  # [V, 2], v down
    base_color: np.ndarray  # [S, S, 3] linear, 0..1
    roughness: np.ndarray  # [S, S] 0..1
    base_color_from: str  # "stage II" or "stage I's radiance (stage II not run)"
    voxel: float
    views: int
    seen_share: float  # of the texels, seen by some view

    def base_color_at(self, uv: np.ndarray) -> np.ndarray:
        """[N, 3] linear base color at texture coordinates [N, 2]."""
        return sample(self.base_color, uv)

    def roughness_at(self, uv: np.ndarray) -> np.ndarray:
        return sample(self.roughness[..., None], uv)[:, 0]

    def summary(self) -> str:
        return (
            f"{len(self.vertices):,} vertices, {len(self.faces):,} triangles (voxel "
            f"{self.voxel:.4g}, {self.views} views); {self.base_color.shape[0]} px textures: "
            f"base color from {self.base_color_from}, {self.seen_share:.0%} of the texels seen"
        )

    def write(self, path: str | Path) -> list[Path]:
        """The asset as ``path`` (.glb, .obj or .ply); returns the files written."""
        path = Path(path)
        if path.suffix.lower() not in FORMATS:
            raise InputError(f"{path}: write .glb, .obj or .ply (not '{path.suffix}')")
        path.parent.mkdir(parents=True, exist_ok=True)
        return {".glb": _write_glb, ".obj": _write_obj, ".ply": _write_ply}[path.suffix.lower()](
            self, path
        )


def read_glb(path: str | Path) -> MeshAsset:
    """A .glb written by MeshAsset.write, back in the world's frame (what `evcap view` shows)."""
    import trimesh

    from evcap.images import srgb_to_linear

    try:
        # the scene's one mesh as stored (force="mesh" would recompute its normals)
        scene = trimesh.load(path, process=False)
        meshes = list(scene.geometry.values()) if isinstance(scene, trimesh.Scene) else [scene]
        if len(meshes) != 1:
            raise ValueError(f"{len(meshes)} meshes, one expected")
        mesh = meshes[0]
        material = mesh.visual.material
        base = np.asarray(material.baseColorTexture.convert("RGB"), np.float64) / 255
        mr = np.asarray(material.metallicRoughnessTexture.convert("RGB"), np.float64) / 255
        uv = np.asarray(mesh.visual.uv, np.float64).reshape(len(mesh.vertices), 2)
    except (ValueError, AttributeError, OSError, KeyError, IndexError, NotImplementedError) as e:
        raise InputError(
            f"{path}: not a mesh written by `evcap export` ({e}); delete it and run again"
        ) from None
    return MeshAsset(
        np.asarray(mesh.vertices) @ Z_UP_TO_Y_UP,  # the inverse of the rotation written
        np.asarray(mesh.faces),
        np.asarray(mesh.vertex_normals) @ Z_UP_TO_Y_UP,
        np.stack([uv[:, 0], 1 - uv[:, 1]], 1),
        srgb_to_linear(base),
        mr[..., 1],
        "the .glb",
        float("nan"),
        0,
        float("nan"),
    )


def export_mesh(
    out: str | Path,
    session: str | Path | None = None,
    config: MeshConfig | None = None,
    progress: Callable[[str], None] | None = None,
) -> MeshAsset:
    """The mesh of the reconstruction folder ``out`` (its session: the one it was made from)."""
    from evcap.recon.export import load_checkpoint, load_material_checkpoint
    from evcap.recon.scene.optics import SensorOptics, render_grid
    from evcap.session import Session

    config = config or MeshConfig()
    say = progress or (lambda _: None)
    folder = ReconstructionFolder(out)
    folder.check()
    if not folder.checkpoint("radiance").exists():
        raise InputError(f"{folder.root}: stage I has not finished; run `evcap reconstruct` first")
    session_path = Path(session) if session is not None else folder.session()
    with Session.open(session_path) as s:
        optics = SensorOptics.from_session(s)
        track = Poses.read_file(folder.poses) if folder.poses.exists() else Poses.read(s)
    material = folder.checkpoint("material").exists()
    if material:
        field = load_material_checkpoint(folder.checkpoint("material"))
    else:
        field, _ = load_checkpoint(folder.checkpoint("radiance"))
    grid = render_grid(optics, config.render_scale)
    K = grid.K.cpu().numpy().astype(np.float64)
    times = np.linspace(track.start, track.end, config.views).astype(np.int64)
    say(f"rendering {config.views} views along the camera path")
    views = []
    with torch.no_grad():
        for T in track.at(times):
            r = field.render(T, grid)
            alpha = r.alpha.cpu().numpy().astype(np.float64)
            depth = np.where(alpha >= config.min_alpha, r.depth.cpu().numpy(), 0.0)
            color = r.color.cpu().numpy().astype(np.float64)
            if material:  # base color and roughness; the light behind adds nothing to them
                maps = color[..., 3:7]
            else:  # the radiance less the background showing through
                behind = field.render(T, grid, hidden=True).color.cpu().numpy()
                radiance = color[..., :3] - (1 - alpha[..., None]) * behind[..., :3]
                maps = np.concatenate([radiance, alpha[..., None]], -1)
            # the Gaussians' values, not their blend with what lies behind
            maps = maps / np.maximum(alpha, 1e-6)[..., None]
            views.append(View(T, K, depth, alpha, maps))
    grid3 = _grid_of(views, config)
    say(f"fusing depth into {grid3.shape[0]} x {grid3.shape[1]} x {grid3.shape[2]} voxels")
    tsdf = Tsdf(grid3, config.truncation_voxels)
    for view in views:
        tsdf.integrate(view.depth, view.K, view.T_world_cam)
    vertices, faces = tsdf.mesh()
    if not len(faces):
        raise InputError(f"{folder.root}: no surface found in the reconstruction's depth; {LOOK}")
    vertices, faces = largest_parts(vertices, faces, config.keep_share)
    vertices, faces = simplified(vertices, faces, config.max_triangles)
    say(f"baking {config.texture_size} px textures onto {len(faces):,} triangles")
    normals = _vertex_normals(vertices, faces)  # before the atlas splits its seams
    a = atlas(vertices, faces, config.texture_size)
    t = texels(a, config.texture_size)
    values, seen = bake(t, views, config.depth_tolerance_voxels * grid3.voxel, config.min_alpha)
    image = np.clip(texture(t, values, seen), 0, 1)
    return MeshAsset(
        a.vertices,
        a.faces,
        normals[a.source_vertex],
        a.uv,
        image[..., :3],
        image[..., 3],
        "stage II" if material else "stage I's radiance (stage II not run)",
        grid3.voxel,
        config.views,
        float(seen.mean()) if len(seen) else 0.0,
    )


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    import trimesh

    return np.asarray(trimesh.Trimesh(vertices, faces, process=False).vertex_normals)


def _grid_of(views: list[View], config: MeshConfig) -> Grid:
    """The voxels around what the views see (the middle 99 % of their surface points), or
    within the config's bounds."""
    points = []
    for view in views:
        v, u = np.nonzero(view.depth > 0)
        z = view.depth[v, u]
        cam = np.stack([(u - view.K[0, 2]) / view.K[0, 0], (v - view.K[1, 2]) / view.K[1, 1]], 1)
        cam = np.concatenate([cam * z[:, None], z[:, None]], 1)
        points.append(cam[::7] @ view.T_world_cam[:3, :3].T + view.T_world_cam[:3, 3])
    points = np.concatenate(points)
    if config.bounds is not None:
        lo, hi = (np.asarray(b, np.float64) for b in config.bounds)
        if not (hi > lo).all():
            raise InputError(f"--bounds: each of the max corner {hi} must exceed the min {lo}")
        points = points[((points >= lo) & (points <= hi)).all(1)]
    if len(points) < 100:
        where = " inside --bounds" if config.bounds is not None else ""
        raise InputError(
            f"the reconstruction renders no opaque surface{where} along the camera path; {LOOK}"
        )
    lo, hi = np.percentile(points, 0.5, axis=0), np.percentile(points, 99.5, axis=0)
    extent = float((hi - lo).max())
    voxel = config.voxel or extent / config.voxels_across
    if config.bounds is not None:  # the box as it is: what lies outside is not wanted
        return Grid.around(*(np.asarray(b, np.float64) for b in config.bounds), voxel)
    margin = 0.05 * extent + 2 * config.truncation_voxels * voxel
    return Grid.around(lo - margin, hi + margin, voxel)


# -- the formats -----------------------------------------------------------------------------


def _images(asset: MeshAsset):
    """(base color as an sRGB PIL image, metallic-roughness as glTF has it: G roughness, B 0)."""
    from PIL import Image

    base = (srgb(asset.base_color) * 255 + 0.5).astype(np.uint8)
    mr = np.zeros((*asset.roughness.shape, 3), np.uint8)
    mr[..., 0] = 255  # R: unused by the material (occlusion where packed): none
    mr[..., 1] = (asset.roughness * 255 + 0.5).astype(np.uint8)
    return Image.fromarray(base), Image.fromarray(mr)


def _trimesh(asset: MeshAsset, rotation: np.ndarray | None = None):
    import trimesh
    from trimesh.visual.material import PBRMaterial

    base, mr = _images(asset)
    material = PBRMaterial(
        name="evcap",
        baseColorTexture=base,
        metallicRoughnessTexture=mr,
        metallicFactor=0.0,
        roughnessFactor=1.0,
    )
    R = np.eye(3) if rotation is None else rotation
    # trimesh's uv have v up (it flips them into glTF's v down)
    uv = np.stack([asset.uv[:, 0], 1 - asset.uv[:, 1]], 1)
    visual = trimesh.visual.TextureVisuals(uv=uv, material=material)
    return trimesh.Trimesh(
        asset.vertices @ R.T,
        asset.faces,
        vertex_normals=asset.normals @ R.T,
        visual=visual,
        process=False,
    )


def _write_glb(asset: MeshAsset, path: Path) -> list[Path]:
    from trimesh.exchange.gltf import export_glb

    # with the vertex normals: without them viewers shade each triangle flat
    _write_bytes(path, export_glb(_trimesh(asset, Z_UP_TO_Y_UP), include_normals=True))
    return [path]


def _write_obj(asset: MeshAsset, path: Path) -> list[Path]:
    import io

    from trimesh.exchange.obj import export_obj

    # trimesh's .mtl keeps the base color only: the .mtl is ours, with the roughness
    text, _ = export_obj(
        _trimesh(asset),
        include_normals=True,
        include_texture=True,
        return_texture=True,
        mtl_name=f"{path.stem}.mtl",
    )
    base, mr = _images(asset)
    names = {"map_Kd": f"{path.stem}_base_color.png", "map_Pr": f"{path.stem}_roughness.png"}
    mtl = "newmtl evcap\nKd 1 1 1\nKs 0 0 0\nPm 0\n"
    mtl += "".join(f"{key} {name}\n" for key, name in names.items())
    files = {path: text.encode(), path.with_suffix(".mtl"): mtl.encode()}
    for name, image in ((names["map_Kd"], base), (names["map_Pr"], mr.getchannel("G"))):
        buffer = io.BytesIO()
        image.save(buffer, "PNG")
        files[path.parent / name] = buffer.getvalue()
    for target, data in files.items():
        _write_bytes(target, data)
    return list(files)


def _write_ply(asset: MeshAsset, path: Path) -> list[Path]:
    import trimesh

    color = (srgb(np.clip(asset.base_color_at(asset.uv), 0, 1)) * 255 + 0.5).astype(np.uint8)
    rough = asset.roughness_at(asset.uv).astype(np.float32)
    mesh = trimesh.Trimesh(
        asset.vertices,
        asset.faces,
        vertex_colors=np.concatenate([color, np.full_like(color[:, :1], 255)], 1),
        vertex_attributes={"roughness": rough},
        process=False,
    )
    _write_bytes(path, mesh.export(file_type="ply", include_attributes=True))
    return [path]


def _write_bytes(path: Path, data: bytes) -> None:
    with atomic_path(path) as partial:  # an interrupted write leaves no half a file
        partial.write_bytes(data)
