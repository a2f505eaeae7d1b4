"""`evcap export` and `evcap view` end to end on a reconstruction folder whose fields are the
truth's (tests/conftest.py, surface_reconstruction): the mesh lies on the sphere, the textures
hold the material, each format opens, and the viewer draws in a browser."""

import numpy as np
import pytest

from evcap.errors import InputError
from evcap.images import srgb
from evcap.recon.mesh.config import MeshConfig
from evcap.recon.mesh.export import export_mesh, read_glb

RADIUS = 0.6  # tests/conftest.py's sphere, at the origin
# the tiny scene's 48 x 36 views rendered at 4 times its focal length: pixels of 1 cm there
SMALL = MeshConfig(voxels_across=64, views=16, texture_size=256, render_scale=4.0)


@pytest.fixture(scope="module")
def asset(surface_reconstruction):
    return export_mesh(surface_reconstruction, config=SMALL)


def test_the_mesh_lies_on_the_sphere_and_faces_out(asset):
    r = np.linalg.norm(asset.vertices, axis=1)
    # the fusion itself is exact to 1 % (tests/recon/test_mesh.py); the Gaussians' depth is
    # each one's centre's, and flat discs on a curved surface lie outside it: about 1.5 % here
    assert np.median(np.abs(r - RADIUS)) < 0.02 * RADIUS
    outward = (asset.normals * asset.vertices).sum(1) / r
    assert np.median(outward) > 0.98
    # the atlas splits vertices along its seams: each copy keeps the surface's one normal
    _, first, which = np.unique(asset.vertices, axis=0, return_index=True, return_inverse=True)
    assert len(first) < len(asset.vertices)
    assert np.allclose(asset.normals, asset.normals[first][which.ravel()])
    assert asset.base_color_from == "stage II" and asset.seen_share > 0.8


def test_the_textures_hold_the_material(asset, surface_material):
    base_color, roughness = surface_material
    on_sphere = asset.vertices * (RADIUS / np.linalg.norm(asset.vertices, axis=1, keepdims=True))
    error = np.abs(asset.base_color_at(asset.uv) - base_color(on_sphere))
    assert np.median(error) < 0.02
    rough = asset.roughness_at(asset.uv)
    assert np.median(np.abs(rough - roughness(on_sphere))) < 0.02


def test_the_glb_validates_with_every_texture(asset, tmp_path):
    import pygltflib
    import trimesh

    path = tmp_path / "asset.glb"
    assert asset.write(path) == [path]
    gltf = pygltflib.GLTF2().load(str(path))
    material = gltf.materials[0]
    pbr = material.pbrMetallicRoughness
    assert pbr.metallicFactor == 0 and pbr.baseColorTexture is not None
    assert pbr.metallicRoughnessTexture is not None
    assert len(gltf.images) == 2 and len(gltf.textures) == 2
    attributes = gltf.meshes[0].primitives[0].attributes
    assert None not in (attributes.POSITION, attributes.NORMAL, attributes.TEXCOORD_0)
    loaded = trimesh.load(path, force="mesh", process=False)
    # y up: the world's z came out as y, its y as -z
    x, y, z = asset.vertices.T
    assert np.allclose(loaded.vertices, np.stack([x, z, -y], 1), atol=1e-5)
    # the texture read back where a vertex's texture coordinates point: its base color
    image = np.asarray(loaded.visual.material.baseColorTexture.convert("RGB")) / 255.0
    uv = loaded.visual.uv  # trimesh's: v up
    rows = np.clip(((1 - uv[:, 1]) * image.shape[0]).astype(int), 0, image.shape[0] - 1)
    cols = np.clip((uv[:, 0] * image.shape[1]).astype(int), 0, image.shape[1] - 1)
    expected = srgb(asset.base_color_at(asset.uv))
    assert np.abs(image[rows, cols] - expected).mean() < 0.03
    # and read back into the world's frame as it was
    back = read_glb(path)
    assert np.allclose(back.vertices, asset.vertices, atol=1e-5)
    assert np.allclose(back.normals, asset.normals, atol=1e-3)
    assert np.allclose(back.uv, asset.uv, atol=1e-6) and np.array_equal(back.faces, asset.faces)
    assert np.abs(back.roughness - asset.roughness).max() < 1 / 255 + 1e-9


def test_obj_and_ply_are_written_beside_their_textures(asset, tmp_path):
    import trimesh
    from PIL import Image

    written = asset.write(tmp_path / "asset.obj")
    names = {p.name for p in written}
    assert names == {"asset.obj", "asset.mtl", "asset_base_color.png", "asset_roughness.png"}
    mtl = (tmp_path / "asset.mtl").read_text()
    assert "map_Kd asset_base_color.png" in mtl and "map_Pr asset_roughness.png" in mtl
    rough = np.asarray(Image.open(tmp_path / "asset_roughness.png"), float) / 255
    assert np.abs(rough - asset.roughness).max() < 1 / 255 + 1e-9
    mesh = trimesh.load(tmp_path / "asset.obj", force="mesh")
    assert len(mesh.faces) == len(asset.faces)
    asset.write(tmp_path / "asset.ply")
    ply = trimesh.load(tmp_path / "asset.ply", process=False)
    assert len(ply.vertices) == len(asset.vertices)
    assert ply.visual.vertex_colors[:, :3].std() > 5  # the base color varies over the sphere
    stored = ply.metadata["_ply_raw"]["vertex"]["data"]["roughness"]  # the property as written
    assert np.allclose(stored, asset.roughness_at(asset.uv), atol=1e-6)
    with pytest.raises(InputError, match=r"\.glb, \.obj or \.ply"):
        asset.write(tmp_path / "asset.fbx")


