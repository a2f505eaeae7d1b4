import numpy as np
import pytest

from evcap.errors import InputError
from evcap.events import Channel, Events, pixel_channels


def make(x, y, t, p, **kw):
    return Events(
        np.array(x),
        np.array(y),
        np.array(t),
        np.array(p),
        kw.pop("width", 346),
        kw.pop("height", 260),
        **kw,
    )


def test_dtypes_are_normalised():
    ev = make([1, 2], [3, 4], [5, 6], [True, False])
    assert (ev.x.dtype, ev.y.dtype, ev.t.dtype, ev.p.dtype) == (
        np.uint16,
        np.uint16,
        np.int64,
        np.uint8,
    )
    assert ev.p.tolist() == [1, 0]


@pytest.mark.parametrize(
    "fields, message",
    [
        (([346], [0], [0], [1]), "x=346 at event 0 is outside 0..345"),
        (([0], [260], [0], [1]), "y=260"),
        (([0], [-1], [0], [1]), "y=-1"),
        (([0], [0], [0], [2]), "p=2"),
        (([0, 0], [0, 0], [5, 4], [1, 1]), "not in time order at event 1"),
        (([0, 0], [0], [5, 6], [1, 1]), "different lengths"),
        (([0.5], [0], [0], [1]), "x must hold integers"),
        (([0], [0], [0.5], [1]), "t must be 1-D integers"),
    ],
)
def test_invalid_events_name_the_problem(fields, message):
    with pytest.raises(InputError, match=message):
        make(*fields)


def test_unknown_color_filter():
    with pytest.raises(InputError, match="unknown color filter"):
        make([0], [0], [0], [0], color_filter="XYZW")


def test_rgbg_channels_follow_pixel_parity():
    # Color-DAVIS346 (RGBG): R at (even x, even y), B at (odd x, odd y), G elsewhere.
    ev = make(
        [0, 1, 0, 1, 2, 345], [0, 0, 1, 1, 2, 259], np.arange(6), [1] * 6, color_filter="RGBG"
    )
    R, G, B = Channel.RED, Channel.GREEN, Channel.BLUE
    assert ev.channels().tolist() == [R, G, G, B, R, B]


def test_other_filters_and_mono():
    x, y = np.array([0, 1, 0, 1]), np.array([0, 0, 1, 1])
    R, G, B = Channel.RED, Channel.GREEN, Channel.BLUE
    assert pixel_channels(x, y, "GRGB").tolist() == [G, R, B, G]
    assert pixel_channels(x, y, "GBGR").tolist() == [G, B, R, G]
    assert pixel_channels(x, y, "BGRG").tolist() == [B, G, G, R]
    assert pixel_channels(x, y, "MONO").tolist() == [Channel.MONO] * 4


def test_time_slice_and_select():
    ev = make([0, 1, 2, 3], [0, 0, 0, 0], [999, 1000, 1000, 2000], [1, 0, 1, 0])
    assert ev.time_slice(1000, 2000).t.tolist() == [1000, 1000]
    assert ev.time_slice(None, 1000).t.tolist() == [999]
    assert len(ev.time_slice(3000, 1000)) == 0
    assert ev.select(ev.p == 1).x.tolist() == [0, 2]
    assert len(Events.empty(346, 260)) == 0
