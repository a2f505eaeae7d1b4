"""E2VID and FireNet: the released checkpoints' layout, checkpoint loading, recurrent frames."""

import numpy as np
import pytest
import torch

from evcap.errors import InputError, InputNotFoundError
from evcap.poses.e2vid import (
    E2VID_LIGHTWEIGHT,
    FIRENET,
    E2VIDRecurrent,
    FireNet,
    FrameReconstructor,
    load_checkpoint,
    random_network,
    save_checkpoint,
)
from evcap.poses.voxel import voxel_grid

# The state dicts of E2VID_lightweight.pth.tar and firenet_1000.pth.tar, read off uzh-rpg/rpg_e2vid
# (model/model.py, unet.py, submodules.py) and FireNet's port (event_cnn_minimal model/legacy.py).
# "name* C" stands for a batch norm's weight, bias, running_mean, running_var [C] and counter.
E2VID_LIGHTWEIGHT_KEYS = """
head.conv2d.weight 32 5 5 5
head.conv2d.bias 32
encoders.0.conv.conv2d.weight 64 32 5 5
encoders.0.conv.norm_layer* 64
encoders.0.recurrent_block.Gates.weight 256 128 3 3
encoders.0.recurrent_block.Gates.bias 256
encoders.1.conv.conv2d.weight 128 64 5 5
encoders.1.conv.norm_layer* 128
encoders.1.recurrent_block.Gates.weight 512 256 3 3
encoders.1.recurrent_block.Gates.bias 512
encoders.2.conv.conv2d.weight 256 128 5 5
encoders.2.conv.norm_layer* 256
encoders.2.recurrent_block.Gates.weight 1024 512 3 3
encoders.2.recurrent_block.Gates.bias 1024
resblocks.0.conv1.weight 256 256 3 3
resblocks.0.bn1* 256
resblocks.0.bn2* 256
resblocks.0.conv2.weight 256 256 3 3
resblocks.1.conv1.weight 256 256 3 3
resblocks.1.bn1* 256
resblocks.1.bn2* 256
resblocks.1.conv2.weight 256 256 3 3
decoders.0.transposed_conv2d.weight 256 128 5 5
decoders.0.norm_layer* 128
decoders.1.transposed_conv2d.weight 128 64 5 5
decoders.1.norm_layer* 64
decoders.2.transposed_conv2d.weight 64 32 5 5
decoders.2.norm_layer* 32
pred.conv2d.weight 1 32 1 1
pred.norm_layer* 1
"""
FIRENET_KEYS = """
head.conv.conv2d.weight 16 5 3 3
head.conv.conv2d.bias 16
head.recurrent_block.reset_gate.weight 16 32 3 3
head.recurrent_block.reset_gate.bias 16
head.recurrent_block.update_gate.weight 16 32 3 3
head.recurrent_block.update_gate.bias 16
head.recurrent_block.out_gate.weight 16 32 3 3
head.recurrent_block.out_gate.bias 16
resblocks.0.conv.conv1.weight 16 16 3 3
resblocks.0.conv.conv1.bias 16
resblocks.0.conv.conv2.weight 16 16 3 3
resblocks.0.conv.conv2.bias 16
resblocks.0.recurrent_block.reset_gate.weight 16 32 3 3
resblocks.0.recurrent_block.reset_gate.bias 16
resblocks.0.recurrent_block.update_gate.weight 16 32 3 3
resblocks.0.recurrent_block.update_gate.bias 16
resblocks.0.recurrent_block.out_gate.weight 16 32 3 3
resblocks.0.recurrent_block.out_gate.bias 16
resblocks.1.conv1.weight 16 16 3 3
resblocks.1.conv1.bias 16
resblocks.1.conv2.weight 16 16 3 3
resblocks.1.conv2.bias 16
pred.conv2d.weight 1 16 1 1
pred.conv2d.bias 1
"""


def _expand(table: str, prefix: str) -> list[tuple[str, tuple[int, ...]]]:
    out = []
    for line in table.strip().splitlines():
        name, *shape = line.split()
        size = tuple(int(s) for s in shape)
        if name.endswith("*"):
            base = prefix + name[:-1]
            stats = ("weight", "bias", "running_mean", "running_var")
            out += [(f"{base}.{s}", size) for s in stats] + [(f"{base}.num_batches_tracked", ())]
        else:
            out.append((prefix + name, size))
    return out


