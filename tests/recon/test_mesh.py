"""The mesh export's parts on scenes whose surface is known exactly: depth fusion and marching
cubes (recon/mesh/tsdf.py), the texture atlas and its baking (recon/mesh/bake.py)."""

import numpy as np
import pytest

from evcap.recon.mesh.tsdf import Grid, Tsdf, largest_parts, simplified
from evcap.sim.trajectory import look_at

CENTRE, RADIUS = np.array([0.1, -0.05, 0.0]), 0.5
K = np.array([[60.0, 0, 40], [0, 60.0, 30], [0, 0, 1]])
W, H = 80, 60


def sphere_depth(T: np.ndarray, centre=CENTRE, radius=RADIUS) -> np.ndarray:
    """Camera z of the sphere each pixel of the pinhole view sees (0: none)."""
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d = rays @ T[:3, :3].T
    o = T[:3, 3] - centre
    b = (d * o).sum(-1)
    a = (d * d).sum(-1)
    disc = b * b - a * ((o * o).sum() - radius**2)
    s = (-b - np.sqrt(np.maximum(disc, 0))) / a  # along the ray of camera z = 1
    return np.where(disc > 0, s, 0.0)


def orbit(n: int, distance: float = 2.0) -> np.ndarray:
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    eyes = np.stack([np.cos(angles), np.sin(angles), 0.3 * np.sin(3 * angles)], 1) * distance
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = look_at(eyes + CENTRE, np.broadcast_to(CENTRE, eyes.shape))
    T[:, :3, 3] = eyes + CENTRE
    return T


def test_fused_depth_of_a_sphere_gives_the_sphere():
    grid = Grid.around(CENTRE - 0.7, CENTRE + 0.7, 0.02)
    tsdf = Tsdf(grid)
    for T in orbit(24):
        tsdf.integrate(sphere_depth(T), K, T)
    vertices, faces = tsdf.mesh()
    r = np.linalg.norm(vertices - CENTRE, axis=1)
    assert np.abs(r - RADIUS).mean() < 0.01 * RADIUS
    normals = np.cross(*(vertices[faces[:, 1:]] - vertices[faces[:, :1]]).transpose(1, 0, 2))
    outward = ((vertices[faces].mean(1) - CENTRE) * normals).sum(1)
    assert (outward > 0).mean() > 0.99  # the normals face the empty side
    # simplified to a tenth of its triangles, it still lies on the sphere
    fewer_v, fewer_f = simplified(vertices, faces, len(faces) // 10)
    assert len(fewer_f) <= len(faces) // 10 + 10
    r = np.linalg.norm(fewer_v - CENTRE, axis=1)
    assert np.abs(r - RADIUS).mean() < 0.01 * RADIUS


def test_a_floater_some_views_see_through_is_carved_and_pieces_are_dropped():
    grid = Grid.around(CENTRE - 1.2, CENTRE + 1.2, 0.03)
    tsdf = Tsdf(grid)
    floater = CENTRE + np.array([0.0, 0.0, 0.9])
    for k, T in enumerate(orbit(24)):
        depth = sphere_depth(T)
        if k == 0:  # one view shows a blob above the sphere
            blob = sphere_depth(T, floater, 0.1)
            depth = np.where((blob > 0) & ((depth == 0) | (blob < depth)), blob, depth)
        tsdf.integrate(depth, K, T)
    vertices, faces = tsdf.mesh()
    # kept, its surface would lie 0.1 from its centre; the sphere's lies 0.4 from it
    assert np.linalg.norm(vertices - floater, axis=1).min() > 0.3
    # a piece left apart is dropped by its area
    piece = vertices[faces[:4]].reshape(-1, 3) + [0, 0, 3.0]
    v2 = np.concatenate([vertices, piece])
    f2 = np.concatenate([faces, len(vertices) + np.arange(len(piece)).reshape(-1, 3)])
    kept_v, kept_f = largest_parts(v2, f2, 0.05)
    assert len(kept_f) > 0.99 * len(faces) and kept_v[:, 2].max() < 2


def test_a_grid_too_fine_is_refused_with_what_to_do():
    from evcap.errors import InputError

    with pytest.raises(InputError, match=r"larger voxel \(--resolution (\S+) or more\)") as e:
        Grid.around(np.zeros(3), np.ones(3), 0.001)
    fits = float(e.value.args[0].split("--resolution ")[1].split()[0])
    Grid.around(np.zeros(3), np.ones(3), fits)  # what it asks for is enough


def sphere_color(points: np.ndarray) -> np.ndarray:
    """A smooth color over the sphere: each channel a function of the direction."""
    d = (points - CENTRE) / RADIUS
    return np.stack([0.5 + 0.4 * d[..., 0], 0.5 + 0.4 * d[..., 2], 0.3 + 0.2 * d[..., 1]], -1)


def sphere_view(T: np.ndarray):
    from evcap.recon.mesh.bake import View

    depth = sphere_depth(T)
    v, u = np.mgrid[0:H, 0:W]
    cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    world = (cam * depth[..., None]) @ T[:3, :3].T + T[:3, 3]
    alpha = (depth > 0).astype(float)
    return View(T, K, depth, alpha, sphere_color(world) * alpha[..., None])


def test_baked_texture_holds_the_surface_color():
    from evcap.recon.mesh.bake import atlas, bake, sample, texels, texture

    grid = Grid.around(CENTRE - 0.7, CENTRE + 0.7, 0.04)
    tsdf = Tsdf(grid)
    poses = orbit(16)
    for T in poses:
        tsdf.integrate(sphere_depth(T), K, T)
    vertices, faces = tsdf.mesh()
    a = atlas(vertices, faces, 256)
    assert a.uv.min() >= 0 and a.uv.max() <= 1
    t = texels(a, 256)
    values, seen = bake(t, [sphere_view(T) for T in poses], tolerance=0.04, min_alpha=0.5)
    assert seen.mean() > 0.9
    image = texture(t, values, seen)
    at_vertices = sample(image, a.uv)
    # the vertices lie on the fused surface, up to a voxel off the true one
    out = a.vertices - CENTRE
    truth = sphere_color(CENTRE + RADIUS * out / np.linalg.norm(out, axis=1, keepdims=True))
    assert np.abs(at_vertices - truth).mean() < 0.02
