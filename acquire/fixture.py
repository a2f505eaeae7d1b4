"""Hardware-replay fixtures: the folder format of hw-fixtures/README.md, written with the
content a correct driver must give back (expected.npz, expected.json).

The expected content is computed from the streams that were encoded (IMU values from their
register values, by the documented scaling), never by decoding.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from evcap.acquire.decoder import imu_signs
from evcap.acquire.encoder import DEFAULT_IMU_CONFIG
from evcap.events import Events
from evcap.streams import TriggerKind

STANDARD_GRAVITY = 9.80665


class FixtureContent:
    """What a stream carries, in the decoder's terms (host-continuous times)."""

    def __init__(self, width: int = 346, height: int = 260) -> None:
        self.width, self.height = width, height
        self.events: list[Events] = []
        self.frames: list[tuple[np.ndarray, int, int]] = []  # (full frame, t, exposure)
        self.imu: list[tuple[int, np.ndarray]] = []  # (t, raw int16 x 7)
        self.triggers: list[tuple[int, int]] = []  # (t, kind)

    def add(self, events=None, frames=None, imu_raw=None, triggers=None, roi=None) -> None:
        if events is not None:
            self.events.append(events)
        if frames is not None:
            sx, sy, ex, ey = roi or (0, 0, self.width - 1, self.height - 1)
            for i in range(len(frames)):
                full = np.zeros((self.height, self.width), np.uint16)
                full[sy : ey + 1, sx : ex + 1] = frames.data[i][sy : ey + 1, sx : ex + 1]
                t, exp = int(frames.t[i]), int(frames.exposure_us[i])
                self.frames.append((full, t, exp))
                self.triggers += [
                    (t, TriggerKind.APS_FRAME_START),
                    (t, TriggerKind.APS_EXPOSURE_START),
                    (t + exp, TriggerKind.APS_EXPOSURE_END),
                    (t + exp, TriggerKind.APS_FRAME_END),
                ]
        if imu_raw is not None:
            self.imu += list(zip(imu_raw[0].tolist(), imu_raw[1], strict=True))
        if triggers is not None:
            self.triggers += list(zip(triggers.t.tolist(), triggers.kind.tolist(), strict=True))

    def arrays(
        self,
        imu_type: int = 1,
        imu_config: int = DEFAULT_IMU_CONFIG,
        imu_flip: tuple[bool, bool, bool] = (False, False, False),
    ) -> dict:
        ev = {
            k: np.concatenate([getattr(e, k) for e in self.events]) if self.events else np.zeros(0)
            for k in "xytp"
        }
        raw = np.array([r for _, r in self.imu], np.float64).reshape(-1, 7)
        accel_lsb = 4.0 * 2.0 ** ((imu_config >> 2) & 3) / 65536.0 * STANDARD_GRAVITY
        gyro_lsb = np.deg2rad(500.0 * 2.0 ** (imu_config & 3) / 65536.0)
        temp = raw[:, 3] / 340.0 + 35.0 if imu_type == 1 else raw[:, 3] / 333.87 + 21.0
        sign = imu_signs(imu_flip)  # the registers' axes into the camera's, as a decoder turns them
        trig = sorted(self.triggers)
        return {
            "events_x": ev["x"].astype(np.uint16),
            "events_y": ev["y"].astype(np.uint16),
            "events_t": ev["t"].astype(np.int64),
            "events_p": ev["p"].astype(np.uint8),
            "frames_data": (
                np.stack([f for f, _, _ in self.frames])
                if self.frames
                else np.zeros((0, self.height, self.width), np.uint16)
            ),
            "frames_t": np.array([t for _, t, _ in self.frames], np.int64),
            "frames_exposure_us": np.array([e for _, _, e in self.frames], np.int64),
            "imu_t": np.array([t for t, _ in self.imu], np.int64),
            "imu_accel": (raw[:, 0:3] * accel_lsb * sign).astype(np.float32),
            "imu_gyro": (raw[:, 4:7] * gyro_lsb * sign).astype(np.float32),
            "imu_temperature": temp.astype(np.float32),
            "triggers_t": np.array([t for t, _ in trig], np.int64),
            "triggers_kind": np.array([k for _, k in trig], np.uint8),
        }


def write_fixture(
    folder: Path,
    *,
    serial: str,
    color_filter: int,
    bulk: bytes,
    content: FixtureContent,
    transfers: np.ndarray | None = None,
    faults: list[dict] | None = None,
    registers: dict | None = None,
    counters: dict | None = None,
    description: str,
) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    regs = {"2.3": color_filter, **(registers or {})}
    lines = [
        f"# {description}",
        "[usb]",
        "idVendor = 0x152A",
        "idProduct = 0x841A",
        "bcdDevice = 0x0006",
        f'serial = "{serial}"',
        'product = "DAVIS FX3"',
        "",
        "[registers]",
    ]
    lines += [f'"{k}" = {v}' for k, v in regs.items()]
    (folder / "device.toml").write_text("\n".join(lines) + "\n")
    (folder / "bulk.bin").write_bytes(bulk)
    if transfers is not None:
        transfers.astype("<u4").tofile(folder / "transfers.u32")
    if faults:
        text = "".join(
            "[[fault]]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in f.items()) + "\n"
            for f in faults
        )
        (folder / "faults.toml").write_text(text)
    arrays = content.arrays(imu_flip=imu_flip(regs))
    with open(folder / "expected.npz", "wb") as f:
        np.savez_compressed(f, **arrays)
    summary = {
        "description": description,
        "serial": serial,
        "color_filter": {0: "MONO", 1: "RGBG", 2: "GRGB", 3: "GBGR", 4: "BGRG"}[color_filter],
        "events": int(arrays["events_t"].size),
        "frames": int(arrays["frames_t"].size),
        "imu_samples": int(arrays["imu_t"].size),
        "triggers": int(arrays["triggers_t"].size),
        "counters": counters or {},
    }
    (folder / "expected.json").write_text(json.dumps(summary, indent=2) + "\n")


def imu_flip(registers: dict) -> tuple[bool, bool, bool]:
    """The IMU orientation flips a fixture's registers give (IMU module 3, parameter 1: bit 2
    flips x, bit 1 y, bit 0 z), as the driver reads them."""
    code = int(registers.get("3.1", 0))
    return bool(code & 4), bool(code & 2), bool(code & 1)
