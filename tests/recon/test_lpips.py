"""LPIPS from weights a user has, on small networks whose output is known."""

import numpy as np
import pytest
import torch

from evcap.errors import InputError
from evcap.recon.evaluate.lpips import CHANNELS, CONVS, Lpips

SHAPES = {0: (64, 3, 11, 11), 3: (192, 64, 5, 5), 6: (384, 192, 3, 3)}
SHAPES |= {8: (256, 384, 3, 3), 10: (256, 256, 3, 3)}
HEADS = (0.1, 0.2, 0.3, 0.4, 0.5)


def write_weights(folder, make_conv, heads=HEADS):
    """The torchvision AlexNet's convolutions and LPIPS's linear heads, in two files named and
    keyed as the published ones are."""
    alexnet = {}
    for index, _, _ in CONVS:
        alexnet[f"features.{index}.weight"], alexnet[f"features.{index}.bias"] = make_conv(index)
    alexnet["classifier.1.weight"] = torch.zeros(4, 9216)  # present in the real file, unused
    linear = {}
    for layer, channels in enumerate(CHANNELS):
        w = torch.zeros(1, channels, 1, 1)
        w[0, 0] = heads[layer]
        linear[f"lin{layer}.model.1.weight"] = w
    torch.save(alexnet, folder / "alexnet-owt-7be5be79.pth")
    torch.save(linear, folder / "alex.pth")
    return folder / "alexnet-owt-7be5be79.pth", folder / "alex.pth"


def centre_tap(index):
    """Each convolution passes its input's first channel straight through to its first."""
    weight = torch.zeros(SHAPES[index])
    k = SHAPES[index][-1] // 2
    weight[0, 0, k, k] = 1.0
    return weight, torch.zeros(SHAPES[index][0])


def test_a_network_that_passes_one_channel_through_gives_the_sum_of_its_heads(tmp_path):
    """White against black: the first channel is positive through every layer for white (unit
    length once normalized) and zero for black, so each layer's squared difference is 1 at
    every position and LPIPS is the sum of the heads' first weights."""
    lpips = Lpips(*write_weights(tmp_path, centre_tap))
    white, black = np.ones((2, 64, 64, 3)), np.zeros((2, 64, 64, 3))
    np.testing.assert_allclose(lpips.per_image(white, black), sum(HEADS), rtol=1e-6)
    assert lpips(black, black) == 0.0


def test_it_is_zero_for_the_same_image_and_symmetric(tmp_path):
    g = torch.Generator().manual_seed(0)
    conv = lambda i: (torch.randn(SHAPES[i], generator=g) * 0.1, torch.zeros(SHAPES[i][0]))  # noqa: E731
    lpips = Lpips(*write_weights(tmp_path, conv))
    rng = np.random.default_rng(1)
    a, b = rng.random((3, 48, 40, 3)), rng.random((3, 48, 40, 3))
    assert lpips(a, a) == pytest.approx(0.0, abs=1e-7)
    np.testing.assert_allclose(lpips.per_image(a, b), lpips.per_image(b, a), rtol=1e-5)
    assert (lpips.per_image(a, b) > 0).all()
    # the per-image figures do not depend on how the images are batched
    np.testing.assert_allclose(lpips.per_image(a, b, batch=1), lpips.per_image(a, b), rtol=1e-5)


def test_missing_or_wrong_weights_are_named(tmp_path):
    alexnet, heads = write_weights(tmp_path, centre_tap)
    with pytest.raises(InputError, match="lack the linear head of layer 0"):
        Lpips(alexnet)
    with pytest.raises(InputError, match=r"lack features\.0\.weight"):
        Lpips(heads)
    with pytest.raises(InputError, match="no such LPIPS weights file"):
        Lpips(tmp_path / "absent.pth")
    (tmp_path / "junk.pth").write_bytes(b"not a torch file")
    with pytest.raises(InputError, match="not a torch state dict"):
        Lpips(tmp_path / "junk.pth", heads)


def test_the_reconstructions_lpips_uses_the_weights_already_on_the_machine(tmp_path, monkeypatch):
    """evaluate's LPIPS: torchvision's AlexNet in torch's hub cache and the heads the lpips
    package ships, computed here; None when either is missing."""
    import sys

    from evcap.recon.evaluate import metrics

    hub, package = tmp_path / "hub", tmp_path / "site" / "lpips"
    (hub / "checkpoints").mkdir(parents=True)
    (package / "weights" / "v0.1").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    alexnet, heads = write_weights(tmp_path, centre_tap)
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(hub))
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    monkeypatch.delitem(sys.modules, "lpips", raising=False)
    white, black = np.ones((1, 64, 64, 3)), np.zeros((1, 64, 64, 3))
    assert metrics.lpips_if_available(white, black) is None  # no backbone in the cache
    alexnet.rename(hub / "checkpoints" / alexnet.name)
    assert metrics.lpips_if_available(white, black) is None  # no heads in the package
    heads.rename(package / "weights" / "v0.1" / "alex.pth")
    assert metrics.lpips_if_available(white, black) == pytest.approx(sum(HEADS), rel=1e-6)
