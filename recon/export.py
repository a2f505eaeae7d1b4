"""What a reconstruction leaves behind: the Gaussians as a 3DGS PLY, rendered views as PNG
(and exact values as .npz) and the checkpoints, where evcap.records.ReconstructionFolder puts
them (it also writes the settings and the figures)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from evcap.atomic_write import atomic_path
from evcap.errors import InputError
from evcap.images import srgb
from evcap.recon.config import Backend
from evcap.recon.material.stage import MaterialField
from evcap.recon.radiance.config import RadianceConfig
from evcap.recon.radiance.stage import RadianceField
from evcap.recon.scene.gaussians import Background, Gaussians
from evcap.recon.scene.sh import C0
from evcap.recon.settings import from_dict
from evcap.records.reconstruction_folder import ReconstructionFolder, Renders, Split


def write_ply(field: RadianceField, path: Path) -> None:
    """The Gaussians in the layout of the 3DGS reference code (binary PLY: x y z nx ny nz
    f_dc_* f_rest_* opacity scale_* rot_*), which existing viewers open.

    Viewers show 0.5 + SH as display color; the field's SH give linear radiance through a
    softplus. The exported coefficients are the display (sRGB) color of the degree-0 part, and
    the higher bands scaled by the slope of that mapping there (first order)."""
    g = field.gaussians
    with torch.no_grad():
        v0 = (C0 * g.sh_dc[:, 0]).double().cpu()
        lin = torch.nn.functional.softplus(v0).clamp(0, 1)
        disp = torch.from_numpy(srgb(lin.numpy()))
        # d display / d v = srgb'(linear) * sigmoid(v)
        eps = 1e-4
        slope = (torch.from_numpy(srgb((lin + eps).numpy())) - disp) / eps * torch.sigmoid(v0)
        f_dc = (disp - 0.5) / C0
        rest = g.sh_rest.double().cpu() * slope[:, None, :]
        cols = [
            g.means.double().cpu(),
            torch.zeros(len(g), 3, dtype=torch.float64),
            f_dc,
            rest.transpose(1, 2).reshape(len(g), -1),  # all of red, then green, then blue
            g.opacity_logits.double().cpu()[:, None],
            g.log_scales.double().cpu(),
            torch.nn.functional.normalize(g.quats.double().cpu(), dim=1),
        ]
        data = torch.cat(cols, 1).float().numpy()
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(rest.shape[1] * 3)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(data)}"]
    header += [f"property float {n}" for n in names] + ["end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode())
        f.write(data.astype("<f4").tobytes())


def read_ply_header(path: Path) -> tuple[int, list[str]]:
    """(vertex count, property names) of a PLY written by write_ply."""
    with open(path, "rb") as f:
        lines = []
        while (line := f.readline().decode().strip()) != "end_header":
            lines.append(line)
    count = next(int(x.split()[-1]) for x in lines if x.startswith("element vertex"))
    return count, [x.split()[-1] for x in lines if x.startswith("property")]


def write_views(
    views: dict[str, np.ndarray],
    out: ReconstructionFolder,
    kind: Renders,
    split: Split,
    gain: np.ndarray | None,
) -> None:
    """PNGs of each view: radiance (sRGB; and after ``gain`` [3] when given), depth
    (16-bit, thousandths of a scene unit), normals ((n + 1) / 2, camera frame), and base color
    (sRGB) and roughness (0..255) when the views have them; the exact values in one .npz."""
    import cv2

    out.renders(kind).mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out.views_values(kind, split), **views)

    def rgb8(x: np.ndarray) -> np.ndarray:
        return (np.clip(x, 0, 1)[..., ::-1] * 255 + 0.5).astype(np.uint8)

    for i in range(len(views["radiance"])):
        images = {
            "radiance": rgb8(srgb(views["radiance"][i])),
            "depth": np.clip(np.round(views["depth"][i] * 1000), 0, 65535).astype(np.uint16),
            "normal": rgb8(views["normal"][i] * 0.5 + 0.5),
        }
        if gain is not None:
            images["radiance_gain"] = rgb8(srgb(views["radiance"][i] * gain))
        if "base_color" in views:
            images["base_color"] = rgb8(srgb(views["base_color"][i]))
        if "roughness" in views:
            rough = np.clip(views["roughness"][i], 0, 1)
            images["roughness"] = (rough * 255 + 0.5).astype(np.uint8)
        for name, image in images.items():
            cv2.imwrite(str(out.view_image(kind, split, i, name)), image)


def write_image(linear: np.ndarray, path: Path) -> None:
    """A linear RGB image [H, W, 3] as an 8-bit sRGB PNG."""
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.clip(srgb(linear), 0, 1)[..., ::-1] * 255 + 0.5
    cv2.imwrite(str(path), img.astype(np.uint8))


def save_checkpoint(field: RadianceField, config: dict, path: Path) -> None:
    """Stage I: the Gaussians, the background and the settings they were fitted with."""
    _save(
        {
            "gaussians": {k: v.detach().cpu() for k, v in field.gaussians.state_dict().items()},
            "background": field.background.faces.detach().cpu(),
            "config": config,
        },
        path,
    )


def save_material_checkpoint(field: MaterialField, path: Path) -> None:
    """Stage II: the material, the light, the baked visibility and which effects were on."""
    state = {k: v.detach().cpu() for k, v in field.state_dict().items()}
    _save({"material": state, "effects": field.effects}, path)


def _save(data: dict, path: Path) -> None:
    with atomic_path(path) as partial:  # a crash mid-write leaves the previous checkpoint
        torch.save(data, partial)


def load_checkpoint(
    path: Path, device: str = "cpu", backend: Backend = "cpu"
) -> tuple[RadianceField, RadianceConfig]:
    """(RadianceField, the settings it was fitted with) from a stage-I checkpoint written by
    save_checkpoint."""
    state = _read_stage_one(path)
    config = _stage_one_config(state, path)
    try:
        gaussians = Gaussians.from_state(state["gaussians"])
        background = Background.from_faces(state["background"])
    except (KeyError, RuntimeError, ValueError) as e:
        raise InputError(f"{path}: not a readable stage-I checkpoint ({e})") from e
    field = RadianceField(gaussians, background, backend, config.background.known, config.surfels)
    return field.to(device), config


def read_stage_one_settings(path: Path) -> RadianceConfig:
    """The settings a stage-I checkpoint was fitted with."""
    return _stage_one_config(_read_stage_one(path), path)


def _read_stage_one(path: Path) -> dict:
    if not path.exists():
        raise InputError(f"{path}: no stage-I checkpoint; run `evcap reconstruct --stage radiance`")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, ValueError, EOFError, OSError) as e:
        raise InputError(f"{path}: not a readable stage-I checkpoint ({e})") from e


def _stage_one_config(state: dict, path: Path) -> RadianceConfig:
    try:
        return from_dict(RadianceConfig, state["config"])
    except (KeyError, TypeError, InputError) as e:
        raise InputError(
            f"{path}: its settings are not those this evcap reads ({e}): an earlier evcap saved "
            "it; fit stage I again (`evcap reconstruct --stage radiance --force`)"
        ) from None


def load_material_checkpoint(
    path: Path, device: str = "cpu", backend: Backend = "cpu"
) -> MaterialField:
    """The stage-II field saved by save_material_checkpoint (its Gaussians included)."""
    if not path.exists():
        raise InputError(f"{path}: no stage-II checkpoint; run `evcap reconstruct` (both stages)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)["material"]
        field = MaterialField.from_state(state, backend)
    except (KeyError, RuntimeError, ValueError) as e:
        raise InputError(f"{path}: not a readable stage-II checkpoint ({e})") from e
    return field.to(device)
