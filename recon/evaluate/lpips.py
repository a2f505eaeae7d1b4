"""LPIPS (Zhang et al., CVPR 2018), the AlexNet-linear form (version 0.1), from weights a user
has: nothing is downloaded. The torchvision AlexNet's convolutions give five feature maps (after
each ReLU); each is scaled to unit length along its channels, the two images' maps are
subtracted and squared, weighted per channel by the published linear heads (1 x 1 convolutions
without bias), averaged over the pixels and summed over the five layers.

The weights: the torchvision AlexNet state dict (``features.0.weight`` ...) and the LPIPS linear
heads (``lin0.model.1.weight`` ... ``lin4``), in one file or two (torch.save'd dicts)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from evcap.errors import InputError

# the input scaling of the published model: images in [-1, 1] to ImageNet's statistics
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
# torchvision AlexNet's convolutions (index in ``features``, stride, padding) and the max-pool
# (3 x 3, stride 2) before the 2nd and 3rd
CONVS = ((0, 4, 2), (3, 1, 2), (6, 1, 1), (8, 1, 1), (10, 1, 1))
POOLED = (1, 2)
CHANNELS = (64, 192, 384, 256, 256)
EPS = 1e-10


class Lpips:
    """LPIPS with the weights in ``paths``; call it on sRGB images [N, H, W, 3] in [0, 1]."""

    def __init__(self, *paths: str | Path, device: str = "cpu") -> None:
        state: dict[str, torch.Tensor] = {}
        for path in paths:
            state.update(_read(Path(path)))
        self.device = device
        convs = (_conv(state, i) for i, _, _ in CONVS)
        self.convs = [(w.to(device), b.to(device)) for w, b in convs]
        self.heads = [_head(state, layer).to(device) for layer in range(len(CONVS))]

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five unit-normalized feature maps of images [N, 3, H, W] in [-1, 1]."""
        shift = torch.tensor(SHIFT, device=x.device)[None, :, None, None]
        scale = torch.tensor(SCALE, device=x.device)[None, :, None, None]
        x = (x - shift) / scale
        out = []
        for layer, ((weight, bias), (_, stride, padding)) in enumerate(
            zip(self.convs, CONVS, strict=True)
        ):
            if layer in POOLED:
                x = F.max_pool2d(x, 3, 2)
            x = F.relu(F.conv2d(x, weight, bias, stride=stride, padding=padding))
            out.append(x / (x.square().sum(1, keepdim=True).sqrt() + EPS))
        return out

    @torch.no_grad()
    def per_image(self, a: np.ndarray, b: np.ndarray, batch: int = 8) -> np.ndarray:
        """LPIPS of each pair of sRGB images [N, H, W, 3] in [0, 1]: [N]."""
        if a.shape != b.shape or a.ndim != 4 or a.shape[-1] != 3:
            raise ValueError(f"LPIPS needs two stacks [N, H, W, 3] alike, got {a.shape}, {b.shape}")
        out = []
        for start in range(0, len(a), batch):
            x, y = (
                torch.as_tensor(np.asarray(v[start : start + batch], np.float32))
                .to(self.device)
                .permute(0, 3, 1, 2)
                .mul(2)
                .sub(1)
                for v in (a, b)
            )
            total = torch.zeros(len(x), device=self.device)
            for fx, fy, head in zip(self.features(x), self.features(y), self.heads, strict=True):
                total += F.conv2d((fx - fy).square(), head).mean((1, 2, 3))
            out.append(total.cpu().numpy())
        return np.concatenate(out)

    def __call__(self, a: np.ndarray, b: np.ndarray) -> float:
        """Mean LPIPS over the pairs of images."""
        return float(self.per_image(a, b).mean())


def _read(path: Path) -> dict[str, torch.Tensor]:
    if not path.is_file():
        raise InputError(f"{path}: no such LPIPS weights file")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001  pickle, zip and torch errors alike
        raise InputError(f"{path}: not a torch state dict ({e})") from e
    if not isinstance(state, dict):
        raise InputError(f"{path}: holds a {type(state).__name__}, not a state dict")
    return state


def _conv(state: dict, index: int) -> tuple[torch.Tensor, torch.Tensor]:
    names = [f"features.{index}.weight", f"features.{index}.bias"]
    missing = [n for n in names if n not in state]
    if missing:
        raise InputError(
            f"the LPIPS weights lack {', '.join(missing)}: give the torchvision AlexNet state "
            "dict (alexnet-owt-7be5be79.pth) beside the linear heads"
        )
    return state[names[0]].float(), state[names[1]].float()


def _head(state: dict, layer: int) -> torch.Tensor:
    found = [k for k in state if k.startswith(f"lin{layer}.") and k.endswith("weight")]
    if len(found) != 1:
        raise InputError(
            f"the LPIPS weights lack the linear head of layer {layer} (lin{layer}.model.1.weight): "
            "give LPIPS's alex.pth (version 0.1) beside the AlexNet weights"
        )
    head = state[found[0]].float()
    if head.shape != (1, CHANNELS[layer], 1, 1):
        raise InputError(f"{found[0]} is {tuple(head.shape)}, not (1, {CHANNELS[layer]}, 1, 1)")
    return head
