"""The commands of the capture floor: import, info, devices, record, monitor."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from evcap.app.command import Command
from evcap.errors import InputError, OutputExistsError

DEVICE_HELP = "usb (the first camera), usb:SERIAL, or replay:PATH (a hardware-replay fixture)"


def _import_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "file", help="the recording: a file, or a ROS 2 bag's or a text sequence's folder"
    )
    p.add_argument("-o", "--output", required=True, help="the session file to write (.h5)")
    p.add_argument(
        "--color-filter",
        choices=["MONO", "RGBG", "GRGB", "GBGR", "BGRG"],
        default=None,
        help="the sensor's color filter where the recording does not state it (default MONO)",
    )
    p.add_argument("--topic", help="a bag's event topic (default: the first with events)")
    p.add_argument(
        "--chip",
        help="an AEDAT 2.0 file's jAER chip class (DVS128, DAVIS240C, Davis346B, ...), used "
        "instead of the one the file names (default: the file's, else inferred from the "
        "address range)",
    )
    p.add_argument(
        "--width", type=int, help="an event text file's sensor width (default: inferred)"
    )
    p.add_argument("--height", type=int, help="an event text file's sensor height")
    p.add_argument("-f", "--force", action="store_true", help="overwrite the output file")


def _import(args: argparse.Namespace) -> int:
    from evcap._progress import progress_bar
    from evcap.importers.detect import import_recording

    with progress_bar(f"importing {args.file}") as update:
        summary = import_recording(
            args.file,
            args.output,
            topic=args.topic,
            chip=args.chip,
            color_filter=args.color_filter,
            width=args.width,
            height=args.height,
            overwrite=args.force,
            progress=update,
        )
    print(
        f"{args.output}: {summary.events:,} events, {summary.frames:,} frames, "
        f"{summary.imu:,} IMU samples, {summary.triggers:,} triggers ({summary.source})"
    )
    for note in summary.notes:
        print(note)
    for warning in summary.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    return 0


IMPORT = Command(
    "import",
    help="convert a recording (AEDAT, ROS bag, text) into a session",
    description="Convert a recording into a session; the container is told by the content: "
    "AEDAT 4 (DV), AEDAT 3.1 (cAER, libcaer), AEDAT 2.0 (jAER: DVS128, DAVIS240, DAVIS346; "
    "a file that names no chip: --chip, else the chip is inferred from the address range), "
    "ROS 1 and ROS 2 bags (dvs_msgs/EventArray, event_camera_msgs/EventPacket, with the "
    "camera's images and IMU), event text files (t x y p; the Event-Camera Dataset's "
    "folder, with calib.txt, groundtruth.txt, images.txt, imu.txt).",
    arguments=_import_arguments,
    run=_import,
)


def _info_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("session", help="the session file (.h5)")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")


def _info(args: argparse.Namespace) -> int:
    from evcap._progress import progress_bar
    from evcap.session import Session
    from evcap.summary import format_summary, summarize

    with progress_bar(f"checking {args.session}") as update:
        session = Session.open(args.session, progress=update)
    with session, progress_bar(f"reading {args.session}") as update:
        summary = summarize(session, update)
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    return 0


INFO = Command(
    "info",
    help="check a session; show its sensor, duration and counts",
    description="Check a session file and describe it.",
    arguments=_info_arguments,
    run=_info,
)


def _devices_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="usb", help=DEVICE_HELP)
    p.add_argument(
        "--udev",
        action="store_true",
        help="print the udev rule that lets users open the camera (Linux)",
    )


def _devices(args: argparse.Namespace) -> int:
    from evcap.acquire.device import UDEV_RULE, Davis346, DeviceSpec, find
    from evcap.errors import DeviceError

    if args.udev:
        print(UDEV_RULE, end="")
        return 0
    spec = DeviceSpec.parse(args.device)
    backend = spec.backend()
    devices = find(spec, backend)
    if not devices:
        print(
            "No DAVIS346 found. Check the cable (use a USB 3 port) and that the camera's LED is "
            "on.\nOn Linux the camera needs a udev rule: evcap devices --udev | sudo tee "
            "/etc/udev/rules.d/65-inivation.rules, then replug it.",
            file=sys.stderr,
        )
        return 1
    status = 0
    for usb_dev in devices:
        try:
            with Davis346(usb_dev, spec) as cam:
                i = cam.info
                print(
                    f"{i.model}  serial {i.serial or '?'}  firmware {i.firmware}  "
                    f"logic {i.logic}.{i.logic_patch}  chip {i.chip}  "
                    f"color filter {i.color_filter}  IMU {i.geometry.imu_type}  "
                    f"bus {usb_dev.bus} address {usb_dev.address}"
                )
        except DeviceError as e:
            print(f"DAVIS346 at bus {usb_dev.bus} address {usb_dev.address}: {e}", file=sys.stderr)
            status = 1
    return status


DEVICES = Command(
    "devices",
    help="list the connected cameras: serial, firmware, color filter",
    description="List the connected DAVIS346 cameras.",
    arguments=_devices_arguments,
    run=_devices,
)


def _capture_arguments(p: argparse.ArgumentParser) -> None:
    """The options of a running camera, shared by record and monitor."""
    p.add_argument("--device", default="usb", help=DEVICE_HELP)
    p.add_argument("--biases", metavar="FILE", help="biases and settings (TOML) over the defaults")
    p.add_argument("--no-aps", action="store_true", help="without APS frames")
    p.add_argument("--no-imu", action="store_true", help="without IMU samples")


def _record_options(args: argparse.Namespace):
    from evcap.acquire.bias_file import load_bias_file
    from evcap.acquire.recorder import RecordOptions

    options = RecordOptions(
        duration_s=getattr(args, "duration", None),
        aps=not args.no_aps,
        imu=not args.no_imu,
        overwrite=getattr(args, "force", False),
    )
    if args.biases:
        options.biases, options.settings = load_bias_file(args.biases)
    return options


def _run_app(app, recorder) -> None:
    """Run the monitor app; SIGTERM stops it as q does. A capture error is raised after."""
    import signal

    signal.signal(signal.SIGTERM, lambda signum, frame: recorder.stop())
    app.run()
    if app.capture_error is not None:
        raise app.capture_error


def _status_line(recorder, watch):
    """An on_batch callback that redraws one status line on stderr, twice a second."""
    import time

    started, last = time.monotonic(), [0.0]

    def show(batch) -> None:
        now = time.monotonic()
        if now - last[0] < 0.5:
            return
        last[0] = now
        if recorder.recording is None:
            return
        r = recorder.recording.result
        size = r.path.stat().st_size / 1e6 if r.path.exists() else 0.0
        print(
            f"\r{now - started:7.1f} s  {r.events:>13,} events  {r.frames:>6,} frames  "
            f"{r.imu:>8,} IMU  {size:8.1f} MB  backlog {watch.backlog.total_bytes / 1e6:5.1f} MB",
            end="",
            file=sys.stderr,
            flush=True,
        )

    return show


def _behind_warnings(watch, tty: bool):
    """An on_event callback that says on stderr, while it happens, when the host falls behind,
    catches up, or the camera drops events (evcap.acquire.backlog)."""
    from evcap.acquire.recorder import Stats

    def on_event(event) -> None:
        if not isinstance(event, Stats):
            return
        for severity, text in watch.update(event.backlog, event.dropped):
            line = f"warning: {text}" if severity == "warning" else text
            # on a terminal, over the status line (redrawn after)
            print(f"\r\x1b[K{line}" if tty else line, file=sys.stderr, flush=True)

    return on_event


def _record_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", required=True, help="the session file to write (.h5)")
    _capture_arguments(p)
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    p.add_argument(
        "--no-tui",
        action="store_true",
        help="no live view (there is none either when output is not a terminal)",
    )
    p.add_argument("-f", "--force", action="store_true", help="overwrite the output file")


def _record(args: argparse.Namespace) -> int:
    import signal

    from evcap.acquire.backlog import BehindWatch
    from evcap.acquire.device import Davis346
    from evcap.acquire.recorder import Recorder

    options = _record_options(args)
    if Path(args.output).exists() and not args.force:
        raise OutputExistsError(f"{args.output} exists; choose another name or pass --force")
    live_view = not args.no_tui and sys.stdout.isatty() and sys.stdin.isatty()
    with Davis346.open(args.device) as camera:
        recorder = Recorder(camera, args.output, options)
        if live_view:
            from evcap.tui import make_app

            app = make_app(recorder, record_mode=True, output_dir=Path(args.output).parent)
            _run_app(app, recorder)
            r = recorder.result
        else:

            def stop(signum, frame):
                if recorder.stop_requested.is_set():  # a second Ctrl-C: stop now
                    raise KeyboardInterrupt
                recorder.stop()

            signal.signal(signal.SIGINT, stop)
            signal.signal(signal.SIGTERM, stop)
            print(
                f"recording {camera.info.model} {camera.info.serial} into {args.output} "
                "(Ctrl-C stops)",
                file=sys.stderr,
            )
            watch = BehindWatch()
            recorder.on_event = _behind_warnings(watch, sys.stderr.isatty())
            if sys.stderr.isatty():
                recorder.on_batch = _status_line(recorder, watch)
            r = recorder.run()
            if sys.stderr.isatty():
                print(file=sys.stderr)  # end the status line
    dropped = sum(r.device_dropped.values())
    print(
        f"{args.output}: {r.events:,} events, {r.frames:,} frames, {r.imu:,} IMU samples, "
        f"{r.triggers:,} triggers ({r.end_reason}; dropped on the device: {dropped:,})"
    )
    if r.behind_seconds:
        print(
            f"warning: the host fell behind the camera while recording (at {r.behind_seconds} "
            f"of the once-a-second checks; the largest backlog {r.largest_backlog_bytes / 1e6:.1f}"
            " MB); fewer programs running beside it, or a faster disk, help",
            file=sys.stderr,
        )
    c = r.decoder or {}
    bad = sum(c.get(k, 0) for k in ("unknown_words", "time_went_backwards", "timestamp_jumps"))
    if bad > 0.001 * c.get("words", 0):
        print(
            f"warning: {bad:,} of {c['words']:,} words from the camera were malformed (unknown "
            "codes, time going back or jumping ahead): check the USB cable and port; they were "
            "skipped, and are counted in the session's decoder_counters",
            file=sys.stderr,
        )
    return 0


RECORD = Command(
    "record",
    help="record a camera into a session file",
    description="Record a DAVIS346 into a session file until q or Ctrl-C, the duration, or the "
    "end of a replay fixture.",
    arguments=_record_arguments,
    run=_record,
)


def _monitor_arguments(p: argparse.ArgumentParser) -> None:
    _capture_arguments(p)
    p.add_argument("--output-dir", default=".", help="where recordings go (default: here)")
    p.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="replay devices: play at this multiple of real time (default 1)",
    )


def _monitor(args: argparse.Namespace) -> int:
    from evcap.acquire.device import Davis346, DeviceSpec
    from evcap.acquire.recorder import Recorder
    from evcap.tui import make_app

    options = _record_options(args)
    output_dir = Path(args.output_dir)
    if not output_dir.is_dir():
        raise InputError(f"{output_dir} is not a folder")
    spec = DeviceSpec.parse(args.device, speed=args.speed)
    with Davis346.open(spec) as camera:
        recorder = Recorder(camera, None, options)
        app = make_app(recorder, output_dir=output_dir)
        _run_app(app, recorder)
    if recorder.result is not None:
        r = recorder.result
        print(f"last recording: {r.path}: {r.events:,} events ({r.end_reason})")
    return 0


MONITOR = Command(
    "monitor",
    help="watch a camera live in the terminal; r records",
    description="Watch a camera live: event rates, events, frames, IMU, biases (editable); "
    "r starts and stops a recording into a new session file.",
    arguments=_monitor_arguments,
    run=_monitor,
)

# in the order `evcap --help` lists them
COMMANDS = (IMPORT, INFO, DEVICES, RECORD, MONITOR)