def test_a_broken_glb_is_refused_with_what_to_do(tmp_path):
    from evcap.recon.mesh.export import read_glb

    broken = (("noise.glb", bytes(range(256)) * 4), ("cut.glb", b"glTF" + b"\0" * 40))
    for name, data in (*broken, ("empty.glb", b""), ("short.glb", b"glTF\2\0")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputError, match="delete it and run again"):
            read_glb(tmp_path / name)


def test_a_folder_without_a_reconstruction_is_refused(tmp_path):
    with pytest.raises(InputError, match="not a reconstruction folder"):
        export_mesh(tmp_path)
    (tmp_path / "config.toml").write_text("[reconstruct]\n")
    with pytest.raises(InputError, match="stage I has not finished"):
        export_mesh(tmp_path)


def test_the_viewer_draws_the_mesh_in_a_browser(surface_reconstruction, screenshot):
    from evcap.app.view import write_folder_viewer
    from evcap.records.reconstruction_folder import ReconstructionFolder

    folder = ReconstructionFolder(surface_reconstruction)
    folder.mesh.unlink(missing_ok=True)
    page = write_folder_viewer(surface_reconstruction, config=SMALL, say=lambda _: None)
    assert page == folder.viewer and folder.mesh.exists()  # the mesh exported on the way
    text = page.read_text()
    for ref in ("http://", "https://", 'src="/'):
        assert ref not in text
    image = screenshot(page, 640, 480).astype(float)
    background = image[:5, -5:].reshape(-1, 3).mean(0)
    # the view starts at the path's first camera, looking at the middle of the mesh
    centre = image[200:280, 280:360].reshape(-1, 3)
    assert np.abs(centre - background).sum(1).mean() > 60
    # the base color: the mesh's pixels vary as the texture does, not one flat color
    assert centre.std(0).max() > 3


def test_the_report_links_the_viewer(surface_reconstruction):
    from evcap.records.reconstruction_folder import ReconstructionFolder
    from evcap.report.html import _viewer_link

    folder = ReconstructionFolder(surface_reconstruction)
    folder.viewer.unlink(missing_ok=True)
    assert "evcap view OUT" in _viewer_link(folder)
    folder.viewer.write_text("<html></html>")
    assert 'href="viewer.html"' in _viewer_link(folder)


def test_evcap_export_and_view_from_the_command_line(surface_reconstruction, tmp_path, capsys):
    from evcap.app.cli import main

    out = str(surface_reconstruction)
    small = ["--views", "8", "--texture-size", "128", "--resolution", "0.03"]
    assert main(["export", out, "-o", str(tmp_path / "a.glb"), *small]) == 0
    assert (tmp_path / "a.glb").stat().st_size > 0
    assert "triangles" in capsys.readouterr().out
    assert main(["export", out, "-o", str(tmp_path / "a.fbx")]) != 0
    assert ".glb, .obj or .ply" in capsys.readouterr().err
    assert main(["export", out, "-o", str(tmp_path / "b.glb"), "--views", "0"]) != 0
    assert "--views must be at least 1" in capsys.readouterr().err
    assert main(["view", out, "--no-open", *small]) == 0
    assert "viewer.html" in capsys.readouterr().out


def test_the_viewer_makes_the_mesh_again_only_when_it_is_out_of_date(surface_reconstruction):
    import os

    from evcap.app.view import _export_again
    from evcap.records.reconstruction_folder import ReconstructionFolder

    folder = ReconstructionFolder(surface_reconstruction)
    folder.mesh.unlink(missing_ok=True)
    assert "no mesh.glb yet" in _export_again(folder, None)
    export_mesh(folder.root, config=SMALL).write(folder.mesh)
    assert _export_again(folder, None) is None
    assert _export_again(folder, MeshConfig()) is None  # the defaults ask nothing new
    assert "options" in _export_again(folder, SMALL)
    ended = folder.checkpoint("material").stat().st_mtime
    os.utime(folder.mesh, (ended - 60, ended - 60))  # exported before stage II ended
    assert "older than the reconstruction" in _export_again(folder, None)


def test_bounds_keep_only_their_box(surface_reconstruction):
    import dataclasses

    upper = dataclasses.replace(SMALL, bounds=((-1.0, -1.0, 0.1), (1.0, 1.0, 1.0)))
    asset = export_mesh(surface_reconstruction, config=upper)
    assert asset.vertices[:, 2].min() >= 0.1 - 1e-6
    assert asset.vertices[:, 2].max() > 0.5  # the sphere's top is in
    empty = dataclasses.replace(SMALL, bounds=((5.0, 5.0, 5.0), (6.0, 6.0, 6.0)))
    with pytest.raises(InputError, match="no opaque surface inside --bounds"):
        export_mesh(surface_reconstruction, config=empty)
