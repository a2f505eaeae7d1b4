"""AEDAT 3.1 (cAER) import: files written here from libcaer's layouts, read back exactly."""

import datetime
import struct

import numpy as np
import pytest

from evcap.errors import ForeignFormatError, InputError
from evcap.importers.aedat3 import import_aedat3, read_layout
from evcap.session import Session

G = 9.80665
START = "2017-04-28 14:03:30 (TZ+0200)"
START_US = int(datetime.datetime(2017, 4, 28, 12, 3, 30, tzinfo=datetime.UTC).timestamp()) * 10**6


# -- a tiny AEDAT 3.1 writer (libcaer's event layouts, independent of the reader) ----------------


def aedat3_file(path, packets, sources=("DAVIS346B",)):
    head = b"#!AER-DAT3.1\r\n#Format: RAW\r\n"
    for i, name in enumerate(sources, start=1):
        head += f"#Source {i}: {name}\r\n".encode()
    head += f"#Start-Time: {START}\r\n#!END-HEADER\r\n".encode()
    path.write_bytes(head + b"".join(packets))
    return path


def packet(etype, events, size, ts_offset, overflow=0, source=1):
    """28-byte header (type, source, size, ts offset, overflow, capacity, number, valid)."""
    n = len(events) // size
    return struct.pack("<hhiiiiii", etype, source, size, ts_offset, overflow, n, n, n) + events


def polarity_packet(x, y, p, ts, overflow=0, valid=None, source=1):
    valid = np.ones(len(x), np.int64) if valid is None else valid
    ev = np.empty((len(x), 2), "<u4")
    ev[:, 0] = (np.asarray(x) << 17) | (np.asarray(y) << 2) | (np.asarray(p) << 1) | valid
    ev[:, 1] = ts
    return packet(1, ev.tobytes(), 8, 4, overflow, source)


def imu6_packet(ts, accel_g, gyro_dps, temp, overflow=0):
    ev = np.zeros(len(ts), [("info", "<u4"), ("t", "<i4"), ("v", "<f4", 7)])
    ev["info"], ev["t"] = 1, ts
    ev["v"][:, :3], ev["v"][:, 3:6], ev["v"][:, 6] = accel_g, gyro_dps, temp
    return packet(3, ev.tobytes(), 36, 4, overflow)


def frame_packet(frames, max_pixels, overflow=0, color_filter=0):
    """frames: (image of 10-bit values, start of exposure, end of exposure, x, y)."""
    size = 36 + 2 * max_pixels
    out = b""
    for image, start, end, px, py in frames:
        h, w = image.shape
        info = 1 | (1 << 1) | (color_filter << 4)  # valid, 1 channel, filter, ROI 0
        head = struct.pack("<I8i", info, start - 100, end + 100, start, end, w, h, px, py)
        pixels = (image.astype("<u2") << 6).tobytes()  # normalised to 16 bits
        out += (head + pixels).ljust(size, b"\0")
    return packet(2, out, size, 12, overflow)


def special_packet(types, ts, overflow=0):
    ev = np.empty((len(types), 2), "<u4")
    ev[:, 0] = (np.asarray(types) << 1) | 1
    ev[:, 1] = ts
    return packet(0, ev.tobytes(), 8, 4, overflow)


def random_events(rng, n, w, h, t0, t1):
    return (
        rng.integers(0, w, n),
        rng.integers(0, h, n),
        rng.integers(0, 2, n),
        np.sort(rng.integers(t0, t1, n)),
    )


# -- tests ---------------------------------------------------------------------------------------


