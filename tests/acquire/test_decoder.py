"""The stream decoder: hand-made word sequences from the protocol description, and round trips
through the encoder for any split of the stream into transfers."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evcap.acquire.decoder import Geometry, StreamDecoder
from evcap.acquire.encoder import StreamEncoder
from evcap.events import Events
from evcap.streams import LIBCAER_TO_CAMERA, Frames, ImuSamples, TriggerKind, Triggers

G = 9.80665


def decode(words, geometry=None, splits=None):
    d = StreamDecoder(geometry or Geometry())
    data = np.asarray(words, "<u2").tobytes()
    if splits is None:
        return d.decode(data), d
    parts = [d.decode(data[a:b]) for a, b in zip([0, *splits], [*splits, len(data)], strict=True)]
    return parts, d


def test_dvs_rows_columns_polarity():
    out, d = decode([0x8000 | 100, 0x1005, 0x300A, 0x200B, 0x1007, 0x3000 | 345])
    ev = out.events
    assert ev.x.tolist() == [10, 11, 345] and ev.y.tolist() == [5, 5, 7]
    assert ev.p.tolist() == [1, 0, 1] and ev.t.tolist() == [100, 100, 100]


def test_wrap_words_count_wraps():
    out, _ = decode([0x7003, 0x3001, 0x8005, 0x3002, 0x7001, 0x3003])
    assert out.events.t.tolist() == [3 * 0x8000, 3 * 0x8000 + 5, 4 * 0x8000]


def test_an_implausible_wrap_jump_is_counted_and_taken_as_one_wrap():
    # 4,000 wraps in one word: over two minutes without a single word from a running camera
    out, d = decode([0x7001, 0x3001, 0x7000 | 4000, 0x8005, 0x3002, 0x7000 | 30, 0x3003])
    assert out.events.t.tolist() == [0x8000, 2 * 0x8000 + 5, 32 * 0x8000]
    assert d.counters["timestamp_jumps"] == 1


def test_random_bytes_do_not_make_a_long_session():
    # a flaky cable's bytes: before the jumps were bounded, 658 kB of them spanned a month
    data = np.random.default_rng(3).integers(0, 256, 658_000, np.uint8).tobytes()
    d = StreamDecoder(Geometry())
    out = d.decode(data)
    assert out.events.t[-1] - out.events.t[0] < 3600e6  # under an hour (measured: 12 minutes)
    assert d.counters["timestamp_jumps"] > 10_000


def test_out_of_range_addresses_are_counted_and_skipped():
    out, d = decode([0x8001, 0x1005, 0x1000 | 260, 0x3001, 0x2000 | 346, 0x3000 | 400])
    assert out.events.y.tolist() == [5]  # the bad row keeps the latched one
    assert d.counters["dvs_out_of_range"] == 3


def test_dvs_invert_xy_swaps():
    out, _ = decode(
        [0x8001, 0x1000 | 300, 0x3000 | 20],
        Geometry(dvs_columns=260, dvs_rows=346, dvs_invert_xy=True),
    )
    assert (out.events.x[0], out.events.y[0]) == (300, 20)
    assert (out.events.width, out.events.height) == (346, 260)


def test_timestamp_reset_keeps_time_running_forward():
    out, d = decode([0x7002, 0x8000 | 1000, 0x3001, 0x0001, 0x8000 | 10, 0x3002])
    t_reset = 2 * 0x8000 + 1000
    assert out.events.t.tolist() == [t_reset, t_reset + 10]
    assert out.triggers.t.tolist() == [t_reset]
    assert out.triggers.kind.tolist() == [TriggerKind.TIMESTAMP_RESET]
    assert d.counters["timestamp_resets"] == 1


def test_backwards_timestamp_is_counted_and_ignored():
    out, d = decode([0x8000 | 500, 0x3001, 0x8000 | 400, 0x3002, 0x8000 | 600, 0x3003])
    assert out.events.t.tolist() == [500, 500, 600]
    assert d.counters["time_went_backwards"] == 1


@pytest.mark.parametrize(
    "code, kind",
    [
        (2, TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE),
        (3, TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE),
        (4, TriggerKind.EXTERNAL_SIGNAL_PULSE),
        (16, TriggerKind.EXTERNAL_GENERATOR_FALLING_EDGE),
        (17, TriggerKind.EXTERNAL_GENERATOR_RISING_EDGE),
    ],
)
def test_external_input_specials(code, kind):
    out, _ = decode([0x8000 | 77, code])
    assert out.triggers.t.tolist() == [77] and out.triggers.kind.tolist() == [kind]


def imu_words(cfg, values):
    words = [0x0005, 0x5300 | cfg]
    for v in values:
        v &= 0xFFFF
        words += [0x5000 | v >> 8, 0x5000 | v & 0xFF]
    return words + [0x0007]


def test_imu_sample_scaling_and_flips():
    # +-4 g (fs 1), +-500 deg/s (fs 1), all sensors on; big-endian int16 AX AY AZ T GX GY GZ;
    # libcaer's axes into the camera's: x and z negated
    raw = [8192, -4096, 100, 340, 655, -6554, 0]
    out, _ = decode([0x8000 | 50, *imu_words(0xE5, raw)])
    imu = out.imu
    assert imu.t.tolist() == [50]
    np.testing.assert_allclose(imu.accel[0], [-G, -0.5 * G, -100 / 8192 * G], rtol=1e-6)
    np.testing.assert_allclose(imu.gyro[0], np.deg2rad([-655, -6554, 0]) / 65.536, rtol=1e-6)
    np.testing.assert_allclose(imu.temperature[0], 36.0, rtol=1e-6)  # raw / 340 + 35
    flipped, _ = decode(
        [0x8000 | 50, *imu_words(0xE5, raw)], Geometry(imu_flip=(True, False, True))
    )
    np.testing.assert_allclose(flipped.imu.accel[0], imu.accel[0] * [-1, 1, -1], rtol=1e-6)
    mpu9250, _ = decode(imu_words(0xE5, raw), Geometry(imu_type=2))
    np.testing.assert_allclose(mpu9250.imu.temperature[0], 340 / 333.87 + 21, rtol=1e-6)
    fs, _ = decode(imu_words(0xE0 | 3 << 2 | 3, raw))  # +-16 g, +-2000 deg/s
    np.testing.assert_allclose(fs.imu.accel[0, 0], -8192 * 32 / 65536 * G, rtol=1e-6)
    np.testing.assert_allclose(fs.imu.gyro[0, 0], -np.deg2rad(655 * 4000 / 65536), rtol=1e-6)


def test_imu_with_sensors_off_skips_their_bytes():
    out, d = decode(imu_words(0x80 | 1 << 2, [8192, 0, 0]))  # accelerometer only: 6 bytes
    assert d.counters["imu_samples"] == 1
    np.testing.assert_allclose(out.imu.accel[0], [-G, 0, 0], rtol=1e-6)
    assert np.isnan(out.imu.gyro[0]).all() and np.isnan(out.imu.temperature[0])
    out, _ = decode(imu_words(0x40 | 1, [0, 0, 6554]))  # gyroscope only
    np.testing.assert_allclose(out.imu.gyro[0], np.deg2rad([0, 0, -6554 / 65.536]), rtol=1e-6)


def test_cut_imu_sample_is_dropped():
    words = imu_words(0xE5, [1, 2, 3, 4, 5, 6, 7])
    out, d = decode(words[:6] + [0x0007])
    assert len(out.imu) == 0 and d.counters["imu_bad"] == 1


def roi_words(sx, sy, ex, ey):
    return [w for v in (sx, sy, ex, ey) for w in (0x5100 | v >> 8, 0x5200 | v & 0xFF)]


def frame_words(roi, resets, signals, start=0x0008):
    """A frame: the reset columns, then the signal columns (global shutter)."""
    words = [start, *roi_words(*roi), 0x000E]
    for kind, image in ((0x000B, resets), (0x000C, signals)):
        if kind == 0x000C:
            words.append(0x000F)
        for column in np.asarray(image).T:
            words += [kind, *(0x4000 | int(v) for v in column), 0x000D]
    return words + [0x000A]


def test_frame_roi_cds_and_saturation_rules():
    resets = np.array([[600, 300], [700, 800]])  # 2 rows x 2 columns
    signals = np.array([[100, 50], [0, 900]])
    words = [0x8000 | 10, *frame_words((100, 200, 101, 201), resets, signals)]
    out, d = decode(words)
    f = out.frames
    assert len(f) == 1 and d.counters["frames"] == 1
    # 600-100; reset < 384 -> 1023; signal 0 -> 1023; 800-900 clamps to 0
    np.testing.assert_array_equal(f.data[0, 200:202, 100:102], [[500, 1023], [1023, 0]])
    assert f.data[0].sum() == 500 + 1023 + 1023  # outside the ROI: 0
    assert f.t.tolist() == [10] and f.exposure_us.tolist() == [0]
    kinds = out.triggers.kind.tolist()
    assert kinds == [
        TriggerKind.APS_FRAME_START,
        TriggerKind.APS_EXPOSURE_START,
        TriggerKind.APS_EXPOSURE_END,
        TriggerKind.APS_FRAME_END,
    ]


def test_frame_orientation_flips():
    image = np.array([[500, 501, 502], [503, 504, 505]])  # what the sensor sees (2 x 3)
    resets = np.full_like(image, 1000)
    # With flipX and flipY the wire sends columns and rows reversed.
    wire = image[::-1, ::-1]
    out, _ = decode(
        frame_words((0, 0, 2, 1), resets, resets - wire), Geometry(aps_flip_x=True, aps_flip_y=True)
    )
    np.testing.assert_array_equal(out.frames.data[0, :2, :3], image)


def test_bad_frame_and_samples_outside_frames():
    resets = np.full((2, 2), 900)
    words = frame_words((0, 0, 1, 1), resets, resets - 5)
    broken = words[: words.index(0x000C)] + [0x000A]  # signal columns missing
    out, d = decode([0x4001, 0x4002, *broken, 0x4003])
    assert len(out.frames) == 0
    assert d.counters["frames_bad"] == 1 and d.counters["aps_samples_skipped"] == 3


def test_odd_byte_split_is_carried_over():
    words = [0x8000 | 100, 0x1005, 0x300A, 0x200B]
    data = np.asarray(words, "<u2").tobytes()
    d = StreamDecoder(Geometry())
    a, b = d.decode(data[:3]), d.decode(data[3:])
    assert len(a.events) == 0 and b.events.x.tolist() == [10, 11]


# -- round trips through the encoder ------------------------------------------------------------

W, H = 346, 260


@st.composite
def streams(draw):
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    n = draw(st.integers(0, 300))
    max_gap = draw(st.sampled_from([1, 50, 5000, 0x8000 * 3, 0x8000 * 5000]))
    t = np.cumsum(rng.integers(0, max_gap, n)) + draw(st.integers(0, 10))
    events = Events(rng.integers(0, W, n), rng.integers(0, H, n), t, rng.integers(0, 2, n), W, H)
    end = int(t[-1]) if n else 1000
    n_frames = draw(st.integers(0, 2))
    starts = np.sort(rng.integers(0, end + 1, n_frames)) if n_frames else np.zeros(0, int)
    for i in range(1, n_frames):  # frames do not overlap
        starts[i] = max(starts[i], starts[i - 1] + 600)
    exposures = rng.integers(0, 500, n_frames)
    frames = Frames(rng.integers(0, 1024, (n_frames, H, W)), starts, exposures)
    n_imu = draw(st.integers(0, 20))
    imu_raw = (
        np.sort(rng.integers(0, end + 1, n_imu)),
        rng.integers(-32768, 32768, (n_imu, 7)).astype(np.int16),
    )
    n_trig = draw(st.integers(0, 5))
    t_trig, kinds = np.sort(rng.integers(0, end + 1, n_trig)), rng.choice(6, n_trig)
    # A timestamp reset during an exposure voids that frame (as on the camera): keep them apart.
    during = ((t_trig[:, None] >= starts) & (t_trig[:, None] <= starts + frames.exposure_us)).any(1)
    kinds[(kinds == TriggerKind.TIMESTAMP_RESET) & during] = TriggerKind.EXTERNAL_SIGNAL_PULSE
    triggers = Triggers(t_trig, kinds)
    cuts = sorted(draw(st.lists(st.integers(1, 10**6), max_size=8)))
    return events, frames, imu_raw, triggers, cuts


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(stream=streams())
def test_encode_decode_round_trip_for_any_split(stream):
    events, frames, imu_raw, triggers, cuts = stream
    data = StreamEncoder().encode(events, frames, None, triggers, imu_raw=imu_raw)
    cuts = sorted({c % (len(data) + 1) for c in cuts})
    d = StreamDecoder(Geometry())
    parts = [d.decode(data[a:b]) for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True)]
    ev = {k: np.concatenate([getattr(p.events, k) for p in parts]) for k in "xytp"}
    for k in "xytp":
        np.testing.assert_array_equal(ev[k], getattr(events, k))
    data3 = np.concatenate([p.frames.data for p in parts])
    np.testing.assert_array_equal(data3, frames.data)
    np.testing.assert_array_equal(np.concatenate([p.frames.t for p in parts]), frames.t)
    np.testing.assert_array_equal(
        np.concatenate([p.frames.exposure_us for p in parts]), frames.exposure_us
    )
    imu_t = np.concatenate([p.imu.t for p in parts])
    np.testing.assert_array_equal(imu_t, imu_raw[0])
    accel = np.concatenate([p.imu.accel for p in parts])
    camera = imu_raw[1][:, :3] / 8192 * G * LIBCAER_TO_CAMERA
    np.testing.assert_allclose(accel, camera, rtol=1e-6, atol=1e-9)
    tr_t = np.concatenate([p.triggers.t for p in parts])
    tr_k = np.concatenate([p.triggers.kind for p in parts])
    external = tr_k < 6  # at equal times, the order of triggers is not kept
    got = sorted(zip(tr_t[external].tolist(), tr_k[external].tolist(), strict=True))
    assert got == sorted(zip(triggers.t.tolist(), triggers.kind.tolist(), strict=True))
    assert (tr_k >= 6).sum() == 4 * len(frames)
    assert d.counters["unknown_words"] == d.counters["frames_bad"] == d.counters["imu_bad"] == 0


def test_physical_imu_values_round_trip():
    rng = np.random.default_rng(0)
    imu = ImuSamples(
        np.arange(50) * 1000,
        rng.normal(0, 15, (50, 3)),
        rng.normal(0, 1.5, (50, 3)),
        rng.normal(30, 5, 50),
    )
    enc = StreamEncoder(Geometry(imu_flip=(True, True, False)))
    out, _ = decode(
        np.frombuffer(enc.encode(imu=imu), "<u2"), Geometry(imu_flip=(True, True, False))
    )
    np.testing.assert_allclose(out.imu.accel, imu.accel, atol=4 * 2 / 65536 * G)
    np.testing.assert_allclose(out.imu.gyro, imu.gyro, atol=np.deg2rad(1000 / 65536))
    np.testing.assert_allclose(out.imu.temperature, imu.temperature, atol=1 / 340)


@settings(max_examples=200, deadline=None)
@given(data=st.binary(max_size=4000), cut=st.integers(0, 4000))
def test_random_bytes_never_crash(data, cut):
    d = StreamDecoder(Geometry(color_filter="RGBG"))
    for part in (data[:cut], data[cut:]):
        out = d.decode(part)  # outputs are valid containers whatever the input
        Events(out.events.x, out.events.y, out.events.t, out.events.p, W, H, "RGBG")
        assert (np.diff(out.events.t) >= 0).all()
        assert out.frames.data.max(initial=0) <= 1023


def test_frames_with_invert_xy_round_trip():
    g = Geometry(aps_columns=260, aps_rows=346, aps_invert_xy=True, aps_flip_x=True)
    assert (g.aps_width, g.aps_height) == (346, 260)
    rng = np.random.default_rng(5)
    frames = Frames(rng.integers(0, 1023, (1, H, W)), [100], [50])
    roi = (10, 20, 109, 69)  # image coordinates, as libcaer takes them
    out, d = decode(np.frombuffer(StreamEncoder(g).encode(frames=frames, roi=roi), "<u2"), g)
    assert d.counters["frames"] == 1
    np.testing.assert_array_equal(out.frames.data[0, 20:70, 10:110], frames.data[0, 20:70, 10:110])


def test_many_small_imu_samples_in_one_transfer():
    # temperature only: 5 words per sample
    words = [w for k in range(300) for w in imu_words(0x20, [340 * k])]
    out, d = decode(words)
    assert len(out.imu) == 300 and d.counters["imu_bad"] == 0
    np.testing.assert_allclose(out.imu.temperature[:3], [35, 36, 37])
    out, d = decode(imu_words(0x00, []))  # a sample with no sensor on carries nothing
    assert len(out.imu) == 0 and d.counters["imu_bad"] == 1


def test_aps_signals_before_the_first_frame_start_are_ignored():
    # Data start (or a timestamp reset) in the middle of a frame: its end is not a frame.
    out, d = decode([0x8000 | 5, 0x000F, 0x000C, 0x4001, 0x000D, 0x000A])
    assert len(out.triggers) == 0 and len(out.frames) == 0
