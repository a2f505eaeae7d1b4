"""The event loss (recon/events/loss.py): its compiled CPU pass against the PyTorch reference
(what runs on a GPU), values and gradients; the calibration's noise events; the crowded events'
bound."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from evcap.events import Events
from evcap.recon.events import windows as event_windows
from evcap.recon.events.loss import event_loss, expected_noise, window_loss
from evcap.recon.events.windows import EventWindows, WindowsConfig
from evcap.recon.presets import preset
from evcap.recon.scene.optics import CHANNEL_WEIGHTS, SensorOptics
from evcap.records import Calibration
from evcap.session import SensorInfo, Session, SessionWriter


@pytest.mark.parametrize("zero_events", ["target", "bound"])
@pytest.mark.parametrize("silent_weight", [None, 0.3])
@pytest.mark.parametrize("noisy", [False, True])
@pytest.mark.parametrize("crowded", [False, True])
def test_event_loss_matches_the_window_by_window_one(
    random_events, zero_events, silent_weight, noisy, crowded
):
    width, height, times, t, codes, starts = random_events(3)
    g = torch.Generator().manual_seed(4)
    n = width * height
    on = 0.15 + 0.1 * torch.rand(n, generator=g)
    off = 0.15 + 0.1 * torch.rand(n, generator=g)
    windows = EventWindows.from_codes(width, height, times, codes, starts, on, off)
    if crowded:  # a third of the events crowded (their counts a table of their own)
        near = np.random.default_rng(6).random(len(codes)) < 0.3
        kept = np.searchsorted(np.flatnonzero(near), starts)
        windows.crowded = EventWindows.from_codes(width, height, times, codes[near], kept, on, off)
    channel = torch.randint(0, 4, (n,), generator=g)
    # expected noise events per window (ON, OFF), as the calibration's rates give them: 0.18
    # to 0.72 in these windows of 7, 11 and 18 ms
    data = SimpleNamespace(
        windows=windows,
        channel_weights=CHANNEL_WEIGHTS[channel],
        mask=torch.rand(n, generator=g) > 0.1,
        optics=SimpleNamespace(noise_on_hz=40.0, noise_off_hz=25.0),
    )
    config = dataclasses.replace(
        preset("tiny").stage1.event_loss,
        zero_events=zero_events,
        silent_weight=silent_weight,
        noise_rates=noisy,
    )
    # two views at one time: no window between them; the windows: (0, 1), (0, 2), (0, 3),
    # (1, 3), (2, 3)
    frames = np.array([2, 9, 9, 20])
    assert expected_noise(data, config, frames, [(0, 1), (0, 3), (1, 3)]).all() == noisy
    # radiance about 0.5, some black and some negative (interpolation's undershoot)
    views = [0.5 + 0.3 * torch.randn(n, 3, generator=g) for _ in frames]
    views[1][:5] = 0.0
    views[2][5:8] = -0.01
    ref = [v.clone().requires_grad_(True) for v in views]
    fast = [v.clone().requires_grad_(True) for v in views]
    expected = event_loss(ref, frames, data, config, path="reference")
    got = event_loss(fast, frames, data, config, path="compiled")
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)
    (2.0 * expected).backward()
    (2.0 * got).backward()
    for a, b in zip(ref, fast, strict=True):
        torch.testing.assert_close(b.grad, a.grad, rtol=1e-4, atol=1e-7)


def test_expected_noise_follows_the_rates_and_the_window_lengths(tmp_path):
    """The calibration's background activity (ON) and shot noise (half each polarity), as
    the reconstruction reads them, times each window's length; nothing unless asked."""
    path = tmp_path / "s.h5"
    with SessionWriter(path, SensorInfo("simulated", 8, 6)):
        pass
    shape = (6, 8)
    Calibration(
        8,
        6,
        "ground truth",
        K=np.array([[10.0, 0, 4], [0, 10, 3], [0, 0, 1]]),
        threshold_on=np.full(shape, 0.2),
        threshold_off=np.full(shape, 0.2),
        background_activity_hz=1.5,
        shot_noise_hz=1.0,
    ).write(path)
    with Session.open(path) as s:
        optics = SensorOptics.from_session(s)
    assert (optics.noise_on_hz, optics.noise_off_hz) == (2.0, 0.5)
    data = SimpleNamespace(
        windows=SimpleNamespace(frame_times=np.array([0, 1000, 5000, 105_000])), optics=optics
    )
    frames, pairs = np.array([0, 2, 3]), [(0, 1), (0, 2), (1, 2)]
    asked = preset("tiny", {"stage1.event_loss.noise_rates": True}).stage1.event_loss
    expected = [[0.01, 0.0025], [0.21, 0.0525], [0.2, 0.05]]
    np.testing.assert_allclose(expected_noise(data, asked, frames, pairs), expected)
    assert not expected_noise(data, preset("tiny").stage1.event_loss, frames, pairs).any()


def test_crowded_events_are_those_within_twice_the_refractory_period(tmp_path, monkeypatch):
    """An event within 2 x the calibration's refractory period of its pixel's previous one
    (of either polarity) is counted again as crowded; a window with one bounds the change's
    size from below, in its direction, and no longer asks for it exactly."""
    path = tmp_path / "s.h5"
    sensor = SensorInfo("simulated", 8, 6)
    # pixel (1, 0): events 300 us apart (crowded after the first), then one 5 ms later;
    # pixel (2, 3): 700 and 1,100 us apart (the first crowded, the second not)
    x = [1, 2, 1, 1, 2, 2, 1]
    y = [0, 3, 0, 0, 3, 3, 0]
    t = [1000, 1500, 1300, 1600, 2200, 3300, 6600]
    p = [1, 0, 1, 1, 0, 0, 1]
    order = np.argsort(t, kind="stable")
    events = Events(*(np.asarray(a)[order] for a in (x, y, t, p)), width=8, height=6)
    with SessionWriter(path, sensor) as w:
        w.append_events(events)
    monkeypatch.setattr(event_windows, "MIN_EVENTS", 0)
    c = np.full((6, 8), 0.2)
    optics = SimpleNamespace(threshold_on=c, threshold_off=c, refractory_us=500.0)
    grid = WindowsConfig(frame_interval_ms=10, max_frames=10, refractory_bound=True)
    with Session.open(path) as s:
        windows = EventWindows.from_session(s, optics, 0, 10_000, grid)
    on, off = windows.crowded.counts(0, 1)
    assert on[1] == 2 and off[3 * 8 + 2] == 1 and on.sum() + off.sum() == 3
    measured = torch.tensor([0.6, -0.4, 0.6])
    predicted = torch.tensor([0.9, -0.1, 0.9])
    counts = torch.ones(3)
    flag = torch.tensor([1.0, 1.0, 0.0])
    c3 = torch.full((3,), 0.2)
    loss = window_loss(predicted, measured, counts, c3, c3, torch.ones(3, dtype=bool), crowded=flag)
    # above the first bound: nothing; short of the second by 0.3; the third exact L1 0.3
    torch.testing.assert_close(loss, torch.tensor(0.2))
