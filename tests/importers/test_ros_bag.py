"""ROS bag import: bags written here with rosbags' writers (ROS 1, ROS 2 sqlite3 and MCAP),
read back through the importer and compared with what went in."""

import json
import sqlite3
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
from ros_helpers import (
    Bag,
    evt3_reference,
    evt3_words,
    libcaer_cmp_packet,
    libcaer_cmp_reference,
    libcaer_packet,
)

from evcap.errors import ForeignFormatError, InputError, OutputExistsError
from evcap.importers.ros_bag import import_ros_bag
from evcap.importers.ros_events import Evt3Decoder, LibcaerCmpDecoder, dvs_event_array
from evcap.importers.ros_images import image_values
from evcap.session import Session

T0_NS = 1_700_000_000_123_456_789  # a Unix time with sub-microsecond digits, as ROS stamps have
W, H = 346, 260


def random_events(n, seed=0, width=W, height=H, t0_us=0, span_us=200_000):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, span_us, n)) + t0_us
    x = rng.integers(0, width, n)
    y = rng.integers(0, height, n)
    p = rng.integers(0, 2, n)
    return x, y, t, p


def add_dvs(bag, topic, x, y, t_us, p, messages=7, width=W, height=H):
    """Events as dvs_msgs arrays; the ROS times keep the sub-microsecond part of T0_NS."""
    t_ns = T0_NS + np.asarray(t_us, np.int64) * 1000
    for chunk in np.array_split(np.arange(len(t_us)), messages):
        bag.dvs(
            topic,
            int(t_ns[chunk[-1]]) + 1,
            x[chunk],
            y[chunk],
            t_ns[chunk],
            p[chunk],
            width,
            height,
            frame_id="davis"[: len(chunk) % 6],
        )


def check_events(session, x, y, t_us, p):
    ev = session.events()
    np.testing.assert_array_equal(ev.x, x)
    np.testing.assert_array_equal(ev.y, y)
    np.testing.assert_array_equal(ev.t, t_us)
    np.testing.assert_array_equal(ev.p, p)


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_dvs_round_trip(tmp_path, kind):
    x, y, t, p = random_events(3000, seed=1, t0_us=3_000)
    bag = Bag(kind)
    add_dvs(bag, "/dvs/events", x, y, t, p)
    rng = np.random.default_rng(2)
    frames = rng.integers(0, 256, (3, H, W), dtype=np.uint8)
    frame_t = [1_000, 60_000, 150_000]  # the first frame comes before the first event
    for image, ft in zip(frames, frame_t, strict=True):
        bag.image("/dvs/image_raw", T0_NS + ft * 1000, "mono8", image)
    accel, gyro = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    imu_t = np.arange(50) * 4_000 + 2_000
    for a, g, it in zip(accel, gyro, imu_t, strict=True):
        bag.imu("/dvs/imu", T0_NS + int(it) * 1000, a, g)
    # another camera's topics are left alone
    bag.image("/other/image_raw", T0_NS, "mono8", frames[0])
    src = bag.write(tmp_path / "rec")
    if kind == "ros1":  # told by its content, not its name
        src = src.rename(tmp_path / "recording.bag.active")
    calls = []
    summary = import_ros_bag(src, tmp_path / "out.h5", progress=lambda d, n: calls.append((d, n)))

    assert (summary.events, summary.frames, summary.imu) == (3000, 3, 50)
    assert "/dvs/image_raw (mono8)" in summary.source and "/other" not in summary.source
    assert calls[-1][0] == calls[-1][1] == 7 + 3 + 50
    with Session.open(tmp_path / "out.h5") as s:
        assert (s.sensor.sensor, s.sensor.width, s.sensor.height) == ("DAVIS346", W, H)
        assert s.sensor.color_filter == "MONO"
        assert s.sensor.t_offset_us == T0_NS // 1000 + 1_000  # the first frame's stamp
        check_events(s, x, y, t - 1_000, p)
        assert (s.n_events, int(s.events().t[0]), int(s.events().t[-1])) == (
            3000,
            t[0] - 1_000,
            t[-1] - 1_000,
        )
        fr = s.frames()
        np.testing.assert_array_equal(fr.data, frames.astype(np.uint16) << 2)
        np.testing.assert_array_equal(fr.t, np.array(frame_t) - 1_000)
        np.testing.assert_array_equal(fr.exposure_us, 0)
        imu = s.imu()
        np.testing.assert_array_equal(imu.t, imu_t - 1_000)
        np.testing.assert_array_equal(imu.accel, accel.astype(np.float32))
        np.testing.assert_array_equal(imu.gyro, gyro.astype(np.float32))
        assert np.isnan(imu.temperature).all()
    with h5py.File(tmp_path / "out.h5") as f:
        assert f["frames"].attrs["precision_bits"] == 8
        assert json.loads(f.attrs["source_topics"]) == {
            "events": "/dvs/events",
            "frames": "/dvs/image_raw",
            "imu": "/dvs/imu",
        }
        assert f.attrs["source_format"].startswith("ROS 1" if kind == "ros1" else "ROS 2")


