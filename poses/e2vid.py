"""Intensity frames from events with a recurrent network: E2VID (Rebecq et al., TPAMI 2019) and
FireNet (Scheerlinck et al., WACV 2020), rebuilt so that their released checkpoints load.

The modules follow uzh-rpg/rpg_e2vid (model/model.py, model/unet.py, model/submodules.py) and
FireNet's branch of it (cedric-scheerlinck/rpg_e2vid, cedric/firenet). Their attribute names
are the checkpoints' state-dict keys: none of them may be renamed.

A checkpoint is a dict {"arch": class name, "model": config, "state_dict": weights}. It is read
with ``torch.load(weights_only=True)``: a file that needs more than tensors and plain containers
is refused, never run. Checkpoints are never downloaded: the user gives the file
(E2VID_lightweight.pth.tar, firenet_1000.pth.tar).

The input is a normalised voxel grid (evcap.poses.voxel); E2VID's output is a sigmoid, FireNet's
a plain 1x1 convolution (trained to [0, 1]), clipped to [0, 1] by FrameReconstructor.
"""

from __future__ import annotations

import copy
import pickle
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from evcap.errors import InputError, InputNotFoundError
from evcap.poses.voxel import normalize_voxels

E2VID_LIGHTWEIGHT: dict[str, Any] = {
    "num_bins": 5,
    "skip_type": "sum",
    "recurrent_block_type": "convlstm",
    "num_encoders": 3,
    "base_num_channels": 32,
    "num_residual_blocks": 2,
    "use_upsample_conv": False,
    "norm": "BN",
}
"""The configuration of the released E2VID_lightweight.pth.tar (10,712,098 parameters)."""

FIRENET: dict[str, Any] = {
    "num_bins": 5,
    "skip_type": "no_skip",
    "recurrent_block_type": "convgru",
    "base_num_channels": 16,
    "num_residual_blocks": 2,
    "norm": None,
    "kernel_size": 3,
    "recurrent_blocks": {"resblock": [0]},
}
"""FireNet as published (37,777 parameters): head, ConvGRU, residual block, ConvGRU, residual
block, 1x1 prediction, with no skip connection."""

# What a config leaves out takes the source code's default, but for FireNet's width and kernel:
# there the source's defaults are E2VID's, and the published FireNet's are taken (loading reads
# both off the weights anyway).
_E2VID_DEFAULTS: dict[str, Any] = {
    "skip_type": "sum",
    "recurrent_block_type": "convlstm",
    "num_encoders": 4,
    "base_num_channels": 32,
    "num_residual_blocks": 2,
    "use_upsample_conv": True,
    "norm": None,
}
_FIRENET_DEFAULTS: dict[str, Any] = {
    "skip_type": "sum",
    "recurrent_block_type": "convgru",
    "base_num_channels": 16,
    "num_residual_blocks": 2,
    "norm": None,
    "kernel_size": 3,
    "recurrent_blocks": {"resblock": [0]},
}
_NOT_A_CHECKPOINT = "not an E2VID/FireNet checkpoint"

State = Any  # per recurrent unit: a (hidden, cell) pair for a ConvLSTM, a tensor for a ConvGRU


# The building blocks: attribute names are the checkpoint keys.


def _norm_layer(norm: str | None, channels: int, *, running_stats: bool) -> nn.Module | None:
    if norm == "BN":
        return nn.BatchNorm2d(channels)
    if norm == "IN":
        return nn.InstanceNorm2d(channels, track_running_stats=running_stats)
    return None


def _finish(x: torch.Tensor, norm_layer: nn.Module | None, relu: bool) -> torch.Tensor:
    if norm_layer is not None:
        x = norm_layer(x)
    return torch.relu(x) if relu else x


class _ConvLayer(nn.Module):
    """Convolution, then the norm and a ReLU where asked."""

    def __init__(
        self,
        cin: int,
        cout: int,
        kernel_size: int,
        stride: int = 1,
        padding: int = 0,
        *,
        relu: bool = True,
        norm: str | None = None,
    ) -> None:
        super().__init__()
        # a batch norm cancels any bias before it: the released weights have none there
        self.conv2d = nn.Conv2d(cin, cout, kernel_size, stride, padding, bias=norm != "BN")
        self.norm_layer = _norm_layer(norm, cout, running_stats=True)
        self.relu = relu

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return _finish(self.conv2d(x), self.norm_layer, self.relu)


