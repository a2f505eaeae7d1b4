"""Time-surface frames: an edge moving back and forth keeps its appearance where the high-pass
filter's frame changes sign (issue 22)."""

import numpy as np
import pytest

from evcap.errors import InputError
from evcap.event_frames import high_pass_frames, time_surface_frames
from evcap.events import Events
from evcap.poses.frames import event_frames

W, H = 40, 8
SWEEP_US = 40_000  # the edge crosses the sensor in this, then comes back


def edge_back_and_forth() -> Events:
    """A bright-to-dark vertical edge: rightwards it darkens the pixels it passes (OFF
    events), leftwards it brightens them (ON). One event per pixel row per column crossed."""
    xs, ts, ps = [], [], []
    for col in range(W):
        xs += [col, col]
        ts += [int((col + 0.5) / W * SWEEP_US), int(2 * SWEEP_US - (col + 0.5) / W * SWEEP_US)]
        ps += [0, 1]
    order = np.argsort(ts, kind="stable")
    x = np.repeat(np.array(xs)[order], H)
    t = np.repeat(np.array(ts)[order], H)
    p = np.repeat(np.array(ps)[order], H)
    y = np.tile(np.arange(H), 2 * W)
    return Events(x=x, y=y, t=t, p=p.astype(np.uint8), width=W, height=H, color_filter="MONO")


def test_a_time_surface_keeps_its_sign_where_the_filter_flips():
    ev = edge_back_and_forth()
    # the edge at column 20 going right (t 20.5 ms), then at column 20 coming back (59.5 ms)
    times = np.array([int(20.6 / 40 * SWEEP_US), int(2 * SWEEP_US - 20.4 / 40 * SWEEP_US)])
    hp = high_pass_frames(ev, times, cutoff_hz=3.0)
    assert hp[0, :, 20].mean() < 0 < hp[1, :, 20].mean()  # the filter's edge changes sign
    ts = time_surface_frames(ev, times, tau_us=5_000)
    assert (ts[:, :, 20] > 0.9).all()  # the time surface's is bright both ways
    assert (ts >= 0).all() and (ts <= 1).all()
    assert ts[0].argmax(axis=1).tolist() == ts[1].argmax(axis=1).tolist() == [20] * H
    # the 8-bit frames: the edge is bright both ways, the filter's dark then bright
    frames = event_frames(ev, times, kind="timesurface")
    assert frames.dtype == np.uint8 and frames.shape == (2, H, W)
    assert (frames[:, :, 20] >= 150).all()  # (blurred: it is the front of the ridge)
    filtered = event_frames(ev, times, kind="filter")
    assert filtered[0, :, 20].mean() < 60 and filtered[1, :, 20].mean() > 195


def test_time_surface_is_deterministic_and_checks_its_input():
    ev = edge_back_and_forth()
    times = np.arange(5_000, 80_000, 5_000)
    a = time_surface_frames(ev, times, tau_us=10_000)
    assert np.array_equal(a, time_surface_frames(ev, times, tau_us=10_000))
    assert (a[0][:, 30:] == 0).all()  # no event there yet
    hot = np.zeros((H, W), bool)
    hot[:, 0] = True
    assert (time_surface_frames(ev, times, tau_us=10_000, exclude=hot)[:, :, 0] == 0).all()
    with pytest.raises(InputError, match="tau"):
        time_surface_frames(ev, times, tau_us=0)
    with pytest.raises(InputError, match="increasing"):
        time_surface_frames(ev, times[::-1], tau_us=10_000)
    with pytest.raises(InputError, match="weights"):
        event_frames(ev, times, kind="timesurface", weights="x.pth.tar")
