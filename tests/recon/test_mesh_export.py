"""`evcap export` end to end on a reconstruction folder whose fields are the truth's: Gaussians
sampled over the simulated sphere (stage I) with a base color and roughness known at every
point (stage II), beside the session they were "made from". The mesh lies on the sphere, the
textures hold the material, and each format opens."""

import numpy as np
import pytest
import torch

from evcap.errors import InputError
from evcap.images import srgb
from evcap.recon.export import save_checkpoint, save_material_checkpoint
from evcap.recon.gaussians import Background, Gaussians
from evcap.recon.material import MaterialField
from evcap.recon.mesh_export import Z_UP_TO_Y_UP, MeshConfig, export_mesh
from evcap.recon.radiance import RadianceField
from evcap.recon.shading import MIN_ROUGHNESS
from evcap.records.reconstruction_folder import ReconstructionFolder
from evcap.sim.meshes import build_mesh, sample_surface
from evcap.sim.scene import load_scene
from evcap.sim.simulate import simulate

RADIUS = 0.6  # tests/conftest.py's sphere, at the origin
# the tiny scene's 48 x 36 views rendered at 4 times its focal length: pixels of 1 cm there
SMALL = MeshConfig(voxels_across=64, views=16, texture_size=256, render_scale=4.0)


def base_color(points: np.ndarray) -> np.ndarray:
    """A smooth color over the sphere."""
    d = points / RADIUS
    return np.stack([0.5 + 0.4 * d[..., 0], 0.5 + 0.4 * d[..., 2], 0.3 + 0.2 * d[..., 1]], -1)


def roughness(points: np.ndarray) -> np.ndarray:
    return 0.5 + 0.3 * points[..., 2] / RADIUS


@pytest.fixture(scope="module")
def reconstruction(tiny_scene, tmp_path_factory):
    folder = tmp_path_factory.mktemp("export")
    scene = load_scene(tiny_scene())
    simulate(scene, folder / "s.h5")
    points, normals, spacing = sample_surface(build_mesh(scene)[0], 6000)
    g = Gaussians.on_surface(points, normals, spacing, sh_degree=0)
    out = ReconstructionFolder(folder / "recon")
    out.checkpoint("radiance").parent.mkdir(parents=True)
    save_checkpoint(RadianceField(g, Background(8)), {}, out.checkpoint("radiance"))
    field = MaterialField(g, Background(8), torch.as_tensor(normals).float(), None, False)
    with torch.no_grad():
        field.base_logits.copy_(torch.logit(torch.as_tensor(base_color(points)).float()))
        r = (torch.as_tensor(roughness(points)).float() - MIN_ROUGHNESS) / (1 - MIN_ROUGHNESS)
        field.roughness_logits.copy_(torch.logit(r.clamp(1e-4, 1 - 1e-4)))
    save_material_checkpoint(field, out.checkpoint("material"))
    out.write_config({"reconstruct": {"session": str(folder / "s.h5")}})
    return out.root


@pytest.fixture(scope="module")
def asset(reconstruction):
    return export_mesh(reconstruction, config=SMALL)


def test_the_mesh_lies_on_the_sphere_and_faces_out(asset):
    r = np.linalg.norm(asset.vertices, axis=1)
    # the fusion itself is exact to 1 % (tests/recon/test_mesh.py); the Gaussians' depth is
    # each one's centre's, and flat discs on a curved surface lie outside it: about 1.5 % here
    assert np.median(np.abs(r - RADIUS)) < 0.02 * RADIUS
    outward = (asset.normals() * asset.vertices).sum(1) / r
    assert np.median(outward) > 0.98
    assert asset.base_color_from == "stage II" and asset.seen_share > 0.8


