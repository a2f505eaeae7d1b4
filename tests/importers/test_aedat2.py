"""AEDAT 2.0 (jAER) import: files written here from jAER's address layouts, read back exactly."""

import numpy as np
import pytest

from evcap.errors import ForeignFormatError, OutputExistsError
from evcap.importers.aedat2 import import_aedat2
from evcap.session import Session

DATA_START_MS = 1_500_000_000_123
G = 9.80665


# -- a tiny AEDAT 2.0 writer (jAER's layouts, independent of the reader) -------------------------


def aedat2_file(path, chip_class, t, address, *, end_line=True):
    """Header lines, then big-endian (int32 address, int32 timestamp) records, in time order."""
    lines = [
        b"#!AER-DAT2.0",
        b"# This is a raw AE data file - do not edit",
        b"# Data format is int32 address, int32 timestamp (8 bytes total)",
        b"# AEChip: " + chip_class.encode(),
        b"# DataStartTime: System.currentTimeMillis() " + str(DATA_START_MS).encode(),
    ]
    if end_line:
        lines.append(b"#End Of ASCII Header")
    t, address = np.asarray(t, np.int64), np.asarray(address, np.int64)
    order = np.argsort(t, kind="stable")
    records = np.empty((t.size, 2), ">u4")
    records[:, 0] = address[order] & 0xFFFFFFFF
    records[:, 1] = t[order] & 0xFFFFFFFF  # jAER's 32-bit timestamps wrap
    path.write_bytes(b"\r\n".join(lines) + b"\r\n" + records.tobytes())
    return path


def dvs128_address(x, y, p):
    # bit 0: 0 = ON; x and y stored mirrored (jAER: x flipped by the extractor, y up)
    return ((127 - y) << 8) | ((127 - x) << 1) | (1 - p)


def davis_dvs_address(x, y, p, w, h):
    return ((h - 1 - y) << 22) | ((w - 1 - x) << 12) | (p << 11)


def davis_imu(t, raw):
    """7 records per sample (ax, ay, az, temperature, gx, gy, gz), one timestamp."""
    codes = np.arange(7)
    address = (1 << 31) | (3 << 10) | (codes << 28) | ((raw.astype(np.int64) & 0xFFFF) << 12)
    return np.repeat(t, 7), address.ravel()


def davis_frame(image, t_reset, t_signal, w, h, reset_value=900):
    """A global-shutter readout: every pixel's reset read, then every signal read."""
    yy, xx = np.mgrid[0:h, 0:w]
    xx, yy = xx.ravel()[::-1], yy.ravel()[::-1]  # jAER reads from the far corner
    pos = ((h - 1 - yy) << 22) | (xx << 12) | (1 << 31)
    signal = reset_value - image[yy, xx].astype(np.int64)
    t = np.concatenate([np.full(xx.size, t_reset), np.full(xx.size, t_signal)])
    address = np.concatenate([pos | reset_value, pos | (1 << 10) | signal])
    return t, address


def random_events(rng, n, w, h, t0, t1):
    t = np.sort(rng.integers(t0, t1, n))
    return rng.integers(0, w, n), rng.integers(0, h, n), rng.integers(0, 2, n), t


# -- tests ---------------------------------------------------------------------------------------


def test_dvs128_round_trip_across_a_timestamp_wrap(tmp_path):
    rng = np.random.default_rng(1)
    start = (1 << 32) - 5_000  # the 32-bit timestamps wrap 5 ms in
    x, y, p, t = random_events(rng, 3_000, 128, 128, start, start + 20_000)
    sync_t = np.array([start + 7_000])
    src = aedat2_file(
        tmp_path / "dvs128.aedat",
        "ch.unizh.ini.jaer.chip.retina.DVS128",
        np.concatenate([t, sync_t]),
        np.concatenate([dvs128_address(x, y, p), [0x8000]]),
    )
    summary = import_aedat2(src, tmp_path / "s.h5")
    assert (summary.events, summary.triggers) == (3_000, 1)
    assert summary.source == "AEDAT 2.0, DVS128"
    with Session.open(tmp_path / "s.h5") as s:
        assert (s.sensor.sensor, s.sensor.width, s.sensor.height) == ("DVS128", 128, 128)
        assert s.sensor.t_offset_us == DATA_START_MS * 1000
        ev = s.events()
        np.testing.assert_array_equal(ev.x, x)
        np.testing.assert_array_equal(ev.y, y)
        np.testing.assert_array_equal(ev.p, p)
        np.testing.assert_array_equal(ev.t, t - t[0])
        assert (int(ev.t[0]), int(ev.t[-1])) == (0, int(t[-1] - t[0]))
        trig = s.triggers()
        np.testing.assert_array_equal(trig.t, sync_t - t[0])


