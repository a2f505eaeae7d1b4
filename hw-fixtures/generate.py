"""Make the hardware-replay fixtures in this folder (see README.md here for their format).

    .venv/bin/python hw-fixtures/generate.py            # (re)write the fixtures made here
    .venv/bin/python hw-fixtures/generate.py --demo     # (re)make the simulated ones (minutes)
    .venv/bin/python hw-fixtures/generate.py --check    # compare with what is committed

Each fixture's streams are made here, encoded into the DAVIS346 wire format with
evcap.acquire.encoder, and written with the content a correct decoder must give back
(expected.npz, expected.json). The expected content is computed here from the inputs, not by
decoding. Everything is seeded: the same code gives the same bytes.

The fixtures of `evcap demo` (demo-scene, demo-calibration) are simulated scenes
(sim/scenes/demo_orbit.toml, demo_calibration.toml) encoded by evcap.sim.fixture, with
demo-scene's ground truth beside it (truth.h5, evcap.sim.truth). Simulating them takes minutes,
so only --demo makes them; --check records each through the driver and compares it with its
expected content (counts, digests of the events and frames, the small streams) and checks that
its scene file is the one it was made from, in seconds.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from evcap.acquire.decoder import Geometry
from evcap.acquire.encoder import StreamEncoder
from evcap.acquire.fixture import FixtureContent as Content
from evcap.acquire.fixture import write_fixture
from evcap.events import Events
from evcap.streams import Frames, TriggerKind, Triggers

HERE = Path(__file__).resolve().parent
SHARED = Path(os.environ.get("EVCAP_SHARED", HERE.parent.parent / "shared"))
DEMO_DATA = HERE.parent / "app" / "demo_data"  # the demo's fixtures ship inside the package
SAMPLE = SHARED / "data" / "davis346-sample" / "davis346_test_data.aedat4"
SCENES = HERE.parent / "sim" / "scenes"
W, H = 346, 260
# The demo's camera: both recordings come from it (one sensor, one USB serial).
DEMO_SERIAL = "00000346"
DEMO = {
    "demo-scene": (
        "demo_orbit.toml",
        "simulated Color-DAVIS346 (the demo's camera): a checkered sphere, the camera "
        "orbiting it, 1 s, APS frames at 10 Hz, IMU at 1 kHz, a sensor with threshold "
        "spread, hot pixels and noise; its ground truth in truth.h5",
    ),
    "demo-calibration": (
        "demo_calibration.toml",
        "simulated Color-DAVIS346 (the demo's camera): the default ChArUco board, the "
        "camera swung in front of it, 1 s, APS frames, IMU at 1 kHz",
    ),
}


# -- scenes -------------------------------------------------------------------------------------


def moving_edge_events(rng, t0: int, t1: int, rate_hz: float) -> Events:
    """Events of a colored bar sweeping right across a Bayer (RGBG) sensor: red pixels turn ON
    at its leading edge, green and blue ones OFF; some background noise."""
    n = int((t1 - t0) * rate_hz / 1e6)
    t = np.sort(rng.integers(t0, t1, n))
    edge = 20 + (t - t0) * (300 / max(1, t1 - t0))
    x = np.clip(np.round(edge + rng.normal(0, 2.0, n)), 0, W - 1).astype(np.int64)
    y = rng.integers(0, H, n)
    red = (x % 2 == 0) & (y % 2 == 0)
    p = red.astype(np.uint8)
    noise = rng.random(n) < 0.1
    x[noise], y[noise], p[noise] = (
        rng.integers(0, W, noise.sum()),
        rng.integers(0, H, noise.sum()),
        rng.integers(0, 2, noise.sum()),
    )
    return Events(x, y, t, p, W, H, "RGBG")


def scene_frames(rng, times: list[int], exposure: int) -> Frames:
    """A smooth color-checker-like mosaic with noise, one frame per time."""
    yy, xx = np.mgrid[0:H, 0:W]
    base = 300 + 200 * np.sin(xx / 23.0) * np.cos(yy / 17.0) + 150 * ((xx // 40 + yy // 40) % 2)
    data = [
        np.clip(base + rng.normal(0, 8, (H, W)) + 40 * k, 0, 1023).astype(np.uint16)
        for k in range(len(times))
    ]
    data[0][:4, :4] = 1023  # saturated pixels (encoded with the signal = 0 rule)
    return Frames(np.stack(data), times, [exposure] * len(times))


def imu_raw_samples(rng, t0: int, t1: int, period: int = 1000) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(t0, t1, period, dtype=np.int64)
    n = t.size
    raw = np.zeros((n, 7), np.int16)
    raw[:, 0:3] = (np.array([0.02, -0.99, 0.1]) * 8192 + rng.normal(0, 40, (n, 3))).astype(np.int16)
    raw[:, 3] = (-2000 + rng.normal(0, 5, n)).astype(np.int16)
    raw[:, 4:7] = (rng.normal(0, 300, (n, 3))).astype(np.int16)
    return t, raw


def color_scene(rng, t_end: int = 3_000_000) -> tuple[StreamEncoder, bytes, Content]:
    """3 s across 91 timestamp wraps, with a timestamp reset at 1.5 s."""
    roi = (140, 100, 203, 147)  # a 64 x 48 APS region of interest
    reset_t = 1_500_000
    enc = StreamEncoder(Geometry(color_filter="RGBG"))
    content = Content()
    events = moving_edge_events(rng, 0, t_end, 20_000)
    frames = scene_frames(rng, list(range(50_000, t_end, 200_000)), 2_000)
    imu = imu_raw_samples(rng, 500, t_end)
    trig = Triggers(
        [100_000, 100_500, reset_t, 2_200_000],
        [
            TriggerKind.EXTERNAL_SIGNAL_RISING_EDGE,
            TriggerKind.EXTERNAL_SIGNAL_FALLING_EDGE,
            TriggerKind.TIMESTAMP_RESET,
            TriggerKind.EXTERNAL_SIGNAL_PULSE,
        ],
    )
    bulk = enc.encode(events, frames, None, trig, roi=roi, imu_raw=imu)
    content.add(events, frames, imu, trig, roi)
    return enc, bulk, content


def real_sample() -> tuple[bytes, Content]:
    """The real DAVIS346 recording in ../shared: every event, IMU sample and trigger-producing
    frame signal; 1 of its 59 frames (to keep the fixture small)."""
    import aedat

    ev, frames, imus = [], [], []
    for packet in aedat.Decoder(str(SAMPLE)):
        if "events" in packet:
            ev.append(packet["events"])
        elif "frame" in packet:
            frames.append(packet["frame"])
        elif "imus" in packet:
            imus.append(packet["imus"])
    ev, imu = np.concatenate(ev), np.concatenate(imus)
    keep = [frames[29]]
    t0 = min(int(ev["t"][0]), int(imu["t"][0]), int(frames[0]["exposure_begin_t"]))
    events = Events(ev["x"], ev["y"], ev["t"].astype(np.int64) - t0, ev["p"].view(np.uint8), W, H)
    fr = Frames(
        np.stack([f["pixels"].astype(np.uint16) << 2 for f in keep]),
        [int(f["exposure_begin_t"]) - t0 for f in keep],
        [int(f["exposure_end_t"]) - int(f["exposure_begin_t"]) for f in keep],
    )
    # DV wrote g, deg/s and degC computed from the registers (+-4 g, +-500 deg/s, MPU-6050):
    # recover the register values.
    raw = np.column_stack(
        [imu[f"accelerometer_{a}"] * 8192.0 for a in "xyz"]
        + [(imu["temperature"] - 35.0) * 340.0]
        + [imu[f"gyroscope_{a}"] * 65.536 for a in "xyz"]
    )
    motion = raw[:, [0, 1, 2, 4, 5, 6]]
    assert np.abs(motion - np.round(motion)).max() < 0.01, "not +-4 g / +-500 deg/s data"
    imu_raw = (imu["t"].astype(np.int64) - t0, np.round(raw).astype(np.int16))
    enc = StreamEncoder()
    bulk = enc.encode(events, fr, None, None, imu_raw=imu_raw)
    content = Content()
    content.add(events, fr, imu_raw)
    return bulk, content


def corrupted(rng) -> tuple[bytes, Content, dict]:
    """A short color stream with malformed words between its pieces; each is skipped, and
    counted in the named decoder counter."""
    enc = StreamEncoder(Geometry(color_filter="RGBG"))
    content = Content()
    pieces = []
    t = 0
    bad_words = [
        ([0x0006, 0x0012, 0x001F, 0x0000], "unknown_words", 4),  # unknown and reserved specials
        (
            [0x5400, 0x5F12, 0x6400, 0x6C00],
            "unknown_words",
            4,
        ),  # misc8 subs 4, 15; misc10 subs 1, 3
        ([0x1000 | 300, 0x2000 | 400, 0x3000 | 346], "dvs_out_of_range", 3),  # bad row, columns
        ([0x4123, 0x4001], "aps_samples_skipped", 2),  # ADC samples outside any frame
        ([0x5012, 0x5385, 0x0007], "imu_bad", 3),  # IMU byte, config, end outside a sample
    ]
    counters = {
        "unknown_words": 0,
        "dvs_out_of_range": 0,
        "aps_samples_skipped": 0,
        "imu_bad": 0,
        "frames_bad": 0,
        "time_went_backwards": 0,
    }
    for k in range(5):
        ev = moving_edge_events(rng, t, t + 40_000, 50_000)
        fr = scene_frames(rng, [t + 10_000], 1_000)
        imu = imu_raw_samples(rng, t + 500, t + 40_000, 4000)
        roi = (10, 10, 41, 33)
        pieces.append(enc.encode(ev, fr, None, None, roi=roi, imu_raw=imu))
        content.add(ev, fr, imu, None, roi)
        words, name, count = bad_words[k]
        # A backwards timestamp right before the true one: counted, and no event sees it.
        now = int(ev.t[-1])
        words = words + [0x8000 | 0, 0x8000 | (now % 0x8000)]
        counters[name] += count
        counters["time_went_backwards"] += 1 if now % 0x8000 else 0
        pieces.append(np.asarray(words, "<u2").tobytes())
        t += 40_000
    # A frame whose readout breaks off (columns missing) and an IMU sample cut short:
    # both dropped, and their APS triggers still appear.
    assert (t + 100) // 0x8000 == now // 0x8000  # the device clock is still in this wrap
    words = [0x8000 | ((t + 100) % 0x8000), 0x0008]
    for value in (0, 0, 1, 1):  # ROI (0, 0) .. (1, 1): 2 x 2 pixels; high byte, low byte
        words += [0x5100, 0x5200 | value]
    words += [0x000E, 0x000B, 0x4200, 0x4200, 0x000D, 0x000F, 0x000A]  # one of two columns
    words += [0x0005, 0x53E5, 0x5001, 0x5002, 0x0007]  # IMU: config and 2 of 14 bytes
    content.triggers += [
        (t + 100, TriggerKind.APS_FRAME_START),
        (t + 100, TriggerKind.APS_EXPOSURE_START),
        (t + 100, TriggerKind.APS_EXPOSURE_END),
        (t + 100, TriggerKind.APS_FRAME_END),
    ]
    counters["frames_bad"] += 1
    counters["imu_bad"] += 1
    pieces.append(np.asarray(words, "<u2").tobytes())
    return b"".join(pieces), content, counters


def random_transfers(rng, total: int, low: int = 1, high: int = 16384) -> np.ndarray:
    sizes = []
    while sum(sizes) < total:
        sizes.append(int(rng.integers(low, high)))
    return np.asarray(sizes, np.uint32)


# -- all fixtures ------------------------------------------------------------------------------


def generate(out: Path) -> list[str]:
    made = []
    rng = np.random.default_rng(346)
    _, bulk, content = color_scene(rng)
    write_fixture(
        out / "color-scene",
        serial="00000042",
        color_filter=1,
        bulk=bulk,
        content=content,
        transfers=random_transfers(rng, len(bulk)),
        description="Color-DAVIS346: a moving colored edge, 64x48 ROI frames, IMU at "
        "1 kHz, external triggers, a timestamp reset; 3 s across 91 wraps; transfers "
        "of random sizes (odd ones too)",
    )
    made.append("color-scene")

    rng = np.random.default_rng(7)
    enc = StreamEncoder(Geometry(color_filter="RGBG"))
    content = Content()
    ev_a = moving_edge_events(rng, 0, 300_000, 30_000)
    imu_a = imu_raw_samples(rng, 500, 300_000, 2000)
    part_a = enc.encode(ev_a, None, None, None, imu_raw=imu_a)
    content.add(ev_a, None, imu_a)
    ev_b = moving_edge_events(rng, 300_000, 500_000, 30_000)
    part_b = enc.encode(ev_b)
    write_fixture(
        out / "disconnect",
        serial="00000043",
        color_filter=1,
        bulk=part_a + part_b,
        content=content,
        faults=[{"at_byte": len(part_a), "kind": "disconnect"}],
        description="Color-DAVIS346 unplugged after 0.3 s: everything before the "
        "fault is expected, nothing after",
    )
    made.append("disconnect")

    rng = np.random.default_rng(8)
    enc = StreamEncoder(Geometry(color_filter="RGBG"))
    ev = moving_edge_events(rng, 0, 400_000, 40_000)
    fr = scene_frames(rng, [100_000, 300_000], 1_000)
    imu = imu_raw_samples(rng, 500, 400_000, 2000)
    roi = (0, 0, 31, 23)
    bulk = enc.encode(ev, fr, None, None, roi=roi, imu_raw=imu)
    content = Content()
    content.add(ev, fr, imu, None, roi)
    n = len(bulk)
    write_fixture(
        out / "timeouts-stall",
        serial="00000044",
        color_filter=1,
        bulk=bulk,
        content=content,
        faults=[
            {"at_byte": n // 5, "kind": "timeout", "count": 3},
            {"at_byte": n // 2, "kind": "stall"},
            {"at_byte": 3 * n // 4, "kind": "timeout", "count": 2},
        ],
        description="Color-DAVIS346 with read timeouts and an endpoint stall: all "
        "recovered, nothing lost",
    )
    made.append("timeouts-stall")

    rng = np.random.default_rng(9)
    bulk, content, counters = corrupted(rng)
    write_fixture(
        out / "corrupted",
        serial="00000045",
        color_filter=1,
        bulk=bulk,
        content=content,
        transfers=random_transfers(rng, len(bulk), 100, 3000),
        counters=counters,
        description="Color-DAVIS346 stream with malformed words: unknown specials and "
        "misc codes, out-of-range addresses, stray APS and IMU words, a broken frame, "
        "a cut IMU sample, a backwards timestamp; all skipped and counted",
    )
    made.append("corrupted")

    if SAMPLE.exists():
        bulk, content = real_sample()
        write_fixture(
            out / "davis346-sample",
            serial="00000002",
            color_filter=0,
            bulk=bulk,
            content=content,
            description="the real DAVIS346 recording of "
            "../shared/data/davis346-sample re-encoded: all 78,830 events and 2,363 "
            "IMU samples, 1 of its 59 frames",
        )
        made.append("davis346-sample")
    return made


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def generate_demo(out: Path, keep: Path | None = None, names: list[str] | None = None) -> list[str]:
    """Simulate the demo's scenes (``names``: those of DEMO, else all) and write their
    fixtures (and demo-scene's truth.h5); ``keep``: a folder to keep the simulated sessions in."""
    from evcap.sim.fixture import write_session_fixture
    from evcap.sim.scene import load_scene
    from evcap.sim.simulate import simulate
    from evcap.sim.truth import write_truth

    made = []
    with tempfile.TemporaryDirectory() as tmp:
        where = keep or Path(tmp)
        where.mkdir(parents=True, exist_ok=True)
        for name, (scene_file, description) in DEMO.items():
            if names and name not in names:
                continue
            scene_path = SCENES / scene_file
            session = where / f"{name}.h5"
            start = time.perf_counter()
            stats = simulate(load_scene(scene_path), session, overwrite=True)
            seconds = time.perf_counter() - start
            folder = out / name
            if folder.exists():
                shutil.rmtree(folder)
            write_session_fixture(
                session,
                folder,
                serial=DEMO_SERIAL,
                description=description,
                compact=True,
                about={
                    "scene": f"sim/scenes/{scene_file}",
                    "scene_sha256": _sha256(scene_path),
                },
            )
            if name == "demo-scene":
                write_truth(session, folder / "truth.h5")
            sizes = ", ".join(f"{f.name} {f.stat().st_size:,} B" for f in sorted(folder.iterdir()))
            print(
                f"{name}: {stats.events:,} events, {stats.frames} frames, {stats.imu:,} IMU "
                f"samples, simulated in {seconds:.0f} s; {sizes}"
            )
            made.append(name)
    return made


def check_demo(folder: Path) -> list[str]:
    """What differs between the committed demo fixtures and their expected content, as the
    driver records them; and whether their scene files changed since they were made."""
    from evcap.sim.fixture import check_fixture
    from evcap.sim.truth import read_truth

    problems = []
    for name, (scene_file, _) in DEMO.items():
        fixture = folder / name
        if not (fixture / "expected.json").exists():
            problems.append(f"{fixture} is missing: make it with generate.py --demo")
            continue
        summary = json.loads((fixture / "expected.json").read_text())
        if summary.get("serial") != DEMO_SERIAL:
            problems.append(f"{fixture}: serial {summary.get('serial')!r}, not {DEMO_SERIAL!r}")
        if summary.get("scene_sha256") != _sha256(SCENES / scene_file):
            problems.append(
                f"{fixture} was not made from the current sim/scenes/{scene_file}: "
                "remake it with generate.py --demo"
            )
        problems += check_fixture(fixture)
    truth = folder / "demo-scene" / "truth.h5"
    if (folder / "demo-scene").exists():
        try:
            held = read_truth(truth)[0].held_out_views()
            if not len(held) or held.radiance.shape[1:3] != (H, W):
                problems.append(f"{truth}: no held-out views of a {W} x {H} camera")
        except Exception as e:
            problems.append(f"{truth}: {e}")
    return problems


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--check",
        action="store_true",
        help="regenerate into a temporary folder and compare with this one; record the demo's "
        "fixtures through the driver and compare with their expected content",
    )
    parser.add_argument(
        "--demo",
        nargs="*",
        choices=list(DEMO),
        metavar="NAME",
        help="simulate and write the demo's fixtures (demo-scene, demo-calibration; or those "
        "named): minutes",
    )
    parser.add_argument(
        "--keep-sessions",
        metavar="DIR",
        type=Path,
        help="--demo: keep the simulated sessions (with their ground truth) in DIR",
    )
    args = parser.parse_args()
    if args.demo is not None:
        for name in generate_demo(DEMO_DATA, args.keep_sessions, args.demo):
            print(f"wrote {DEMO_DATA / name}")
        return 0
    if not args.check:
        for name in generate(HERE):
            print(f"wrote {HERE / name}")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        differ = []
        for name in generate(Path(tmp)):
            for f in sorted((Path(tmp) / name).iterdir()):
                mine = HERE / name / f.name
                if f.name != "expected.npz" and (
                    not mine.exists() or mine.read_bytes() != f.read_bytes()
                ):
                    differ.append(str(mine))
                elif f.name == "expected.npz":
                    a, b = np.load(f), np.load(mine)
                    if set(a) != set(b) or any(not np.array_equal(a[k], b[k]) for k in a):
                        differ.append(str(mine))
        for path in differ:
            print(f"differs from the generator: {path}")
    demo = check_demo(DEMO_DATA)
    for line in demo:
        print(line)
    return 1 if differ or demo else 0


if __name__ == "__main__":
    sys.exit(main())
