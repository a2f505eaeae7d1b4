"""What `evcap info` says about a session."""

from __future__ import annotations

from collections.abc import Callable

from evcap.session import Session


def summarize(session: Session, progress: Callable[[int, int], None] | None = None) -> dict:
    """Sensor, duration, stream counts, event rate and ON fraction of an open session."""
    on = 0
    for done, block in enumerate(session.iter_events(), start=1):
        on += int(block.p.sum())
        if progress:
            progress(min(done * len(block), session.n_events), session.n_events)
    span = session.time_range()
    duration_s = (span[1] - span[0]) / 1e6 if span else 0.0
    a = session.attrs
    return {
        "path": str(session.path),
        "sensor": session.sensor.sensor,
        "serial": session.sensor.serial,
        "width": session.sensor.width,
        "height": session.sensor.height,
        "color_filter": session.sensor.color_filter,
        "schema_version": a["schema_version"],
        "created": a["created"],
        "complete": session.complete,
        "t_offset_us": session.sensor.t_offset_us,
        "t_first_us": span[0] if span else None,
        "t_last_us": span[1] if span else None,
        "duration_s": duration_s,
        "events": session.n_events,
        "frames": session.n_frames,
        "imu_samples": session.n_imu,
        "triggers": session.n_triggers,
        "mean_event_rate_hz": session.n_events / duration_s if duration_s > 0 else 0.0,
        "on_fraction": on / session.n_events if session.n_events else None,
        "groups": session.groups,
    }


def format_summary(s: dict) -> str:
    """The summary as aligned lines for a terminal."""
    on = "-" if s["on_fraction"] is None else f"{100 * s['on_fraction']:.1f} %"
    rows = [
        ("file", s["path"] + ("" if s["complete"] else "  (incomplete: the recording was cut)")),
        ("sensor", f"{s['sensor']} {s['serial']}".strip()),
        ("resolution", f"{s['width']} x {s['height']}, color filter {s['color_filter']}"),
        ("duration", f"{s['duration_s']:.3f} s"),
        ("events", f"{s['events']:,}"),
        ("frames", f"{s['frames']:,}"),
        ("IMU samples", f"{s['imu_samples']:,}"),
        ("triggers", f"{s['triggers']:,}"),
        ("event rate", f"{s['mean_event_rate_hz'] / 1e3:,.1f} kev/s (mean)"),
        ("ON fraction", on),
        ("groups", ", ".join(s["groups"])),
    ]
    return "\n".join(f"{k:<12} {v}" for k, v in rows)