def test_davis346_round_trip_across_a_timestamp_overflow(tmp_path):
    rng = np.random.default_rng(1)
    w, h = 346, 260
    near = (1 << 31) - 3_000  # the 31-bit timestamps overflow into the next packet's base
    a = random_events(rng, 1_000, w, h, near, near + 2_000)
    b = random_events(rng, 1_500, w, h, 100, 4_000)  # overflow 1: time 2^31 + ts
    imu_ts = a[3][0] + np.array([10, 1_010])
    accel = rng.normal(0, 1, (2, 3)).astype(np.float32)
    gyro = rng.normal(0, 30, (2, 3)).astype(np.float32)
    temp = np.array([30.5, 30.75], np.float32)
    images = [rng.integers(0, 1024, (h, w)) for _ in range(2)]
    frames = frame_packet(
        [(images[0], near + 200, near + 700, 0, 0), (images[1], near + 1_500, near + 1_900, 0, 0)],
        w * h,
    )
    special = special_packet(
        [2, 14, 0], [a[3][0] + 5, a[3][0] + 150, 2**31 - 1]
    )  # rising, frame start
    src = aedat3_file(
        tmp_path / "davis346.aedat",
        [
            special,
            polarity_packet(*a[:3], a[3]),
            imu6_packet(imu_ts, accel, gyro, temp),
            frames,
            polarity_packet(*b[:3], b[3], overflow=1),
        ],
    )
    summary = import_aedat3(src, tmp_path / "s.h5")
    assert (summary.events, summary.frames, summary.imu, summary.triggers) == (2_500, 2, 2, 2)
    assert summary.source == "AEDAT 3.1, DAVIS346B"
    t0 = int(a[3][0])
    with Session.open(tmp_path / "s.h5") as s:
        assert (s.sensor.sensor, s.sensor.width, s.sensor.height) == ("DAVIS346B", 346, 260)
        assert (s.sensor.color_filter, s.sensor.t_offset_us) == ("MONO", START_US)
        ev = s.events()
        np.testing.assert_array_equal(ev.x, np.concatenate([a[0], b[0]]))
        np.testing.assert_array_equal(ev.y, np.concatenate([a[1], b[1]]))
        np.testing.assert_array_equal(ev.p, np.concatenate([a[2], b[2]]))
        np.testing.assert_array_equal(ev.t, np.concatenate([a[3], (1 << 31) + b[3]]) - t0)
        assert (int(ev.t[0]), int(ev.t[-1])) == (0, (1 << 31) + int(b[3][-1]) - t0)
        imu = s.imu()
        np.testing.assert_array_equal(imu.t, imu_ts - t0)
        # cAER's (libcaer's) axes into the camera's: x and z negated
        np.testing.assert_allclose(imu.accel, accel * G * [-1, 1, -1], rtol=1e-6)
        np.testing.assert_allclose(imu.gyro, np.deg2rad(gyro) * [-1, 1, -1], rtol=1e-6)
        np.testing.assert_array_equal(imu.temperature, temp)
        fr = s.frames()
        np.testing.assert_array_equal(fr.data, np.stack(images))
        np.testing.assert_array_equal(fr.t, [near + 200 - t0, near + 1_500 - t0])
        np.testing.assert_array_equal(fr.exposure_us, [500, 400])
        trig = s.triggers()
        np.testing.assert_array_equal(trig.t, [5, 150])
        np.testing.assert_array_equal(trig.kind, [1, 6])  # external rising edge, frame start


@pytest.mark.parametrize("source, w, h", [("DVS128", 128, 128), ("DAVIS240C", 240, 180)])
def test_dvs128_and_davis240_sources(tmp_path, source, w, h):
    rng = np.random.default_rng(2)
    x, y, p, t = random_events(rng, 2_000, w, h, 50, 100_000)
    src = aedat3_file(
        tmp_path / "s.aedat",
        [
            polarity_packet(x[:700], y[:700], p[:700], t[:700]),
            polarity_packet(*[v[700:] for v in (x, y, p, t)]),
        ],
        sources=(source,),
    )
    import_aedat3(src, tmp_path / "s.h5")
    with Session.open(tmp_path / "s.h5") as s:
        assert (s.sensor.sensor, s.sensor.width, s.sensor.height) == (source, w, h)
        ev = s.events()
        np.testing.assert_array_equal(ev.x, x)
        np.testing.assert_array_equal(ev.y, y)
        np.testing.assert_array_equal(ev.p, p)
        np.testing.assert_array_equal(ev.t, t - t[0])


def test_invalid_events_and_other_sources_are_skipped(tmp_path):
    x, y, p = np.array([1, 2, 3, 4]), np.array([4, 3, 2, 1]), np.array([1, 0, 1, 0])
    t = np.array([10, 20, 30, 40])
    src = aedat3_file(
        tmp_path / "v.aedat",
        [
            polarity_packet(x, y, p, t, valid=np.array([1, 0, 1, 1])),
            polarity_packet(x, y, p, t + 5, source=2),  # a second camera
        ],
        sources=("DVS128", "DVS128"),
    )
    assert import_aedat3(src, tmp_path / "s.h5").events == 3
    with Session.open(tmp_path / "s.h5") as s:
        np.testing.assert_array_equal(s.events().x, [1, 3, 4])
        np.testing.assert_array_equal(s.events().t, [0, 20, 30])


def test_frames_state_the_color_filter(tmp_path):
    rng = np.random.default_rng(3)
    image = rng.integers(0, 1024, (260, 346))
    frames = frame_packet([(image, 1_000, 2_000, 0, 0)], 346 * 260, color_filter=1)  # RGBG
    src = aedat3_file(tmp_path / "c.aedat", [frames], sources=("DAVIS346B",))
    import_aedat3(src, tmp_path / "s.h5")
    with Session.open(tmp_path / "s.h5") as s:
        assert s.sensor.color_filter == "RGBG"
        np.testing.assert_array_equal(s.frames().data[0], image)
    with pytest.raises(InputError, match="state color filter RGBG, not GBGR"):
        import_aedat3(src, tmp_path / "o.h5", color_filter="GBGR")
    # events alone do not state it: the option does
    only_events = aedat3_file(tmp_path / "e.aedat", [polarity_packet([1], [2], [1], [5])])
    import_aedat3(only_events, tmp_path / "e.h5", color_filter="GBGR")
    with Session.open(tmp_path / "e.h5") as s:
        assert s.sensor.color_filter == "GBGR"