class _UpsampleConvLayer(_ConvLayer):
    """Bilinear upsampling by 2, then a convolution (no checkerboard artefacts, slower)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
        return super().forward(x)


class _TransposedConvLayer(nn.Module):
    """A transposed convolution of stride 2, then the norm and a ReLU."""

    def __init__(
        self, cin: int, cout: int, kernel_size: int, padding: int = 0, *, norm: str | None = None
    ) -> None:
        super().__init__()
        self.transposed_conv2d = nn.ConvTranspose2d(
            cin, cout, kernel_size, 2, padding, output_padding=1, bias=norm != "BN"
        )
        self.norm_layer = _norm_layer(norm, cout, running_stats=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return _finish(self.transposed_conv2d(x), self.norm_layer, True)


class _ResidualBlock(nn.Module):
    """Two 3x3 convolutions around an identity shortcut."""

    def __init__(self, channels: int, norm: str | None = None) -> None:
        super().__init__()
        bias = norm != "BN"
        # in the source's order, so that the state dicts list their keys alike
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1, bias=bias)
        self.bn1 = _norm_layer(norm, channels, running_stats=False)
        self.bn2 = _norm_layer(norm, channels, running_stats=False)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = _finish(self.conv1(x), self.bn1, True)
        out = _finish(self.conv2(out), self.bn2, False)
        return torch.relu(out + x)


class _ConvLSTM(nn.Module):
    """A convolutional LSTM cell; its state is (hidden, cell)."""

    def __init__(self, channels: int, kernel_size: int = 3) -> None:
        super().__init__()
        self.channels = channels
        self.Gates = nn.Conv2d(2 * channels, 4 * channels, kernel_size, padding=kernel_size // 2)

    def forward(self, x: torch.Tensor, state: State | None) -> State:
        if state is None:
            zero = x.new_zeros(x.shape[0], self.channels, *x.shape[2:])
            state = (zero, zero)
        hidden, cell = state
        # the gates' order in the released weights: input, forget, output, candidate
        i, f, o, g = self.Gates(torch.cat([x, hidden], 1)).chunk(4, 1)
        cell = torch.sigmoid(f) * cell + torch.sigmoid(i) * torch.tanh(g)
        return torch.sigmoid(o) * torch.tanh(cell), cell


class _ConvGRU(nn.Module):
    """A convolutional GRU cell; its state is the hidden tensor."""

    def __init__(self, channels: int, kernel_size: int = 3) -> None:
        super().__init__()
        self.channels = channels
        pad = kernel_size // 2
        self.reset_gate = nn.Conv2d(2 * channels, channels, kernel_size, padding=pad)
        self.update_gate = nn.Conv2d(2 * channels, channels, kernel_size, padding=pad)
        self.out_gate = nn.Conv2d(2 * channels, channels, kernel_size, padding=pad)
        # the initialisation FireNet was trained from
        for gate in (self.reset_gate, self.update_gate, self.out_gate):
            nn.init.orthogonal_(gate.weight)
            nn.init.zeros_(gate.bias)

    def forward(self, x: torch.Tensor, state: State | None) -> State:
        if state is None:
            state = x.new_zeros(x.shape[0], self.channels, *x.shape[2:])
        both = torch.cat([x, state], 1)
        update = torch.sigmoid(self.update_gate(both))
        reset = torch.sigmoid(self.reset_gate(both))
        candidate = torch.tanh(self.out_gate(torch.cat([x, state * reset], 1)))
        return state * (1 - update) + candidate * update


def _recurrent_block(kind: str, channels: int) -> nn.Module:
    return _ConvLSTM(channels) if kind == "convlstm" else _ConvGRU(channels)


def _output(state: State) -> torch.Tensor:
    """A recurrent block's output: the hidden tensor of its state."""
    return state[0] if isinstance(state, tuple) else state