@pytest.mark.parametrize("kind", ["sqlite3", "mcap"])
def test_bare_storage_file_and_cdr_layouts(tmp_path, kind):
    """Arrays of 0, 1, 2 and more events, frame ids of every length mod 4 (CDR alignment),
    read from the storage file itself; Bayer images give the color filter."""
    x, y, t, p = random_events(40, seed=3)
    bag = Bag(kind)
    t_ns = T0_NS + t * 1000
    for i, (a, b) in enumerate([(0, 1), (1, 3), (3, 3), (3, 20), (20, 40)]):
        bag.dvs(
            "/dvs/events",
            int(t_ns[max(b - 1, 0)]) + i,
            x[a:b],
            y[a:b],
            t_ns[a:b],
            p[a:b],
            frame_id="abcd"[:i],
        )
    raw = np.random.default_rng(4).integers(0, 1 << 16, (H, W), dtype=np.uint16)
    bag.image("/dvs/image_raw", T0_NS + 900_000_000, "bayer_rggb16", raw)
    folder = bag.write(tmp_path / "rec")
    storage = next(folder.glob("*.mcap" if kind == "mcap" else "*.db3"))
    summary = import_ros_bag(storage, tmp_path / "out.h5")
    assert (summary.events, summary.frames) == (40, 1)
    with Session.open(tmp_path / "out.h5") as s:
        assert (s.sensor.sensor, s.sensor.color_filter) == ("Color-DAVIS346", "RGBG")
        check_events(s, x, y, t - t[0], p)
        np.testing.assert_array_equal(s.frames().data[0], raw >> 6)


@pytest.mark.parametrize("n", [0, 1, 2, 5])
def test_big_endian_cdr(n):
    x, y, t, p = random_events(n, seed=n)
    bag = Bag("mcap")
    bag.dvs("/e", 0, x, y, T0_NS + t * 1000, p, frame_id="ab")
    raw = bag.store.serialize_cdr(
        bag.messages[0][4], "dvs_msgs/msg/EventArray", little_endian=False
    )
    width, height, events = dvs_event_array(raw, cdr=True)
    assert (width, height) == (W, H)
    np.testing.assert_array_equal(events.x, x)
    np.testing.assert_array_equal(events.t_ns, T0_NS + t * 1000)
    np.testing.assert_array_equal(events.p, p)


def test_ros2_bag_without_definitions(tmp_path):
    """Bags recorded before ROS 2 Iron hold type names only: the known types are used."""
    x, y, t, p = random_events(500, seed=5)
    bag = Bag("sqlite3")
    add_dvs(bag, "/dvs/events", x, y, t, p)
    bag.imu("/dvs/imu", T0_NS + 10_000, (0.0, 0.0, 9.8), (0.1, 0.2, 0.3))
    folder = bag.write(tmp_path / "rec")
    with sqlite3.connect(next(folder.glob("*.db3"))) as db:
        db.execute("DELETE FROM message_definitions")
    summary = import_ros_bag(folder, tmp_path / "out.h5")
    assert (summary.events, summary.imu) == (500, 1)
    with Session.open(tmp_path / "out.h5") as s:
        check_events(s, x, y, t - t[0], p)


def runs(groups, seed, offsets, width=W, height=H, t0_us=0, span_us=300_000):
    """Events in runs of 1 to 4 sharing time, polarity and one coordinate, the other at the
    given offsets (so that the vector words are used); the run's axis is returned first."""
    rng = np.random.default_rng(seed)
    sizes = rng.integers(1, 5, groups)
    t = np.sort(rng.integers(0, span_us, groups)).repeat(sizes) + t0_us
    along = rng.integers(0, width - 24, groups).repeat(sizes)
    along += np.concatenate([offsets[:k] for k in sizes])
    across = rng.integers(0, height, groups).repeat(sizes)
    p = rng.integers(0, 2, groups).repeat(sizes)
    return along, across, t, p