def test_the_textures_hold_the_material(asset):
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
    loaded = trimesh.load(path, force="mesh")
    # y up: the world's z came out as y
    assert np.allclose(np.sort(loaded.vertices[:, 1]), np.sort(asset.vertices[:, 2]), atol=1e-5)
    assert np.allclose(Z_UP_TO_Y_UP @ [0, 0, 1], [0, 1, 0])
    # the texture read back where a vertex's texture coordinates point: its base color
    image = np.asarray(loaded.visual.material.baseColorTexture.convert("RGB")) / 255.0
    uv = loaded.visual.uv  # trimesh's: v up
    rows = np.clip(((1 - uv[:, 1]) * image.shape[0]).astype(int), 0, image.shape[0] - 1)
    cols = np.clip((uv[:, 0] * image.shape[1]).astype(int), 0, image.shape[1] - 1)
    expected = srgb(asset.base_color_at(asset.uv))
    assert np.abs(image[rows, cols] - expected).mean() < 0.03


def test_obj_and_ply_are_written_beside_their_textures(asset, tmp_path):
    import trimesh

    written = asset.write(tmp_path / "asset.obj")
    names = {p.name for p in written}
    assert "asset.obj" in names and "asset.mtl" in names and any(n.endswith(".png") for n in names)
    mesh = trimesh.load(tmp_path / "asset.obj", force="mesh")
    assert len(mesh.faces) == len(asset.faces)
    asset.write(tmp_path / "asset.ply")
    ply = trimesh.load(tmp_path / "asset.ply", process=False)
    assert len(ply.vertices) == len(asset.vertices)
    assert ply.visual.vertex_colors[:, :3].std() > 5  # the checker's two colors
    with pytest.raises(InputError, match=r"\.glb, \.obj or \.ply"):
        asset.write(tmp_path / "asset.fbx")


def test_a_folder_without_a_reconstruction_is_refused(tmp_path):
    with pytest.raises(InputError, match="not a reconstruction folder"):
        export_mesh(tmp_path)
    (tmp_path / "config.toml").write_text("[reconstruct]\n")
    with pytest.raises(InputError, match="stage I has not finished"):
        export_mesh(tmp_path)


def test_the_viewer_draws_the_mesh_in_a_browser(reconstruction, screenshot):
    from evcap.records.reconstruction_folder import ReconstructionFolder
    from evcap.report.viewer import write_folder_viewer

    folder = ReconstructionFolder(reconstruction)
    folder.mesh.unlink(missing_ok=True)
    page = write_folder_viewer(reconstruction, config=SMALL, say=lambda _: None)
    assert page == folder.viewer and folder.mesh.exists()  # the mesh exported on the way
    text = page.read_text()
    for ref in ("http://", "https://", 'src="/'):
        assert ref not in text
    image = screenshot(page, 640, 480).astype(float)
    background = image[-5:, -5:].reshape(-1, 3).mean(0)
    # the view starts at the path's first camera, looking at the middle of the mesh
    centre = image[200:280, 280:360].reshape(-1, 3)
    assert np.abs(centre - background).sum(1).mean() > 60
    # the base color: the mesh's pixels vary as the texture does, not one flat color
    assert centre.std(0).max() > 3


def test_the_report_links_the_viewer(reconstruction):
    from evcap.records.reconstruction_folder import ReconstructionFolder
    from evcap.report.html import _viewer_link

    folder = ReconstructionFolder(reconstruction)
    folder.viewer.unlink(missing_ok=True)
    assert "evcap view OUT" in _viewer_link(folder)
    folder.viewer.write_text("<html></html>")
    assert 'href="viewer.html"' in _viewer_link(folder)


def test_evcap_export_and_view_from_the_command_line(reconstruction, tmp_path, capsys):
    from evcap.app.cli import main

    small = ["--views", "8", "--texture-size", "128", "--resolution", "0.03"]
    assert main(["export", str(reconstruction), "-o", str(tmp_path / "a.glb"), *small]) == 0
    assert (tmp_path / "a.glb").stat().st_size > 0
    assert "triangles" in capsys.readouterr().out
    assert main(["export", str(reconstruction), "-o", str(tmp_path / "a.fbx")]) != 0
    assert ".glb, .obj or .ply" in capsys.readouterr().err
    assert main(["export", str(reconstruction), "-o", str(tmp_path / "b.glb"), "--views", "0"]) != 0
    assert "--views must be at least 1" in capsys.readouterr().err
    assert main(["view", str(reconstruction), "--no-open", *small]) == 0
    assert "viewer.html" in capsys.readouterr().out