def frame_image(rng, w, h):
    return rng.integers(0, 800, (h, w))


@pytest.mark.parametrize(
    "chip_class, w, h",
    [
        ("eu.seebetter.ini.chips.davis.DAVIS240C", 240, 180),
        ("eu.seebetter.ini.chips.davis.Davis346B", 346, 260),
        ("eu.seebetter.ini.chips.davis.Davis346red", 346, 260),
    ],
)
def test_davis_events_imu_and_frames(tmp_path, chip_class, w, h):
    rng = np.random.default_rng(2)
    x, y, p, t = random_events(rng, 5_000, w, h, 1_000, 90_000)
    imu_t = np.arange(2_000, 90_000, 10_000)
    imu_raw = rng.integers(-30_000, 30_000, (imu_t.size, 7))
    it, ia = davis_imu(imu_t, imu_raw)
    images = [frame_image(rng, w, h) for _ in range(2)]
    f1 = davis_frame(images[0], 20_000, 25_000, w, h)
    f2 = davis_frame(images[1], 60_000, 62_000, w, h)
    src = aedat2_file(
        tmp_path / "davis.aedat",
        chip_class,
        np.concatenate([t, it, f1[0], f2[0]]),
        np.concatenate([davis_dvs_address(x, y, p, w, h), ia, f1[1], f2[1]]),
    )
    summary = import_aedat2(src, tmp_path / "s.h5")
    assert (summary.events, summary.imu, summary.frames) == (5_000, imu_t.size, 2)
    t0 = min(int(t[0]), int(imu_t[0]))
    with Session.open(tmp_path / "s.h5") as s:
        assert (s.sensor.sensor, s.sensor.width, s.sensor.height) == (
            chip_class.rsplit(".", 1)[1],
            w,
            h,
        )
        ev = s.events()
        np.testing.assert_array_equal(ev.x, x)
        np.testing.assert_array_equal(ev.y, y)
        np.testing.assert_array_equal(ev.p, p)
        np.testing.assert_array_equal(ev.t, t - t0)
        imu = s.imu()
        np.testing.assert_array_equal(imu.t, imu_t - t0)
        np.testing.assert_allclose(imu.accel, imu_raw[:, :3] / 8192 * G, rtol=1e-6)
        np.testing.assert_allclose(imu.gyro, np.deg2rad(imu_raw[:, 4:] / 65.5), rtol=1e-6)
        np.testing.assert_allclose(imu.temperature, imu_raw[:, 3] / 340 + 35, rtol=1e-6)
        fr = s.frames()
        np.testing.assert_array_equal(fr.data, np.stack(images))
        # global shutter: exposure from the last reset read to the first signal read
        np.testing.assert_array_equal(fr.t, [20_000 - t0, 60_000 - t0])
        np.testing.assert_array_equal(fr.exposure_us, [5_000, 2_000])


def test_a_frame_the_recording_starts_within_is_left_out(tmp_path):
    w, h = 240, 180
    rng = np.random.default_rng(3)
    image = frame_image(rng, w, h)
    first = davis_frame(frame_image(rng, w, h), 1_000, 2_000, w, h)
    second = davis_frame(image, 10_000, 11_000, w, h)
    half = first[0].size // 2 + 100  # the file starts in the middle of the first readout
    src = aedat2_file(
        tmp_path / "f.aedat",
        "eu.seebetter.ini.chips.davis.DAVIS240C",
        np.concatenate([first[0][half:], second[0]]),
        np.concatenate([first[1][half:], second[1]]),
    )
    assert import_aedat2(src, tmp_path / "s.h5").frames == 1
    with Session.open(tmp_path / "s.h5") as s:
        np.testing.assert_array_equal(s.frames().data[0], image)