def packet_of(splits, index):
    return int(np.searchsorted(splits, index, "right")) - 1


def test_evt3_packets(tmp_path):
    """EVT 3.0 across packets split anywhere, a packet starting with the 2^24 us rollover of
    the time high; the times are the sensor's, placed at the stamp of the packet that brought
    the first event."""
    x, y, t, p = runs(1500, 6, [0, 1, 5, 13], 640, 480, t0_us=(1 << 24) - 150_000)
    # and one event beyond the sensor, which the decoder drops
    words = evt3_words(np.r_[x, 640], np.r_[y, 7], np.r_[t, t[-1]], np.r_[p, 1], 640)
    words = np.array(words, "<u2")
    bag = Bag("mcap")
    highs = np.flatnonzero(words >> 12 == 8)
    rollover = int(highs[np.flatnonzero(np.diff(words[highs].astype(int) & 0xFFF) < 0)[0] + 1])
    splits = [0, 5, 6, 1001, 1002, 2500, rollover, words.size]  # one packet starts with it
    stamp0 = T0_NS + 777_000
    for i, (a, b) in enumerate(zip(splits[:-1], splits[1:], strict=True)):
        stamp = stamp0 + i * 10**6
        bag.packet("/prophesee/events", stamp, stamp, "evt3", words[a:b].tobytes(), 0, 640, 480, i)
    first_event = next(i for i, w in enumerate(words) if i > 2 and w >> 12 in (2, 4, 5))
    summary = import_ros_bag(bag.write(tmp_path / "rec"), tmp_path / "out.h5")
    assert summary.events == t.size and "evt3" in summary.source
    with Session.open(tmp_path / "out.h5") as s:
        assert (s.sensor.sensor, s.sensor.width, s.sensor.height) == ("unknown", 640, 480)
        stamp = stamp0 + packet_of(splits, first_event) * 10**6
        assert s.sensor.t_offset_us == stamp // 1000
        check_events(s, x, y, t - t[0], p)
        assert int(s.events().t[-1]) > 150_000  # went past the rollover


@pytest.mark.parametrize("kind", ["sqlite3", "ros1"])
def test_libcaer_cmp_packets(tmp_path, kind):
    y, x, t, p = runs(1000, 7, [0, 2, 3, 11], H, W, t0_us=40_000_000)
    base_ns = 1_650_000_000_000_000_321  # the driver's ROS time at start-up
    bag = Bag(kind)
    for i, chunk in enumerate(np.array_split(np.arange(t.size), 6)):
        time_base = base_ns + int(t[chunk[0]]) * 1000
        data = libcaer_cmp_packet(x[chunk], y[chunk], t[chunk], p[chunk])
        bag.packet(
            "/event_camera/events", time_base, time_base, "libcaer_cmp", data, time_base, W, H, i
        )
    summary = import_ros_bag(bag.write(tmp_path / "rec"), tmp_path / "out.h5")
    assert summary.events == t.size
    with Session.open(tmp_path / "out.h5") as s:
        assert s.sensor.sensor == "DAVIS346"
        assert s.sensor.t_offset_us == (base_ns + int(t[0]) * 1000) // 1000
        check_events(s, x, y, t - t[0], p)


def test_libcaer_wraps_within_and_between_packets(tmp_path):
    """libcaer's 31-bit microsecond timestamps wrap every 2^31 us: the driver moves the wraps
    before a packet into its time_base, the decoder counts those inside it."""
    x, y, t, p = random_events(900, seed=8, t0_us=(1 << 31) - 3_000, span_us=9_000)
    x2, y2, t2, p2 = random_events(300, seed=9, t0_us=(2 << 31) - 1_000, span_us=2_000)
    x, y, t, p = (np.r_[a, b] for a, b in [(x, x2), (y, y2), (t, t2), (p, p2)])
    base_ns = 1_650_000_000_000_000_321
    bag = Bag("mcap")
    cuts = [0, 100, 450, 700, 900, 1000, 1200]  # one packet wraps inside, others between
    for i, (a, b) in enumerate(zip(cuts[:-1], cuts[1:], strict=True)):
        high_us, data = libcaer_packet(x[a:b], y[a:b], t[a:b], p[a:b])
        time_base = base_ns + high_us * 1000
        bag.packet(
            "/event_camera/events", time_base, time_base, "libcaer", data, time_base, W, H, i
        )
    import_ros_bag(bag.write(tmp_path / "rec"), tmp_path / "out.h5")
    with Session.open(tmp_path / "out.h5") as s:
        assert s.sensor.t_offset_us == (base_ns + int(t[0]) * 1000) // 1000
        check_events(s, x, y, t - t[0], p)