class _Opaque:
    """Anything a plain pickle holds and weights_only loading does not allow."""


@pytest.fixture(scope="module")
def e2vid():
    return random_network("e2vid", seed=0)


@pytest.fixture(scope="module")
def firenet():
    return random_network("firenet", seed=0)


@pytest.fixture(params=["e2vid", "firenet"])
def network(request):
    return request.getfixturevalue(request.param)


def _voxel(seed, height=24, width=32, bins=5):
    rng = np.random.default_rng(seed)
    n = 400
    return voxel_grid(
        rng.integers(0, width, n),
        rng.integers(0, height, n),
        np.sort(rng.integers(0, 10_000, n)),
        rng.integers(0, 2, n),
        width,
        height,
        bins,
    )


def test_state_dicts_have_the_released_keys_and_shapes(e2vid, firenet):
    for net, table, prefix in [
        (e2vid, E2VID_LIGHTWEIGHT_KEYS, "unetrecurrent."),
        (firenet, FIRENET_KEYS, "net."),
    ]:
        got = [(k, tuple(v.shape)) for k, v in net.state_dict().items()]
        assert got == _expand(table, prefix)


def test_parameter_counts_are_the_published_ones(e2vid, firenet):
    # E2VID: "10.71 M" (lightweight, as released); FireNet: 38 k (WACV 2020)
    assert sum(p.numel() for p in e2vid.parameters()) == 10_712_098
    assert sum(p.numel() for p in firenet.parameters()) == 37_777
    # the code's defaults (4 encoders, upsampling convolutions, no norm): the full E2VID
    assert sum(p.numel() for p in E2VIDRecurrent({"num_bins": 5}).parameters()) == 43_220_097


@pytest.mark.parametrize("height, width", [(24, 32), (25, 33), (17, 31), (3, 5)])
def test_frames_have_the_input_size_and_lie_in_0_1(network, height, width):
    frames = FrameReconstructor(network)
    image = frames(_voxel(1, height, width))
    assert image.shape == (height, width) and image.dtype == np.float32
    assert image.min() >= 0.0 and image.max() <= 1.0 and np.isfinite(image).all()


def test_recurrence_and_reset(network):
    frames = FrameReconstructor(network)
    v = _voxel(2, 25, 33)
    first = frames(v)
    second = frames(v)
    assert np.abs(first - second).max() > 1e-6  # the state changed the output
    frames.reset()
    np.testing.assert_array_equal(frames(v), first)
    # another size starts afresh
    other = _voxel(3, 17, 31)
    np.testing.assert_array_equal(frames(other), FrameReconstructor(network)(other))


def test_voxel_grids_of_the_wrong_shape_are_refused(e2vid):
    frames = FrameReconstructor(e2vid)
    with pytest.raises(InputError, match=r"takes \[5, H, W\]"):
        frames(np.zeros((3, 8, 8), np.float32))
    with pytest.raises(InputError, match="NaN"):
        frames(np.full((5, 8, 8), np.nan, np.float32))


def test_random_networks_are_deterministic_and_leave_the_global_stream_alone():
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    a = random_network("firenet", seed=4)
    assert torch.equal(torch.rand(3), expected)
    b = random_network("firenet", seed=4)
    c = random_network("firenet", seed=5)
    w = "net.head.conv.conv2d.weight"
    assert torch.equal(a.state_dict()[w], b.state_dict()[w])
    assert not torch.equal(a.state_dict()[w], c.state_dict()[w])
    with pytest.raises(InputError, match="unknown network"):
        random_network("unet")


@pytest.mark.parametrize("plain", [False, True])
def test_checkpoint_round_trip(network, tmp_path, plain):
    path = tmp_path / "net.pth.tar"
    if plain:
        # a bare state dict: the arch and config are read off its keys and shapes
        torch.save(network.state_dict(), path)
    else:
        save_checkpoint(network, path)
    loaded = load_checkpoint(path)
    assert type(loaded) is type(network) and not loaded.training
    if not plain or isinstance(network, E2VIDRecurrent):
        assert loaded.config == network.config
    v = _voxel(4, 25, 33)
    a, b = FrameReconstructor(network), FrameReconstructor(loaded)
    for _ in range(2):
        np.testing.assert_array_equal(a(v), b(v))


