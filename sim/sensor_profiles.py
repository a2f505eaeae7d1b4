"""Named sensors: contrast thresholds and effects at the levels a real camera shows, each number
with where it comes from. A scene takes one with ``[sensor] profile = "davis346"`` (its own keys
and effects still win), `evcap simulate` with ``--sensor davis346``.

"davis346", a DAVIS346 in good light (sim/scenes/README.md gives the table):
- thresholds: the datasheet's contrast sensitivity at 50 % of pixels responding, 14.3 % (ON) and
  22.5 % (OFF) Weber, ln(1.143) and ln(1.225) in log units (iniVation's DAVIS346 specification,
  quoted in the EvaGaussians appendix). `evcap calibrate` on the bundled real recording fits
  0.24 / 0.27 on the 0.1 % of pixels its frames allow (biases unknown): no contradiction, no
  better figure;
- threshold spread: sigma 0.03 (v2e's default for DAVIS cameras; ESIM's 0.021);
- background activity: 0.1 Hz a pixel, "about one event per 10 s in good light" (iniVation's
  biasing guide); the bundled real recording measures 0.002 Hz, so the guide's is the pessimistic
  end;
- shot noise: 0.001 Hz (v2e's default for good light); the real recording measures none;
- refractory period: 0.5 ms (v2e's default); the real recording bounds it by 1.57 ms (its scene
  never drives a pixel harder);
- bandwidth: a 300 Hz first-order cutoff (v2e's default, good light; the datasheet's latency,
  under 1 ms, asks at least 160 Hz);
- footprint: sigma 0.28 px, what one pixel sees of the image (its photodiode's area and the
  lens's blur), measured by evcap.calib.footprint on the bundled real recording's APS frames
  (the median of its 59 frames from a still camera; the sharpest tenth of its 75 straight
  edges, the median edge 0.41 px: a scene's edges are not all steps). A DAVIS pixel's APS and
  DVS share the photodiode. Without it a simulated pixel is a point, and an edge crossing it
  makes all its events at once, most of which the refractory period then drops.
Left out, with the reason: hot pixels (the real recording has none, and no figure is published;
bench/robustness.py adds them as a stress), timestamp jitter (1 µs timestamps, no published
jitter), dropped events (the DAVIS346 drops only past its 12 MEv/s bus; the bundled scenes stay
under it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from evcap.errors import InputError


@dataclass(frozen=True)
class SensorProfile:
    name: str
    threshold_on: float
    threshold_off: float
    effects: dict = field(default_factory=dict)  # as [sensor.effects] (sim/scene.py EFFECTS)


PROFILES = {
    "ideal": SensorProfile("ideal", 0.2, 0.2),
    "davis346": SensorProfile(
        "davis346",
        threshold_on=math.log(1.143),
        threshold_off=math.log(1.225),
        effects={
            "threshold_spread": {"sigma": 0.03},
            "background_activity": {"rate_hz": 0.1},
            "shot_noise": {"rate_hz": 0.001},
            "refractory": {"period_us": 500},
            "bandwidth": {"cutoff_hz": 300.0},
            "footprint": {"sigma_px": 0.28},
        },
    ),
}


def sensor_profile(name: str | SensorProfile) -> SensorProfile:
    """The profile so named (a profile as it is); InputError listing the known ones."""
    if isinstance(name, SensorProfile):
        return name
    try:
        return PROFILES[name]
    except KeyError:
        raise InputError(f"unknown sensor profile {name!r}; known: {', '.join(PROFILES)}") from None