@pytest.mark.parametrize("seed", range(4))
def test_decoders_match_a_word_by_word_reading(seed):
    """Random words of every code, cut into packets anywhere: the vectorised decoders give
    what reading one word at a time gives."""
    rng = np.random.default_rng(seed)
    for codes, decoder, reference in (
        ([0, 0, 2, 2, 3, 4, 5, 6, 8, 9, 10, 14, 15], Evt3Decoder(), evt3_reference),
        ([0, 1, 2, 3, 3, 4, 5, 5], LibcaerCmpDecoder(), libcaer_cmp_reference),
    ):
        n = 3000
        words = (rng.choice(codes, n) << 12) | rng.integers(0, 1 << 12, n)
        words[words >> 12 == 8] &= 0xF00F  # time highs close together: few rollovers
        cuts = np.sort(rng.choice(np.arange(1, n), 12, replace=False))
        packets = [w.astype("<u2").tobytes() for w in np.split(words, cuts)]
        got = [decoder.decode(np.frombuffer(d, np.uint8), 0, 1500, 900) for d in packets]
        want = reference(packets, 1500, 900)
        for i, name in enumerate(("x", "y", "t_ns", "p")):
            values = np.concatenate([getattr(g, name) for g in got]).astype(np.int64)
            np.testing.assert_array_equal(values, want[i] * (1000 if name == "t_ns" else 1))


def two_cameras(tmp_path):
    bag = Bag("ros1")
    left = random_events(300, seed=10, t0_us=5_000)
    right = random_events(200, seed=11, t0_us=9_000)
    add_dvs(bag, "/davis/left/events", *left, messages=3)
    add_dvs(bag, "/davis/right/events", *right, messages=2)
    for side, value in (("left", 10), ("right", 20)):
        image = np.full((H, W), value, np.uint8)
        bag.image(f"/davis/{side}/image_raw", T0_NS + 20_000_000, "mono8", image)
    bag.add(
        "/davis/left/exposure",
        "std_msgs/msg/Int32",
        T0_NS,
        bag.store.types["std_msgs/msg/Int32"](data=3),
    )
    return bag.write(tmp_path / "stereo"), left, right


def test_topic_choice(tmp_path):
    src, left, right = two_cameras(tmp_path)
    summary = import_ros_bag(src, tmp_path / "left.h5")
    assert summary.events == 300
    import_ros_bag(src, tmp_path / "right.h5", topic="/davis/right/events")
    with Session.open(tmp_path / "left.h5") as s:
        check_events(s, left[0], left[1], left[2] - left[2][0], left[3])
        assert int(s.frames().data.max()) == 10 << 2
    with Session.open(tmp_path / "right.h5") as s:
        check_events(s, right[0], right[1], right[2] - right[2][0], right[3])
        assert int(s.frames().data.max()) == 20 << 2


def test_refusals(tmp_path):
    src, _, _ = two_cameras(tmp_path)
    with pytest.raises(InputError, match=r"std_msgs/msg/Int32.*dvs_msgs/msg/EventArray"):
        import_ros_bag(src, tmp_path / "a.h5", topic="/davis/left/exposure")
    with pytest.raises(InputError, match=r"no topic '/dvs/events'.*/davis/left/events"):
        import_ros_bag(src, tmp_path / "a.h5", topic="/dvs/events")
    bag = Bag("mcap")
    bag.packet("/ev", T0_NS, T0_NS, "mono", b"\0" * 8, T0_NS, W, H, 0)
    with pytest.raises(InputError, match=r"'mono' is not known.*evt3, libcaer_cmp, libcaer"):
        import_ros_bag(bag.write(tmp_path / "mono"), tmp_path / "a.h5")
    bag = Bag("ros1")
    bag.imu("/dvs/imu", T0_NS, (0, 0, 1), (0, 0, 0))
    with pytest.raises(InputError, match=r"no event messages.*/dvs/imu \(sensor_msgs/msg/Imu\)"):
        import_ros_bag(bag.write(tmp_path / "imu"), tmp_path / "a.h5")
    bag = Bag("ros1", event_msg="uint16 x\nuint16 y\ntime ts\nint8 polarity\n")
    add_dvs(bag, "/dvs/events", *random_events(10), messages=1)
    with pytest.raises(ForeignFormatError, match=r"dvs_msgs/msg/Event in this bag.*not rpg_dvs"):
        import_ros_bag(bag.write(tmp_path / "other_dvs"), tmp_path / "a.h5")
    (tmp_path / "b.h5").touch()
    with pytest.raises(OutputExistsError):
        import_ros_bag(src, tmp_path / "b.h5")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(ForeignFormatError, match="not a ROS bag"):
        import_ros_bag(tmp_path / "notes.txt", tmp_path / "c.h5")
    (tmp_path / "broken.bag").write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 100)
    with pytest.raises(ForeignFormatError, match="cannot read the ROS bag"):
        import_ros_bag(tmp_path / "broken.bag", tmp_path / "c.h5")
    assert not (tmp_path / "a.h5").exists() and not (tmp_path / "c.h5").exists()