def test_a_checkpoint_in_the_released_layout_loads(tmp_path):
    # as the 2019 files are: config under config["model"], training extras, old BN counters absent
    net = random_network("e2vid", seed=1)
    state = {k: v for k, v in net.state_dict().items() if "num_batches_tracked" not in k}
    raw = {
        "arch": "E2VIDRecurrent",
        "epoch": 1000,
        "config": {"name": "E2VID", "model": dict(E2VID_LIGHTWEIGHT, norm="BN")},
        "state_dict": state,
        "optimizer": {"state": {}, "param_groups": [{"lr": 1e-4}]},
    }
    path = tmp_path / "E2VID_lightweight.pth.tar"
    torch.save(raw, path, _use_new_zipfile_serialization=False)
    loaded = load_checkpoint(path)
    v = _voxel(5)
    np.testing.assert_array_equal(FrameReconstructor(loaded)(v), FrameReconstructor(net)(v))


def test_firenet_config_gaps_are_filled_from_the_weights(tmp_path):
    net = random_network("firenet", config=dict(FIRENET, kernel_size=5))
    path = tmp_path / "firenet.pth.tar"
    torch.save({"arch": "FireNet", "model": {"num_bins": 5}, "state_dict": net.state_dict()}, path)
    loaded = load_checkpoint(path)
    assert isinstance(loaded, FireNet)
    assert loaded.config["kernel_size"] == 5 and loaded.config["base_num_channels"] == 16


def _bad_checkpoint(kind, network):
    state = dict(network.state_dict())
    raw = {"arch": network.arch, "model": network.config, "state_dict": state}
    if kind == "wrong key":
        state["net.head.conv.conv2d.weights"] = state.pop("net.head.conv.conv2d.weight")
    elif kind == "wrong shape":
        state["net.pred.conv2d.weight"] = torch.zeros(1, 32, 1, 1)
    elif kind == "unknown arch":
        raw["arch"] = "ResNet50"
    elif kind == "pickled object":
        raw["extra"] = _Opaque()
    elif kind == "no weights":
        raw = {"arch": "FireNet", "epoch": 3}
    elif kind == "foreign weights":
        raw = {"fc.weight": torch.zeros(2, 2)}
    return raw


@pytest.mark.parametrize(
    "kind, message",
    [
        ("wrong key", r"FireNet\(.*\): missing keys net\.head\.conv\.conv2d\.weight; unexpected "),
        ("wrong shape", r"net\.pred\.conv2d\.weight has shape \[1, 32, 1, 1\], expected \[1, 16"),
        ("unknown arch", r"unknown arch 'ResNet50' \(expected E2VIDRecurrent or FireNet\)"),
        ("pickled object", r"holds pickled objects \(.*_Opaque\) that loading with weights_only"),
        ("no weights", r"has no state_dict \(its keys: arch, epoch\)"),
        ("foreign weights", r"names no arch, and its keys \(fc\.weight\) are neither"),
    ],
)
def test_bad_checkpoints_are_refused_in_one_line(firenet, tmp_path, kind, message):
    path = tmp_path / "bad.pth.tar"
    torch.save(_bad_checkpoint(kind, firenet), path)
    with pytest.raises(InputError, match=message) as raised:
        load_checkpoint(path)
    text = str(raised.value)
    assert text.startswith("not an E2VID/FireNet checkpoint: ") and "\n" not in text


def test_files_that_are_no_checkpoint_at_all(tmp_path):
    with pytest.raises(InputNotFoundError, match="--weights"):
        load_checkpoint(tmp_path / "missing.pth.tar")
    junk = tmp_path / "junk.pth.tar"
    junk.write_bytes(b"this is not a pickle" * 10)
    with pytest.raises(InputError, match="is not a PyTorch file"):
        load_checkpoint(junk)
    empty = tmp_path / "empty.pth.tar"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match="is not a PyTorch file, or is damaged"):
        load_checkpoint(empty)
    tensor = tmp_path / "tensor.pth"
    torch.save(torch.zeros(3), tensor)
    with pytest.raises(InputError, match="holds a Tensor, not a dict"):
        load_checkpoint(tensor)