def test_a_timestamp_reset_continues_from_the_last_time(tmp_path):
    t = np.array([100, 200, 300, 40, 50])  # jAER's timestamps restart after a reset
    x, y, p = np.array([1, 2, 3, 4, 5]), np.array([5, 4, 3, 2, 1]), np.array([1, 0, 1, 0, 1])
    src = tmp_path / "r.aedat"
    # written in file order, not sorted: the reset is a step back
    lines = b"#!AER-DAT2.0\r\n# AEChip: ch.unizh.ini.jaer.chip.retina.DVS128\r\n"
    records = np.stack([dvs128_address(x, y, p), t], axis=1).astype(">u4")
    src.write_bytes(lines + records.tobytes())
    import_aedat2(src, tmp_path / "s.h5")
    with Session.open(tmp_path / "s.h5") as s:
        np.testing.assert_array_equal(s.events().t, [0, 100, 200, 200, 210])
        trig = s.triggers()
        assert list(trig.t) == [200] and list(trig.kind) == [0]  # TIMESTAMP_RESET
        assert s.sensor.t_offset_us == 0  # no DataStartTime in this header


def test_unknown_chip_class_is_refused(tmp_path):
    src = aedat2_file(tmp_path / "u.aedat", "ch.unizh.ini.jaer.chip.retina.Tmpdiff128", [1], [0])
    with pytest.raises(ForeignFormatError, match="unknown jAER chip class") as e:
        import_aedat2(src, tmp_path / "s.h5")
    message = str(e.value)
    assert "Tmpdiff128" in message and "DVS128" in message and "DAVIS240" in message
    assert "pass --chip" in message
    assert "\n" not in message and not (tmp_path / "s.h5").exists()


def test_chip_class_that_does_not_match_the_data(tmp_path):
    address = davis_dvs_address(np.array([10]), np.array([5]), np.array([1]), 346, 260)
    src = aedat2_file(tmp_path / "m.aedat", "eu.seebetter.ini.chips.davis.DAVIS240C", [5], address)
    with pytest.raises(ForeignFormatError, match="outside the 240 x 180 sensor of chip DAVIS240C"):
        import_aedat2(src, tmp_path / "s.h5")
    assert not (tmp_path / "s.h5").exists()


def test_truncated_file_keeps_the_whole_records(tmp_path):
    rng = np.random.default_rng(4)
    x, y, p, t = random_events(rng, 100, 128, 128, 0, 10_000)
    src = aedat2_file(
        tmp_path / "t.aedat", "ch.unizh.ini.jaer.chip.retina.DVS128", t, dvs128_address(x, y, p)
    )
    data = src.read_bytes()
    src.write_bytes(data[:-5])  # the last record is cut
    with pytest.raises(ForeignFormatError, match=f"truncated.*byte {len(data) - 8}") as e:
        import_aedat2(src, tmp_path / "s.h5")
    assert e.value.summary.events == 99
    with Session.open(tmp_path / "s.h5") as s:
        np.testing.assert_array_equal(s.events().x, x[:99])


def test_header_problems(tmp_path):
    bad = tmp_path / "bad.aedat"
    bad.write_bytes(b"#!AER-DAT3.1\r\n#Format: RAW\r\n")
    with pytest.raises(ForeignFormatError, match="AEDAT 3.1, not AEDAT 2.0"):
        import_aedat2(bad, tmp_path / "s.h5")
    # no '# AEChip:' line and addresses that fit no chip (headerless files that fit one are
    # read: test_aedat2_headerless.py)
    bad.write_bytes(b"#!AER-DAT2.0\r\n# no chip here\r\n" + (0x7FFFF000).to_bytes(4) + bytes(4))
    with pytest.raises(ForeignFormatError, match="no '# AEChip:' header line.*pass --chip"):
        import_aedat2(bad, tmp_path / "s.h5")
    bad.write_bytes(b"#!AER-DAT2.0\r\n# AEChip: eu.seebetter.ini.chips.davis.DAVIS240C")
    with pytest.raises(ForeignFormatError, match="truncated: it ends inside its header"):
        import_aedat2(bad, tmp_path / "s.h5")
    bad.write_bytes(b"hello")
    with pytest.raises(ForeignFormatError, match="not an AEDAT file"):
        import_aedat2(bad, tmp_path / "s.h5")