class _RecurrentConvLayer(nn.Module):
    """A convolution followed by a recurrent block."""

    def __init__(
        self,
        cin: int,
        cout: int,
        kernel_size: int,
        stride: int,
        padding: int,
        kind: str,
        norm: str | None,
    ) -> None:
        super().__init__()
        self.conv = _ConvLayer(cin, cout, kernel_size, stride, padding, norm=norm)
        self.recurrent_block = _recurrent_block(kind, cout)

    def forward(self, x: torch.Tensor, state: State | None) -> tuple[torch.Tensor, State]:
        state = self.recurrent_block(self.conv(x), state)
        return _output(state), state


class _RecurrentResidualLayer(nn.Module):
    """A residual block followed by a recurrent block."""

    def __init__(self, channels: int, kind: str, norm: str | None) -> None:
        super().__init__()
        self.conv = _ResidualBlock(channels, norm)
        self.recurrent_block = _recurrent_block(kind, channels)

    def forward(self, x: torch.Tensor, state: State | None) -> tuple[torch.Tensor, State]:
        state = self.recurrent_block(self.conv(x), state)
        return _output(state), state


def _skip(kind: str, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
    if kind == "sum":
        return x + skip
    if kind == "concat":
        return torch.cat([x, skip], 1)
    return x


class _UNetRecurrent(nn.Module):
    """E2VID's U-Net: head, strided encoders each with a recurrent block, residual blocks,
    upsampling decoders fed the encoders' outputs (skips), 1x1 prediction."""

    def __init__(self, o: dict[str, Any]) -> None:
        super().__init__()
        base, n, norm, skip = o["base_num_channels"], o["num_encoders"], o["norm"], o["skip_type"]
        self.skip_type = skip
        widths = [base * 2**i for i in range(n + 1)]
        self.head = _ConvLayer(o["num_bins"], base, 5, padding=2)
        self.encoders = nn.ModuleList(
            _RecurrentConvLayer(widths[i], widths[i + 1], 5, 2, 2, o["recurrent_block_type"], norm)
            for i in range(n)
        )
        self.resblocks = nn.ModuleList(
            _ResidualBlock(widths[-1], norm) for _ in range(o["num_residual_blocks"])
        )
        k = 1 if skip == "sum" else 2
        up = _UpsampleConvLayer if o["use_upsample_conv"] else _TransposedConvLayer
        self.decoders = nn.ModuleList(
            up(k * c, c // 2, 5, padding=2, norm=norm) for c in reversed(widths[1:])
        )
        self.pred = _ConvLayer(k * base, 1, 1, relu=False, norm=norm)

    def forward(
        self, x: torch.Tensor, states: list[State] | None
    ) -> tuple[torch.Tensor, list[State]]:
        x = head = self.head(x)
        states = states or [None] * len(self.encoders)
        skips, new_states = [], []
        for encoder, state in zip(self.encoders, states, strict=True):
            x, state = encoder(x, state)
            skips.append(x)
            new_states.append(state)
        for block in self.resblocks:
            x = block(x)
        for decoder, skip in zip(self.decoders, reversed(skips), strict=True):
            x = decoder(_skip(self.skip_type, x, skip))
        return torch.sigmoid(self.pred(_skip(self.skip_type, x, head))), new_states


class _UNetFire(nn.Module):
    """FireNet at one resolution: a recurrent head, residual blocks (some recurrent), 1x1
    prediction."""

    def __init__(self, o: dict[str, Any]) -> None:
        super().__init__()
        base, kind, norm, kernel = (
            o["base_num_channels"],
            o["recurrent_block_type"],
            o["norm"],
            o["kernel_size"],
        )
        self.skip_type = o["skip_type"]
        self.head = _RecurrentConvLayer(o["num_bins"], base, kernel, 1, kernel // 2, kind, norm)
        recurrent = o["recurrent_blocks"].get("resblock", [])
        self.recurrent = [
            i in recurrent or -1 in recurrent for i in range(o["num_residual_blocks"])
        ]
        self.resblocks = nn.ModuleList(
            _RecurrentResidualLayer(base, kind, norm) if r else _ResidualBlock(base, norm)
            for r in self.recurrent
        )
        self.pred = _ConvLayer(
            2 * base if self.skip_type == "concat" else base, 1, 1, relu=False, norm=None
        )
        # the initialisation FireNet was trained from: a mid-grey image
        nn.init.constant_(self.pred.conv2d.bias, 0.5)

    def forward(
        self, x: torch.Tensor, states: list[State] | None
    ) -> tuple[torch.Tensor, list[State]]:
        states = list(states or [None] * (1 + sum(self.recurrent)))
        x, state = self.head(x, states.pop(0))
        head, new_states = x, [state]
        for block, recurrent in zip(self.resblocks, self.recurrent, strict=True):
            if recurrent:
                x, state = block(x, states.pop(0))
                new_states.append(state)
            else:
                x = block(x)
        return self.pred(_skip(self.skip_type, x, head)), new_states


# The networks


class E2VIDRecurrent(nn.Module):
    """E2VID: a recurrent U-Net (ConvLSTM after each encoder) from voxel grid to image in [0, 1]."""

    arch = "E2VIDRecurrent"

    def __init__(self, config: Mapping[str, Any]) -> None:
        super().__init__()
        self.config = _options(config, _E2VID_DEFAULTS, self.arch)
        if self.config["skip_type"] not in ("sum", "concat"):
            raise InputError(f"E2VID: skip_type {self.config['skip_type']!r} is not sum or concat")
        self.num_bins: int = self.config["num_bins"]
        self.size_multiple: int = 2 ** self.config["num_encoders"]
        self.unetrecurrent = _UNetRecurrent(self.config)

    def forward(
        self,
        x: torch.Tensor,  # [N, num_bins, H, W], H and W multiples of size_multiple
        states: list[State] | None = None,
    ) -> tuple[torch.Tensor, list[State]]:
        """The image [N, 1, H, W] in [0, 1] and the new recurrent states."""
        return self.unetrecurrent(x, states)


class FireNet(nn.Module):
    """FireNet: E2VID made light (no downsampling, ConvGRU, 16 channels, 3x3 convolutions)."""

    arch = "FireNet"

    def __init__(self, config: Mapping[str, Any]) -> None:
        super().__init__()
        self.config = _options(config, _FIRENET_DEFAULTS, self.arch)
        if self.config["skip_type"] not in ("sum", "concat", "no_skip"):
            raise InputError(
                f"FireNet: skip_type {self.config['skip_type']!r} is not sum, concat or no_skip"
            )
        self.num_bins: int = self.config["num_bins"]
        self.size_multiple = 1
        self.net = _UNetFire(self.config)

    def forward(
        self,
        x: torch.Tensor,  # [N, num_bins, H, W]
        states: list[State] | None = None,
    ) -> tuple[torch.Tensor, list[State]]:
        """The image [N, 1, H, W] (not clipped: about [0, 1]) and the new recurrent states."""
        return self.net(x, states)


Network = E2VIDRecurrent | FireNet
_ARCHS: dict[str, type[E2VIDRecurrent] | type[FireNet]] = {
    "E2VIDRecurrent": E2VIDRecurrent,
    "FireNet": FireNet,
}
_PREFIXES = {"unetrecurrent.": "E2VIDRecurrent", "net.": "FireNet"}


def random_network(
    kind: Literal["e2vid", "firenet"] = "e2vid",
    seed: int = 0,
    config: Mapping[str, Any] | None = None,
) -> Network:
    """A network with deterministic random weights (E2VID_LIGHTWEIGHT or FIRENET unless
    ``config`` is given): it makes no useful image, but runs like a trained one."""
    if kind not in ("e2vid", "firenet"):
        raise InputError(f"unknown network {kind!r}; expected e2vid or firenet")
    # the caller's random stream stays as it was
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        if kind == "e2vid":
            network: Network = E2VIDRecurrent(config or E2VID_LIGHTWEIGHT)
        else:
            network = FireNet(config or FIRENET)
    return network.eval()


def save_checkpoint(network: Network, path: str | Path) -> None:
    """Write ``network`` as the released checkpoints are: {"arch", "model", "state_dict"}."""
    if not isinstance(network, E2VIDRecurrent | FireNet):
        raise TypeError(f"save_checkpoint: {type(network).__name__} is not E2VID or FireNet")
    state = {k: v.detach().cpu() for k, v in network.state_dict().items()}
    torch.save(
        {"arch": network.arch, "model": copy.deepcopy(network.config), "state_dict": state},
        Path(path),
    )


def load_checkpoint(path: str | Path) -> Network:
    """The network of an E2VID or FireNet checkpoint (or of a plain state dict of one), on the
    CPU in eval mode, its weights checked key by key and shape by shape."""
    path = Path(path)
    raw = _read(path)
    arch, config, state = _unpack(raw, path)
    hints = _config_from_weights(arch, state)
    if config is not None and hints.get("skip_type") == "no_skip":
        # a config that leaves the skip out means what the source makes of it: a sum
        del hints["skip_type"]
    # the weights fill what the config leaves out (FireNet's kernel size, say); the config wins
    try:
        network = _ARCHS[arch]({**hints, **(config or {})})
    except InputError as e:
        raise InputError(f"{_NOT_A_CHECKPOINT}: {path}: {e}") from None
    _check_weights(network, state, path)
    expected = network.state_dict()
    # checkpoints from before PyTorch 0.4.1 have no batch-norm counters
    for key in expected.keys() - state.keys():
        state[key] = expected[key]
    network.load_state_dict(state, strict=True)
    return network.eval()


class FrameReconstructor:
    """Runs a network over successive voxel grids, carrying its recurrent state from one call
    to the next. A grid of another size restarts the recurrence."""

    def __init__(
        self, network: Network, device: str | torch.device = "cpu", *, normalize: bool = True
    ) -> None:
        self.device = torch.device(device)
        self.network = network.to(self.device).eval()
        self.normalize = normalize  # normalize_voxels before the network (as E2VID was trained)
        self._states: list[State] | None = None
        self._size: tuple[int, int] | None = None

    def reset(self) -> None:
        """Forget the past: the next frame is made as if it were the first."""
        self._states = None

    def __call__(self, voxel: np.ndarray) -> np.ndarray:
        """The image [H, W] float32 in [0, 1] for the voxel grid ``voxel`` [bins, H, W]."""
        v = np.asarray(voxel, np.float32)
        bins = self.network.num_bins
        if v.ndim != 3 or v.shape[0] != bins or 0 in v.shape:
            raise InputError(f"voxel grid of shape {v.shape}; the network takes [{bins}, H, W]")
        if not np.isfinite(v).all():
            raise InputError("voxel grid holds NaN or infinite values")
        if self.normalize:
            v = normalize_voxels(v)
        height, width = v.shape[1:]
        if self._size != (height, width):
            self._states, self._size = None, (height, width)
        x = torch.from_numpy(v)[None].to(self.device)
        x, (top, left) = _pad(x, self.network.size_multiple)
        with torch.no_grad():
            image, self._states = self.network(x, self._states)
        image = image[0, 0, top : top + height, left : left + width].clamp(0.0, 1.0)
        return image.cpu().numpy().astype(np.float32)


def _pad(x: torch.Tensor, multiple: int) -> tuple[torch.Tensor, tuple[int, int]]:
    """``x`` [N, C, H, W] padded (reflected) to multiples of ``multiple``, and the offset of
    the original in it (as rpg_e2vid's CropParameters: the larger half before)."""
    height, width = x.shape[2:]
    ph = -height % multiple
    pw = -width % multiple
    top, left = (ph + 1) // 2, (pw + 1) // 2
    if ph == pw == 0:
        return x, (0, 0)
    # reflection needs a pad smaller than the side: tiny images repeat their border instead
    mode = (
        "reflect" if max(top, ph - top) < height and max(left, pw - left) < width else "replicate"
    )
    return F.pad(x, (left, pw - left, top, ph - top), mode=mode), (top, left)


# Configuration


def _options(config: Mapping[str, Any], defaults: dict[str, Any], arch: str) -> dict[str, Any]:
    """The network's complete, validated configuration from ``config`` and the defaults."""
    if not isinstance(config, Mapping):
        raise InputError(f"{arch}: the model config is a {type(config).__name__}, not a dict")
    if "num_bins" not in config:
        raise InputError(f"{arch}: the model config has no num_bins")
    o = {**copy.deepcopy(defaults), **{k: config[k] for k in config if k in defaults}}
    o["num_bins"] = config["num_bins"]
    try:
        for key in ("num_bins", "num_encoders", "base_num_channels", "kernel_size"):
            if key in o:
                o[key] = int(o[key])
                if o[key] < 1:
                    raise ValueError(f"{key}={o[key]} must be at least 1")
        o["num_residual_blocks"] = int(o["num_residual_blocks"])
        if o["num_residual_blocks"] < 0:
            raise ValueError(f"num_residual_blocks={o['num_residual_blocks']} is negative")
        if "use_upsample_conv" in o:
            o["use_upsample_conv"] = bool(o["use_upsample_conv"])
        # the source reads the norm with str(): a None written out reads back as "None"
        o["norm"] = None if o["norm"] in (None, "None", "none", "") else str(o["norm"])
        if o["norm"] not in (None, "BN", "IN"):
            raise ValueError(f"norm {o['norm']!r} is not BN, IN or None")
        o["skip_type"] = str(o["skip_type"])
        if o["recurrent_block_type"] not in ("convlstm", "convgru"):
            raise ValueError(
                f"recurrent_block_type {o['recurrent_block_type']!r} is not convlstm or convgru"
            )
        if "recurrent_blocks" in o:
            blocks = o["recurrent_blocks"]
            if not isinstance(blocks, Mapping):
                raise ValueError(f"recurrent_blocks {blocks!r} is not a dict")
            o["recurrent_blocks"] = {str(k): [int(i) for i in v] for k, v in blocks.items()}
    except (TypeError, ValueError) as e:
        raise InputError(f"{arch}: bad model config: {e}") from None
    return o


def _config_from_weights(arch: str, state: Mapping[str, torch.Tensor]) -> dict[str, Any]:
    """What the weights' keys and shapes tell of the configuration that made them."""
    prefix = "unetrecurrent." if arch == "E2VIDRecurrent" else "net."
    head_key = prefix + (
        "head.conv2d.weight" if arch == "E2VIDRecurrent" else "head.conv.conv2d.weight"
    )
    head = state.get(head_key)
    if not isinstance(head, torch.Tensor) or head.ndim != 4:
        return {}
    base = int(head.shape[0])
    o: dict[str, Any] = {"num_bins": int(head.shape[1]), "base_num_channels": base}

    def indices(group: str) -> set[int]:
        found = re.compile(re.escape(prefix + group) + r"\.(\d+)\.")
        return {int(m.group(1)) for k in state if (m := found.match(k))}

    norm_key = prefix + (
        "encoders.0.conv.norm_layer" if arch == "E2VIDRecurrent" else "head.conv.norm_layer"
    )
    if norm_key + ".weight" in state:
        o["norm"] = "BN"
    elif norm_key + ".running_mean" in state:
        o["norm"] = "IN"
    else:
        o["norm"] = None
    gru = any(".recurrent_block.reset_gate." in k for k in state)
    o["recurrent_block_type"] = "convgru" if gru else "convlstm"
    o["num_residual_blocks"] = len(indices("resblocks"))
    pred = state.get(prefix + "pred.conv2d.weight")
    concat = isinstance(pred, torch.Tensor) and pred.ndim == 4 and pred.shape[1] == 2 * base
    if arch == "E2VIDRecurrent":
        o["num_encoders"] = len(indices("encoders"))
        o["use_upsample_conv"] = not any(".transposed_conv2d." in k for k in state)
        o["skip_type"] = "concat" if concat else "sum"
    else:
        o["kernel_size"] = int(head.shape[-1])
        recurrent = {
            int(m.group(1))
            for k in state
            if (m := re.match(re.escape(prefix) + r"resblocks\.(\d+)\.recurrent_block\.", k))
        }
        o["recurrent_blocks"] = {"resblock": sorted(recurrent)}
        # a sum skip and none have the same weights: the published FireNet has none
        o["skip_type"] = "concat" if concat else "no_skip"
    return o


# Reading checkpoints


def _read(path: Path) -> Any:
    """The unpickled content of ``path``, allowing nothing but tensors and plain containers."""
    if not path.exists():
        raise InputNotFoundError(f"checkpoint {path} does not exist (give it with --weights FILE)")
    if not path.is_file():
        raise InputError(f"{_NOT_A_CHECKPOINT}: {path} is not a file")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except OSError as e:
        raise InputError(f"{_NOT_A_CHECKPOINT}: {path} cannot be read ({e})") from None
    except pickle.UnpicklingError as e:
        refused = re.findall(r"Unsupported global: GLOBAL ([\w.]+)", str(e))
        if refused:
            raise InputError(
                f"{_NOT_A_CHECKPOINT}: {path} holds pickled objects ({', '.join(refused)}) that "
                "loading with weights_only refuses, and evcap never runs code from a checkpoint; "
                "if you trust the file, re-save its arch, model and state_dict as plain "
                "tensors and dicts"
            ) from None
        raise InputError(
            f"{_NOT_A_CHECKPOINT}: {path} is not a PyTorch file, or is damaged"
        ) from None
    except Exception as e:  # a damaged file fails anywhere in the unpickler, with any error
        reason = str(e).splitlines()[0] if str(e) else "it ends too soon"
        raise InputError(
            f"{_NOT_A_CHECKPOINT}: {path} is not a PyTorch file, or is damaged "
            f"({type(e).__name__}: {reason})"
        ) from None


def _unpack(raw: Any, path: Path) -> tuple[str, dict[str, Any] | None, dict[str, torch.Tensor]]:
    """The arch, model config (None if none) and weights of a loaded checkpoint."""
    where = f"{_NOT_A_CHECKPOINT}: {path}"
    if not isinstance(raw, Mapping):
        raise InputError(f"{where} holds a {type(raw).__name__}, not a dict")
    if "state_dict" in raw:
        state, arch = raw["state_dict"], raw.get("arch")
        config = raw.get("model")
        if config is None and isinstance(raw.get("config"), Mapping):
            config = raw["config"].get("model")
    elif raw and all(isinstance(v, torch.Tensor) for v in raw.values()):
        state, arch, config = raw, None, None
    else:
        raise InputError(f"{where}: it has no state_dict (its keys: {_few(list(raw), 5)})")
    if not isinstance(state, Mapping) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()
    ):
        raise InputError(f"{where}: its state_dict is not a dict of named tensors")
    state = dict(state)
    # saved from a DataParallel wrapper
    if state and all(k.startswith("module.") for k in state):
        state = {k.removeprefix("module."): v for k, v in state.items()}
    if arch is None:
        found = {a for p, a in _PREFIXES.items() if any(k.startswith(p) for k in state)}
        if len(found) != 1:
            raise InputError(
                f"{where}: it names no arch, and its keys ({_few(list(state), 3)}) are neither "
                "E2VID's (unetrecurrent.*) nor FireNet's (net.*)"
            )
        arch = found.pop()
    if arch not in _ARCHS:
        raise InputError(f"{where}: unknown arch {arch!r} (expected E2VIDRecurrent or FireNet)")
    if config is not None and not isinstance(config, Mapping):
        raise InputError(f"{where}: its model config is a {type(config).__name__}, not a dict")
    return arch, None if config is None else dict(config), state


def _check_weights(network: Network, state: Mapping[str, torch.Tensor], path: Path) -> None:
    """Raise InputError unless ``state`` has exactly the keys and shapes of ``network``."""
    expected = network.state_dict()
    missing = [k for k in expected if k not in state and not k.endswith(".num_batches_tracked")]
    unexpected = [k for k in state if k not in expected]
    wrong = [k for k in state if k in expected and state[k].shape != expected[k].shape]
    problems = []
    if missing:
        problems.append(f"missing keys {_few(missing)}")
    if unexpected:
        problems.append(f"unexpected keys {_few(unexpected)}")
    if wrong:
        k = wrong[0]
        more = f" (and {len(wrong) - 1} more wrong shapes)" if len(wrong) > 1 else ""
        problems.append(
            f"{k} has shape {list(state[k].shape)}, expected {list(expected[k].shape)}{more}"
        )
    if problems:
        raise InputError(
            f"{_NOT_A_CHECKPOINT}: {path}: as {_describe(network)} ({len(expected)} keys): "
            + "; ".join(problems)
        )


def _describe(network: Network) -> str:
    c = network.config
    return f"{network.arch}({', '.join(f'{k}={c[k]!r}' for k in sorted(c))})"


def _few(names: list[str], n: int = 3) -> str:
    shown = ", ".join(names[:n])
    return f"{shown} (+{len(names) - n} more)" if len(names) > n else shown
