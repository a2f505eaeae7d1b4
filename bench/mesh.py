"""`evcap export`'s mesh against the truth of a simulated scene: the exported asset as a user
gets it (the .glb written and read back), scored where the cameras saw the scene.

    .venv/bin/python bench/mesh.py OUT [--session S] [--scene single_object] [--resolution V]
        [--bounds X0 Y0 Z0 X1 Y1 Z1] [--views N] [--texture-size S] [--name mesh]

- Chamfer distance: points sampled over the exported mesh to the true surface, and points of the
  true surface some camera of the path saw (in its view, nothing in front) to the mesh; each
  direction's mean distance, their mean, as a share of the object's radius (the true seen
  surface's bounding sphere). Distances to the nearest of 2 M points sampled over the other
  surface (--samples; at 2 M on single_object their spacing adds under 0.1 % of the radius).
- The mesh's vertices: the distance of each to the true seen surface, its median and 90th
  percentile as a share of the radius.
- Normals: the mesh's at its sampled points against the true surface's at the nearest point.
- The held-out views ray-cast through the mesh (each sensor pixel's ray, its lens included):
  the base color texture where the ray meets the mesh, scored as stage II's maps are scored
  (recon/evaluate/metrics.py: on the truth's surface, PSNR after a gain and offset per channel
  fitted once over the views), beside stage II's own maps of the same views; depth and
  normals there.
- The .glb read back by pygltflib: every texture present.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import RESULTS, machine, scene_file

from evcap.recon.mesh.config import MeshConfig
from evcap.recon.mesh.export import MeshAsset, export_mesh, read_glb

PATH_VIEWS = 40  # cameras of the path that decide which of the truth was seen


def truth_surface(scene: str, track, optics, samples: int, seed: int = 0):
    """(points [P, 3], normals [P, 3]) of the true surface that some camera of the path saw
    (inside the pinhole view that holds the sensor's pixels, nothing in front)."""
    from evcap.recon.scene.optics import render_grid
    from evcap.sim.meshes import build_mesh, sample_surface
    from evcap.sim.raytrace import Bvh
    from evcap.sim.scene import load_scene

    grid = render_grid(optics, 1.0)
    K, size = grid.K.numpy().astype(np.float64), (grid.width, grid.height)
    mesh = build_mesh(load_scene(scene_file(scene)))[0]
    points, normals, _ = sample_surface(mesh, samples, seed=seed)
    bvh = Bvh(mesh.vertices, mesh.faces)
    seen = np.zeros(len(points), bool)
    for T in track.at(np.linspace(track.start, track.end, PATH_VIEWS).astype(np.int64)):
        c = T[:3, 3]
        cam = (points - c) @ T[:3, :3]
        z = np.maximum(cam[:, 2], 1e-9)
        u, v = K[0, 0] * cam[:, 0] / z + K[0, 2], K[1, 1] * cam[:, 1] / z + K[1, 2]
        inside = (cam[:, 2] > 0) & (u >= 0) & (u < size[0]) & (v >= 0) & (v < size[1])
        facing = ((c - points) * normals).sum(1) > 0
        idx = np.flatnonzero(inside & facing & ~seen)
        d = points[idx] - c
        dist = np.linalg.norm(d, axis=1)
        blocked = bvh.occluded(c, d / dist[:, None], dist * (1 - 1e-4))
        seen[idx[~blocked]] = True
    return points[seen], normals[seen]


def surface_figures(
    asset: MeshAsset, points: np.ndarray, normals: np.ndarray, samples: int
) -> dict:
    """Chamfer distance and normals of the mesh against the true seen surface."""
    import trimesh
    from scipy.spatial import cKDTree

    mesh = trimesh.Trimesh(asset.vertices, asset.faces, process=False)
    on_mesh, face = trimesh.sample.sample_surface(mesh, samples, seed=1)
    to_truth, nearest = cKDTree(points).query(on_mesh, workers=-1)
    to_mesh, _ = cKDTree(on_mesh).query(points, workers=-1)
    vertex_off, _ = cKDTree(points).query(asset.vertices, workers=-1)
    centre = 0.5 * (points.min(0) + points.max(0))
    radius = float(np.linalg.norm(points - centre, axis=1).max())
    n = mesh.face_normals[face]
    angle = np.degrees(np.arccos(np.clip((n * normals[nearest]).sum(1), -1, 1)))
    return {
        "radius": radius,
        "chamfer": float((to_truth.mean() + to_mesh.mean()) / 2),
        "chamfer_pct_radius": float(100 * (to_truth.mean() + to_mesh.mean()) / 2 / radius),
        "mesh_to_truth_pct_radius": float(100 * to_truth.mean() / radius),
        "truth_to_mesh_pct_radius": float(100 * to_mesh.mean() / radius),
        "truth_covered_within_1pct": float((to_mesh <= 0.01 * radius).mean()),
        # where the mesh's vertices lie: a skirt or a sheet shows in the upper percentiles
        "vertices_median_pct_radius": float(100 * np.median(vertex_off) / radius),
        "vertices_p90_pct_radius": float(100 * np.percentile(vertex_off, 90) / radius),
        "normal_mae_deg": float(angle.mean()),
        "normal_median_deg": float(np.median(angle)),
    }


def ray_cast(asset: MeshAsset, poses: np.ndarray, optics) -> dict[str, np.ndarray]:
    """The held-out views through the mesh at the sensor's pixels: base color, depth (camera
    z) and normals (camera frame, facing the camera); 0 where a ray meets no triangle."""
    from evcap.sim.raytrace import Bvh

    bvh = Bvh(asset.vertices, asset.faces)
    xy = optics.undistorted()
    rays = np.c_[xy, np.ones(len(xy))]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    tri = asset.vertices[asset.faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    face_n /= np.maximum(np.linalg.norm(face_n, axis=1, keepdims=True), 1e-12)
    H, W = optics.height, optics.width
    out = {k: [] for k in ("base_color", "depth", "normal")}
    for T in poses:
        d = rays @ T[:3, :3].T
        t, face, u, v = bvh.closest(T[:3, 3], d)
        hit = face >= 0
        f = asset.faces[face[hit]]
        w = np.stack([1 - u[hit] - v[hit], u[hit], v[hit]], 1)
        uv = (asset.uv[f] * w[..., None]).sum(1)
        base = np.zeros((H * W, 3))
        base[hit] = asset.base_color_at(uv)
        depth = np.zeros(H * W)
        depth[hit] = t[hit] * rays[hit, 2]
        n_cam = face_n[face[hit]] @ T[:3, :3]
        n_cam *= -np.sign((n_cam * rays[hit]).sum(1, keepdims=True))
        normal = np.zeros((H * W, 3))
        normal[hit] = n_cam
        out["base_color"].append(base.reshape(H, W, 3))
        out["depth"].append(depth.reshape(H, W))
        out["normal"].append(normal.reshape(H, W, 3))
    return {k: np.stack(v) for k, v in out.items()}


def view_figures(asset: MeshAsset, out: Path, session: Path) -> dict:
    """The mesh's base color, depth and normals in the held-out views, and stage II's maps of
    the same views scored the same way."""
    from evcap.recon.evaluate.metrics import depth_rel_err, normal_mae_deg, surface_metrics
    from evcap.recon.scene.optics import SensorOptics
    from evcap.records import GroundTruth
    from evcap.records.reconstruction_folder import ReconstructionFolder
    from evcap.session import Session

    with Session.open(session) as s:
        optics = SensorOptics.from_session(s)
        truth = GroundTruth.read(s).held_out_views()
    if truth.base_color is None:
        return {}
    views = ray_cast(asset, truth.T_world_cam, optics)
    surface = np.linalg.norm(truth.normal, axis=-1) > 0.5
    figures = {
        "mesh_" + k: v
        for k, v in surface_metrics(
            views["base_color"], truth.base_color, surface, "base_color"
        ).items()
    }
    figures["mesh_depth_rel_err"] = depth_rel_err(views["depth"], truth.depth)
    figures["mesh_view_normal_mae_deg"] = normal_mae_deg(views["normal"], truth.normal)
    figures["mesh_hit_share"] = float((views["depth"][surface] > 0).mean())
    maps = ReconstructionFolder(out).views_values("material", "test")
    if maps.exists():
        stage2 = np.load(maps)["base_color"]
        same = surface_metrics(stage2, truth.base_color, surface, "base_color")
        figures["stage2_base_color_psnr_gain"] = same["base_color_psnr_gain"]
        figures["stage2_base_color_psnr"] = same["base_color_psnr"]
    return figures


def glb_figures(asset: MeshAsset, folder: Path) -> tuple[dict, MeshAsset]:
    """The asset written as a .glb, validated and read back (what the figures score)."""
    import pygltflib

    path = folder / "mesh.glb"
    asset.write(path)
    gltf = pygltflib.GLTF2().load(str(path))
    pbr = gltf.materials[0].pbrMetallicRoughness
    textures = [pbr.baseColorTexture, pbr.metallicRoughnessTexture]
    figures = {
        "glb_bytes": path.stat().st_size,
        "glb_textures": sum(t is not None for t in textures),
        "glb_images": len(gltf.images),
        "glb_metallic": pbr.metallicFactor,
    }
    back = read_glb(path)
    back.base_color_from, back.voxel = asset.base_color_from, asset.voxel
    return figures, back


def main(argv: list[str] | None = None) -> dict:
    from evcap.recon.scene.optics import SensorOptics
    from evcap.records import Poses
    from evcap.records.reconstruction_folder import ReconstructionFolder
    from evcap.session import Session

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", metavar="OUT", help="a reconstruction folder")
    parser.add_argument("--session", help="its session (default: the one it names)")
    parser.add_argument("--scene", help="the simulated scene (default: the session's)")
    parser.add_argument("--resolution", type=float, help="the voxel size (scene units)")
    parser.add_argument("--bounds", type=float, nargs=6, help="the box kept (evcap export's)")
    parser.add_argument("--views", type=int, default=MeshConfig.views)
    parser.add_argument("--texture-size", type=int, default=MeshConfig.texture_size)
    parser.add_argument("--samples", type=int, default=2_000_000, help="points over each surface")
    parser.add_argument("--name", default="mesh", help="the results' file name")
    args = parser.parse_args(argv)
    folder = ReconstructionFolder(args.out)
    session = Path(args.session) if args.session else folder.session()
    with Session.open(session) as s:
        scene = args.scene or str(s.attrs.get("scene_file") or s.attrs["scene"])
        optics = SensorOptics.from_session(s)
        track = Poses.read_file(folder.poses) if folder.poses.exists() else Poses.read(s)
    bounds = (tuple(args.bounds[:3]), tuple(args.bounds[3:])) if args.bounds else None
    config = MeshConfig(
        voxel=args.resolution, bounds=bounds, views=args.views, texture_size=args.texture_size
    )
    started = time.perf_counter()
    asset = export_mesh(folder.root, session, config, lambda m: print(m, flush=True))
    seconds = time.perf_counter() - started
    print(asset.summary(), f"({seconds:.0f} s)", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        glb, asset = glb_figures(asset, Path(tmp))
    points, normals = truth_surface(scene, track, optics, args.samples)
    run = folder.read_result().to_json() if folder.finished() else {}
    figures = {
        "out": str(folder.root),
        "scene": scene,
        "bounds": args.bounds,
        "export_seconds": seconds,
        "vertices": len(asset.vertices),
        "triangles": len(asset.faces),
        "voxel": asset.voxel,
        **glb,
        **surface_figures(asset, points, normals, args.samples),
        **view_figures(asset, folder.root, session),
        "stage2_metrics_base_color_psnr_gain": run.get("base_color_psnr_gain"),
        "stage1_depth_rel_err": run.get("depth_rel_err"),
        "stage1_normal_mae_deg": run.get("radiance_normal_mae_deg") or run.get("normal_mae_deg"),
    }
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{args.name}.json"
    path.write_text(json.dumps({"benchmark": args.name, "machine": machine(), **figures}, indent=2))
    for k, v in figures.items():
        print(f"{k}: {v:.4g}" if isinstance(v, float) else f"{k}: {v}")
    print(f"-> {path}")
    return figures


if __name__ == "__main__":
    main()