def test_existing_output_and_progress(tmp_path):
    src = aedat2_file(tmp_path / "e.aedat", "ch.unizh.ini.jaer.chip.retina.DVS128", [1, 2], [0, 2])
    out = tmp_path / "s.h5"
    out.write_text("keep me")
    with pytest.raises(OutputExistsError):
        import_aedat2(src, out)
    calls = []
    import_aedat2(
        src, out, overwrite=True, color_filter="RGBG", progress=lambda *a: calls.append(a)
    )
    assert calls[-1] == (src.stat().st_size, src.stat().st_size)
    with Session.open(out) as s:
        assert s.sensor.color_filter == "RGBG" and s.n_events == 2


def davis_rolling_frame(image, t_reset, exposure, w, h, column_us=10):
    """A rolling-shutter readout: column c is reset at t_reset + c * column_us and read
    ``exposure`` later, so that reset and signal reads interleave."""
    reset_value = 900
    records_t, records_a = [], []
    for c in range(w):
        y = np.arange(h)
        pos = ((h - 1 - y) << 22) | (c << 12) | (1 << 31)
        signal = reset_value - image[y, c].astype(np.int64)
        records_t += [
            np.full(h, t_reset + c * column_us),
            np.full(h, t_reset + exposure + c * column_us),
        ]
        records_a += [pos | reset_value, pos | (1 << 10) | signal]
    return np.concatenate(records_t), np.concatenate(records_a)


def test_rolling_shutter_frame_and_external_inputs(tmp_path):
    w, h = 240, 180
    rng = np.random.default_rng(5)
    image = frame_image(rng, w, h)
    ft, fa = davis_rolling_frame(image, 1_000, 300, w, h)
    ext_t = np.array([500, 600, 700, 800])
    ext_a = np.array([0x402, 0x403, 0x404, 0x400])  # falling, rising, pulse, edge not stated
    src = aedat2_file(
        tmp_path / "rs.aedat",
        "eu.seebetter.ini.chips.davis.DAVIS240C",
        np.concatenate([ext_t, ft]),
        np.concatenate([ext_a, fa]),
    )
    summary = import_aedat2(src, tmp_path / "s.h5")
    assert (summary.frames, summary.triggers) == (1, 3)
    with Session.open(tmp_path / "s.h5") as s:
        fr = s.frames()
        np.testing.assert_array_equal(fr.data[0], image)
        assert (int(fr.t[0]), int(fr.exposure_us[0])) == (500, 300)
        trig = s.triggers()
        assert list(trig.t) == [0, 100, 200] and list(trig.kind) == [2, 1, 3]


def test_block_boundaries_change_nothing(tmp_path, monkeypatch):
    """IMU samples and frames that a block boundary cuts are decoded whole."""
    import evcap.importers.aedat2 as aedat2

    w, h = 240, 180
    rng = np.random.default_rng(6)
    x, y, p, t = random_events(rng, 2_000, w, h, (1 << 32) - 30_000, (1 << 32) + 30_000)
    imu_t = np.arange((1 << 32) - 29_000, (1 << 32) + 29_000, 1_000)
    it, ia = davis_imu(imu_t, rng.integers(-30_000, 30_000, (imu_t.size, 7)))
    ft, fa = davis_frame(frame_image(rng, w, h), (1 << 32) - 100, (1 << 32) + 100, w, h)
    src = aedat2_file(
        tmp_path / "b.aedat",
        "eu.seebetter.ini.chips.davis.DAVIS240C",
        np.concatenate([t, it, ft]),
        np.concatenate([davis_dvs_address(x, y, p, w, h), ia, fa]),
    )
    whole = import_aedat2(src, tmp_path / "whole.h5")
    monkeypatch.setattr(aedat2, "_BLOCK", 1_003)
    blocks = import_aedat2(src, tmp_path / "blocks.h5")
    assert whole == blocks and (whole.events, whole.imu, whole.frames) == (2_000, imu_t.size, 1)
    with Session.open(tmp_path / "whole.h5") as a, Session.open(tmp_path / "blocks.h5") as b:
        np.testing.assert_array_equal(a.events().t, b.events().t)
        np.testing.assert_array_equal(a.imu().accel, b.imu().accel)
        np.testing.assert_array_equal(a.frames().data, b.frames().data)
