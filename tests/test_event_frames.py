"""The high-pass event frames: each event adds its threshold, what is old fades."""

import numpy as np
import pytest

from evcap.errors import InputError
from evcap.event_frames import high_pass_frames
from evcap.events import Events


def test_events_add_their_thresholds_and_fade():
    # pixel (1, 0): three ON events at 0.25; pixel (2, 1): one OFF event at 0.1
    ev = Events(
        x=[1, 1, 1, 2], y=[0, 0, 0, 1], t=[0, 10, 20, 30], p=[1, 1, 1, 0], width=4, height=2
    )
    on = np.full((2, 4), 0.25)
    frames = high_pass_frames(
        ev, [25, 40, 1_000_040], cutoff_hz=1.0, threshold_on=on, threshold_off=0.1
    )
    assert frames.shape == (3, 2, 4)
    assert frames[0, 0, 1] == pytest.approx(0.75, rel=1e-4)
    assert frames[0, 1, 2] == 0  # its event comes after the frame
    assert frames[1, 1, 2] == pytest.approx(-0.1, rel=1e-4)
    # one second later: faded by exp(-2 pi)
    assert frames[2, 0, 1] == pytest.approx(0.75 * np.exp(-2 * np.pi), rel=1e-3)
    assert np.count_nonzero(frames[1]) == 2


def test_excluded_pixels_stay_at_zero_and_bad_times_are_refused():
    ev = Events(x=[0, 1], y=[0, 0], t=[0, 5], p=[1, 1], width=2, height=1)
    hot = np.array([[True, False]])
    frames = high_pass_frames(ev, [10], exclude=hot)
    assert frames[0, 0, 0] == 0 and frames[0, 0, 1] > 0
    with pytest.raises(InputError, match="increasing"):
        high_pass_frames(ev, [10, 5])


def test_with_aps_frames_the_events_correct_the_latest_frame():
    from evcap.streams import Frames

    data = np.full((2, 1, 2), 99, np.uint16)
    data[1, 0, 1] = 399  # the second frame: pixel 1 four times brighter
    aps = Frames(data, t=[0, 100_000], exposure_us=[1000, 1000])  # mid-exposure 500, 100500
    ev = Events(x=[0], y=[0], t=[1000], p=[1], width=2, height=1)
    frames = high_pass_frames(ev, [1000, 50_000, 200_000], cutoff_hz=5.0, aps=aps)
    level = np.log(100.0)  # 99 counts per ms, + 1
    assert frames[0, 0, 0] == pytest.approx(level + 0.2, rel=1e-5)  # the frame + one ON event
    assert frames[0, 0, 1] == pytest.approx(level, rel=1e-5)
    decayed = 0.2 * np.exp(-2 * np.pi * 5.0 * 0.049)
    assert frames[1, 0, 0] == pytest.approx(level + decayed, rel=1e-4)  # back towards the frame
    assert frames[2, 0, 1] == pytest.approx(np.log(400.0), abs=0.1 * np.log(4))