def test_a_frame_roi_and_an_unnamed_sensor(tmp_path):
    rng = np.random.default_rng(4)
    roi = rng.integers(0, 1024, (20, 30))
    frames = frame_packet([(roi, 100, 200, 10, 5)], 30 * 20)
    src = aedat3_file(
        tmp_path / "u.aedat",
        [polarity_packet([63], [47], [1], [50]), frames],
        sources=("SomeCamera",),
    )
    import_aedat3(src, tmp_path / "s.h5")
    with Session.open(tmp_path / "s.h5") as s:
        # the size the data spans: the event at (63, 47)
        assert (s.sensor.sensor, s.sensor.width, s.sensor.height) == ("SomeCamera", 64, 48)
        data = s.frames().data[0]
        np.testing.assert_array_equal(data[5:25, 10:40], roi)
        assert data.sum() == roi.sum()


def test_a_timestamp_reset_continues_from_the_last_time(tmp_path):
    before = polarity_packet([1, 2], [1, 2], [1, 1], [1_000, 1_500])
    reset = special_packet([1], [2**31 - 1])  # libcaer stamps the reset INT32_MAX
    after = polarity_packet([3, 4], [3, 4], [0, 0], [10, 30])
    src = aedat3_file(tmp_path / "r.aedat", [before, reset, after], sources=("DVS128",))
    summary = import_aedat3(src, tmp_path / "s.h5")
    assert (summary.events, summary.triggers) == (4, 1)
    with Session.open(tmp_path / "s.h5") as s:
        np.testing.assert_array_equal(s.events().t, [0, 500, 510, 530])
        trig = s.triggers()
        assert list(trig.t) == [500] and list(trig.kind) == [0]  # TIMESTAMP_RESET


def test_truncated_file_keeps_what_is_whole(tmp_path):
    rng = np.random.default_rng(5)
    x, y, p, t = random_events(rng, 300, 128, 128, 0, 10_000)
    first = polarity_packet(x[:100], y[:100], p[:100], t[:100])
    second = polarity_packet(x[100:], y[100:], p[100:], t[100:])
    src = aedat3_file(tmp_path / "t.aedat", [first, second], sources=("DVS128",))
    data = src.read_bytes()
    second_at = len(data) - len(second)
    src.write_bytes(data[:-12])  # the last event is cut, and half the one before
    with pytest.raises(ForeignFormatError, match=f"truncated.*packet at byte {second_at}") as e:
        import_aedat3(src, tmp_path / "s.h5")
    assert e.value.summary.events == 298 and "\n" not in str(e.value)
    with Session.open(tmp_path / "s.h5") as s:
        np.testing.assert_array_equal(s.events().x, x[:298])
    # cut inside a packet header: the packets before it are whole
    src.write_bytes(data[: second_at + 10])
    with pytest.raises(ForeignFormatError, match=f"inside the packet header at byte {second_at}"):
        import_aedat3(src, tmp_path / "s.h5", overwrite=True)
    assert len(read_layout(src).packets) == 1


def test_header_problems(tmp_path):
    bad = tmp_path / "bad.aedat"
    bad.write_bytes(b"#!AER-DAT2.0\r\n# AEChip: DVS128\r\n")
    with pytest.raises(ForeignFormatError, match="AEDAT 2.0, not AEDAT 3.1"):
        import_aedat3(bad, tmp_path / "s.h5")
    bad.write_bytes(b"#!AER-DAT3.1\r\n#Format: SerializedTS\r\n#!END-HEADER\r\n")
    with pytest.raises(ForeignFormatError, match="'SerializedTS'; evcap reads RAW"):
        import_aedat3(bad, tmp_path / "s.h5")
    bad.write_bytes(b"#!AER-DAT3.1\r\n#Format: RAW\r\n#Source 1: DVS128\r\n")
    with pytest.raises(ForeignFormatError, match="its header has no end"):
        import_aedat3(bad, tmp_path / "s.h5")
    bad.write_bytes(b"\x00" * 40)
    with pytest.raises(ForeignFormatError, match="not an AEDAT file"):
        import_aedat3(bad, tmp_path / "s.h5")
    assert not (tmp_path / "s.h5").exists()


def test_events_outside_the_named_sensor(tmp_path):
    src = aedat3_file(tmp_path / "o.aedat", [polarity_packet([200], [5], [1], [5])], ("DVS128",))
    with pytest.raises(ForeignFormatError, match=r"at \(200, 5\), outside the 128 x 128 sensor"):
        import_aedat3(src, tmp_path / "s.h5")
    assert not (tmp_path / "s.h5").exists()