def test_color_from_topic_names_and_option(tmp_path):
    """CED-style /dvs/image_color: the Color-DAVIS346 (RGBG); its rgb8 images keep each
    pixel's own channel; the option overrules the name. A Bayer encoding states the filter:
    an option that contradicts it is an error."""
    x, y, t, p = random_events(100, seed=12)
    bag = Bag("ros1")
    add_dvs(bag, "/dvs/events", x, y, t, p, messages=2)
    rgb = np.random.default_rng(13).integers(0, 256, (H, W, 3), dtype=np.uint8)
    bag.image("/dvs/image_color", T0_NS + 50_000_000, "rgb8", rgb)
    src = bag.write(tmp_path / "ced")
    import_ros_bag(src, tmp_path / "ced.h5")
    with Session.open(tmp_path / "ced.h5") as s:
        assert (s.sensor.sensor, s.sensor.color_filter) == ("Color-DAVIS346", "RGBG")
        raw = s.frames().data[0] >> 2
        assert raw[0, 0] == rgb[0, 0, 0] and raw[0, 1] == rgb[0, 1, 1]
        assert raw[1, 1] == rgb[1, 1, 2] and raw[1, 0] == rgb[1, 0, 1]
    import_ros_bag(src, tmp_path / "mono.h5", color_filter="MONO")
    with Session.open(tmp_path / "mono.h5") as s:
        assert s.sensor.color_filter == "MONO" and s.n_frames == 0  # rgb8 of a MONO sensor

    bag = Bag("ros1")
    add_dvs(bag, "/dvs/events", x, y, t, p, messages=2)
    bag.image("/dvs/image_raw", T0_NS, "bayer_grbg8", rgb[..., 0])
    src = bag.write(tmp_path / "bayer")
    with pytest.raises(InputError, match="bayer_grbg8 \\(GRGB\\).*RGBG contradicts"):
        import_ros_bag(src, tmp_path / "a.h5", color_filter="RGBG")
    import_ros_bag(src, tmp_path / "b.h5", color_filter="GRGB")
    with Session.open(tmp_path / "b.h5") as s:
        assert s.sensor.color_filter == "GRGB"
        np.testing.assert_array_equal(s.frames().data[0], rgb[..., 0].astype(np.uint16) << 2)


def test_image_encodings():
    """Padded rows, byte order, BGR order, and the encodings that are refused."""
    rng = np.random.default_rng(14)
    rgb = rng.integers(0, 256, (4, 6, 3), dtype=np.uint8)

    def image(encoding, pixels, big=False, pad=2):
        rows = pixels.reshape(pixels.shape[0], -1).view(np.uint8)
        data = np.pad(rows, ((0, 0), (0, pad))).reshape(-1)
        return SimpleNamespace(
            encoding=encoding,
            height=pixels.shape[0],
            width=pixels.shape[1],
            step=rows.shape[1] + pad,
            is_bigendian=big,
            data=data,
        )

    as_rgb = image_values(image("rgb8", rgb), "GBGR")
    np.testing.assert_array_equal(
        image_values(image("bgr8", rgb[..., ::-1].copy()), "GBGR"), as_rgb
    )
    assert as_rgb[0, 0] == int(rgb[0, 0, 1]) << 2 and as_rgb[0, 1] == int(rgb[0, 1, 2]) << 2
    mono = rng.integers(0, 1 << 16, (4, 6), dtype=np.uint16)
    np.testing.assert_array_equal(image_values(image("mono16", mono), "MONO"), mono >> 6)
    big = image("mono16", mono.byteswap(), big=True)
    np.testing.assert_array_equal(image_values(big, "MONO"), mono >> 6)
    with pytest.raises(InputError, match="'yuv422' are not supported"):
        image_values(image("yuv422", rgb[..., :2].copy()), "MONO")
