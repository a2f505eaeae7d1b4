"""Frames from events for structure from motion: rate, demosaicing, both kinds of frames."""

import numpy as np
import pytest

from evcap.errors import InputError
from evcap.events import Events
from evcap.poses.e2vid import random_network, save_checkpoint
from evcap.poses.frames import demosaic, event_frames, frame_rate


def moving_edge(width=40, height=30, n=4000, span_us=100_000, seed=0) -> Events:
    """ON events of a vertical edge sweeping right over ``span_us``."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, span_us, n))
    x = np.clip((t / span_us * width + rng.normal(0, 0.5, n)).astype(int), 0, width - 1)
    y = rng.integers(0, height, n)
    return Events(
        x=x, y=y, t=t, p=np.ones(n, np.uint8), width=width, height=height, color_filter="RGBG"
    )


def test_demosaic_restores_a_flat_color():
    h, w = 6, 8
    rgb = np.array([0.8, 0.4, 0.2])
    yy, xx = np.mgrid[0:h, 0:w]
    from evcap.events import pixel_channels

    mosaic = rgb[pixel_channels(xx.ravel(), yy.ravel(), "RGBG")].reshape(h, w)
    assert np.allclose(demosaic(mosaic, "RGBG"), rgb, atol=1e-6)
    assert np.allclose(demosaic(mosaic, "MONO")[..., 1], mosaic)


def test_frame_rate_follows_the_event_rate():
    ev = moving_edge(n=100_000, span_us=10_000_000)
    assert frame_rate(ev) == pytest.approx(100_000 / 10 / (0.35 * 40 * 30), rel=0.01)
    assert frame_rate(moving_edge(n=9000, span_us=10_000_000)) == pytest.approx(6.0, rel=1e-3)
    assert frame_rate(moving_edge(n=9000)) == 60.0  # at most


@pytest.mark.parametrize("kind", ["filter", "e2vid", "firenet"])
def test_frames_of_each_kind(kind, tmp_path):
    ev = moving_edge()
    weights = None
    if kind != "filter":
        weights = tmp_path / f"{kind}.pth.tar"
        save_checkpoint(random_network(kind, seed=1), weights)
    frames = event_frames(ev, np.array([30_000, 60_000, 90_000]), kind=kind, weights=weights)
    assert frames.shape == (3, 30, 40) and frames.dtype == np.uint8
    if kind == "filter":  # the edge has passed the left part by 60 ms: brighter there
        assert frames[1][:, :10].mean() > frames[1][:, 30:].mean()


def test_a_network_without_weights_or_the_wrong_one_is_refused(tmp_path):
    ev = moving_edge()
    with pytest.raises(InputError, match="--weights"):
        event_frames(ev, np.array([50_000]), kind="e2vid")
    path = tmp_path / "firenet.pth.tar"
    save_checkpoint(random_network("firenet"), path)
    with pytest.raises(InputError, match="not e2vid"):
        event_frames(ev, np.array([50_000]), kind="e2vid", weights=path)
