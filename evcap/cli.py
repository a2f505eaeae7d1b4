"""The `evcap` command: parses arguments and hands over to the step that does the work.

Kept thin and light: each subcommand imports what it needs when it runs, so that
`evcap --help` (and `evcap record`) never wait for torch or other heavy packages.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from evcap import __version__
from evcap.errors import EvcapError, InputError, OutputExistsError
from evcap.recon.config import (
    ABLATION_FLAGS,
    BACKENDS,
    DEVICES,
    EFFECT_MODES,
    PRESET_NAMES,
    REFINE_POSES,
    STAGES,
    ZERO_EVENTS,
)


def _cmd_import(args: argparse.Namespace) -> int:
    from evcap._progress import progress_bar
    from evcap.importers.detect import import_recording

    with progress_bar(f"importing {args.file}") as update:
        summary = import_recording(
            args.file,
            args.output,
            topic=args.topic,
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
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    from evcap._progress import progress_bar
    from evcap.session import Session
    from evcap.summary import format_summary, summarize

    with progress_bar(f"checking {args.session}") as update:
        session = Session.open(args.session, progress=update)
    with session, progress_bar(f"reading {args.session}") as update:
        summary = summarize(session, update)
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    return 0


def _cmd_devices(args: argparse.Namespace) -> int:
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


def _status_line(recorder):
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
            f"{r.imu:>8,} IMU  {size:8.1f} MB",
            end="",
            file=sys.stderr,
            flush=True,
        )

    return show


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


def _cmd_record(args: argparse.Namespace) -> int:
    import signal

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
            if sys.stderr.isatty():
                recorder.on_batch = _status_line(recorder)
            r = recorder.run()
            if sys.stderr.isatty():
                print(file=sys.stderr)  # end the status line
    dropped = sum(r.device_dropped.values())
    print(
        f"{args.output}: {r.events:,} events, {r.frames:,} frames, {r.imu:,} IMU samples, "
        f"{r.triggers:,} triggers ({r.end_reason}; dropped on the device: {dropped:,})"
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


def _cmd_monitor(args: argparse.Namespace) -> int:
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


DEVICE_HELP = "usb (the first camera), usb:SERIAL, or replay:PATH (a hardware-replay fixture)"


def _cmd_simulate(args: argparse.Namespace) -> int:
    from evcap._progress import progress_bar

    if (args.scene is None) == (args.from_images is None):
        raise InputError("give a scene file, or --from-images TRANSFORMS (not both)")
    if args.held_out and not args.from_images:
        raise InputError("--held-out goes with --from-images")
    if args.from_images:
        from evcap.sim.from_images import simulate_from_images

        with progress_bar("simulating") as update:
            n = simulate_from_images(
                args.from_images,
                args.output,
                held_out=args.held_out,
                background=args.background,
                fps=args.fps,
                color_filter=args.color_filter,
                threshold=args.threshold,
                scale=args.scale,
                seed=args.seed or 0,
                overwrite=args.force,
                progress=update,
            )
        print(f"{args.output}: {n:,} events from {args.from_images}")
        return 0
    from evcap.sim.scene import example_scene, load_scene
    from evcap.sim.simulate import simulate

    scene = load_scene(example_scene(args.scene))
    with progress_bar(f"simulating {scene.name}") as update:
        stats = simulate(
            scene,
            args.output,
            seed=args.seed,
            overwrite=args.force,
            fixture=args.fixture,
            progress=update,
        )
    print(
        f"{args.output}: {stats.events:,} events, {stats.frames:,} frames, {stats.imu:,} IMU "
        f"samples ({stats.key_renders:,} renders, {sum(stats.seconds.values()):.1f} s)"
    )
    if args.fixture:
        print(
            f"{args.fixture}: hardware-replay fixture (evcap record --device replay:{args.fixture})"
        )
    return 0


def _cmd_reconstruct(args: argparse.Namespace) -> int:
    from evcap._progress import progress_bar
    from evcap.recon.reconstruct import reconstruct

    without = set(args.without or ())
    with progress_bar(f"reconstructing ({args.preset})") as update:
        result = reconstruct(
            args.session,
            args.output,
            preset=args.preset,
            stage=args.stage,
            device=args.device,
            backend=args.backend,
            resolution=args.resolution,
            iterations=args.iterations,
            material_iterations=args.material_iterations,
            seed=args.seed,
            zero_events=args.zero_events,
            visibility="off" if "visibility" in without else args.visibility,
            indirect="off" if "indirect" in without else args.indirect,
            ablate=tuple(ABLATION_FLAGS[w] for w in sorted(without) if w in ABLATION_FLAGS),
            relight=args.relight,
            refine_poses=args.refine_poses,
            write_poses=args.write_poses,
            overwrite=args.force,
            resume=not args.force,
            say=print,
            progress=update,
        )
    stopped = ""
    if result.interrupted:
        stopped = " (interrupted: what was learnt so far; the same command goes on from there)"
    if args.stage != "material":
        print(
            f"{args.output}: {result.gaussians:,} Gaussians after {result.iterations:,} "
            f"steps in {result.seconds:.0f} s on {result.device}{stopped}"
        )
    if result.has_material:
        on = [k for k, v in (result.effects or {}).items() if v]
        print(
            f"{args.output}: material after {result.material_iterations:,} steps in "
            f"{result.material_seconds:.0f} s (with {', '.join(on) or 'nothing else'}){stopped}"
        )
    shown = (
        "object_psnr_cc",
        "object_psnr_constant",
        "normal_mae_deg",
        "depth_rel_err",
        "render_psnr_cc",
        "blur_psnr",
        "base_color_psnr_cc",
        "base_color_psnr_cc_baseline",
        "roughness_mae",
        "pbr_render_psnr_cc",
        "relit_object_psnr_cc",
        "relit_object_psnr_cc_baseline",
    )
    measured = result.figures.measured()
    figures = "  ".join(f"{k} {measured[k]:.3f}" for k in shown if k in measured)
    if figures:
        print(f"held-out views: {figures}")
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from evcap.calib.board import DEFAULT_BOARD, parse_board, write_board_image

    board = parse_board(args.board) if args.board else DEFAULT_BOARD
    if args.print_board:
        width_mm, height_mm = write_board_image(board, args.print_board, dpi=args.dpi)
        print(
            f"{args.print_board}: {board.describe()}; print at 100 % ({args.dpi} dpi): "
            f"{width_mm:.0f} x {height_mm:.0f} mm"
        )
        if args.session is None:
            return 0
    if args.session is None:
        raise InputError("give the session to calibrate (or only --print-board OUT.png)")
    from evcap._progress import progress_bar
    from evcap.calib.calibrate import calibrate, check_targets, write_calibration

    targets = [args.session, *(args.apply_to or ())]
    check_targets(targets)  # before minutes of work
    with progress_bar("calibrating") as update:
        cal = calibrate(
            args.session,
            board=board,
            skip=frozenset(args.skip or ()),
            say=print,
            progress=update,
        )
    write_calibration(targets, cal)
    print(cal.summary())
    print(f"written to /calibration of {', '.join(str(p) for p in targets)}")
    if args.report:
        from evcap.calib.report import write_report

        write_report(cal, args.report)
        print(f"{args.report}: maps of the thresholds, hot pixels and reprojection errors")
    return 0


def _cmd_poses(args: argparse.Namespace) -> int:
    from evcap._progress import progress_bar
    from evcap.poses.estimate import estimate_poses, write_poses

    with progress_bar("poses") as update:
        result = estimate_poses(
            args.session,
            kind=args.frames,
            weights=args.weights,
            rate_hz=args.rate,
            export_frames=args.export_frames,
            gravity=not args.no_gravity,
            gyro=not args.no_gyro,
            aps={"auto": None, "on": True, "off": False}[args.aps],
            threads=args.threads,
            say=print,
            progress=update,
        )
    write_poses(args.session, result)
    print(result.summary())
    print(f"written to /poses of {args.session} ({result.seconds:.0f} s of structure from motion)")
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from evcap.report.html import write_report

    page = write_report(args.output, args.session)
    print(f"{page}: open it in a browser (self-contained, no network needed)")
    return 0


def _cmd_batch(args: argparse.Namespace) -> int:
    from evcap._progress import progress_bar
    from evcap.batch.manifest import read_manifest
    from evcap.batch.run import run_batch

    manifest = read_manifest(args.manifest)
    with progress_bar(f"{len(manifest.recordings)} recordings") as update:
        rows = run_batch(
            manifest,
            args.output,
            steps=tuple(args.steps),
            preset=args.preset,
            device=args.device,
            seed=args.seed,
            cpus=args.cpus,
            address=args.address,
            workers=args.workers,
            use_ray=False if args.in_process else None,
            say=print,
            progress=update,
        )
    failed = [r for r in rows if r.status != "done"]
    print(
        f"{len(rows) - len(failed)} of {len(rows)} recordings done; "
        f"{Path(args.output) / 'index.html'} shows them side by side"
    )
    for r in failed:
        print(f"  {r.name}: {r.status}: {r.error}", file=sys.stderr)
    return 1 if failed else 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from evcap.demo import run_demo

    run_demo(args.output, preset=args.preset, fixtures=args.fixtures, force=args.force)
    return 0


def _capture_arguments(p: argparse.ArgumentParser) -> None:
    """The options of a running camera, shared by record and monitor."""
    p.add_argument("--device", default="usb", help=DEVICE_HELP)
    p.add_argument("--biases", metavar="FILE", help="biases and settings (TOML) over the defaults")
    p.add_argument("--no-aps", action="store_true", help="without APS frames")
    p.add_argument("--no-imu", action="store_true", help="without IMU samples")


class _HelpFormatter(argparse.HelpFormatter):
    """argparse measures the command names without the indent they are printed with, so the
    longest one would sit on a line of its own."""

    def add_argument(self, action: argparse.Action) -> None:
        super().add_argument(action)
        if isinstance(action, argparse._SubParsersAction):
            self._action_max_length += self._indent_increment


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="evcap",
        description="Record, calibrate and reconstruct scenes with a color event camera.",
        formatter_class=_HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"evcap {__version__}")
    sub = parser.add_subparsers(title="commands", metavar="COMMAND", required=True)

    p = sub.add_parser(
        "import",
        help="convert a recording (AEDAT, ROS bag, text) into a session",
        description="Convert a recording into a session; the container is told by the content: "
        "AEDAT 4 (DV), AEDAT 3.1 (cAER, libcaer), AEDAT 2.0 (jAER: DVS128, DAVIS240, DAVIS346), "
        "ROS 1 and ROS 2 bags (dvs_msgs/EventArray, event_camera_msgs/EventPacket, with the "
        "camera's images and IMU), event text files (t x y p; the Event-Camera Dataset's "
        "folder, with calib.txt, groundtruth.txt, images.txt, imu.txt).",
    )
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
        "--width", type=int, help="an event text file's sensor width (default: inferred)"
    )
    p.add_argument("--height", type=int, help="an event text file's sensor height")
    p.add_argument("-f", "--force", action="store_true", help="overwrite the output file")
    p.set_defaults(run=_cmd_import)

    p = sub.add_parser(
        "info",
        help="check a session; show its sensor, duration and counts",
        description="Check a session file and describe it.",
    )
    p.add_argument("session", help="the session file (.h5)")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(run=_cmd_info)

    p = sub.add_parser(
        "devices",
        help="list the connected cameras: serial, firmware, color filter",
        description="List the connected DAVIS346 cameras.",
    )
    p.add_argument("--device", default="usb", help=DEVICE_HELP)
    p.add_argument(
        "--udev",
        action="store_true",
        help="print the udev rule that lets users open the camera (Linux)",
    )
    p.set_defaults(run=_cmd_devices)

    p = sub.add_parser(
        "record",
        help="record a camera into a session file",
        description="Record a DAVIS346 into a session file until q or Ctrl-C, the duration, or the "
        "end of a replay fixture.",
    )
    p.add_argument("-o", "--output", required=True, help="the session file to write (.h5)")
    _capture_arguments(p)
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    p.add_argument(
        "--no-tui",
        action="store_true",
        help="no live view (there is none either when output is not a terminal)",
    )
    p.add_argument("-f", "--force", action="store_true", help="overwrite the output file")
    p.set_defaults(run=_cmd_record)

    p = sub.add_parser(
        "monitor",
        help="watch a camera live in the terminal; r records",
        description="Watch a camera live: event rates, events, frames, IMU, biases (editable); "
        "r starts and stops a recording into a new session file.",
    )
    _capture_arguments(p)
    p.add_argument("--output-dir", default=".", help="where recordings go (default: here)")
    p.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="replay devices: play at this multiple of real time (default 1)",
    )
    p.set_defaults(run=_cmd_monitor)

    p = sub.add_parser(
        "simulate",
        help="simulate a color event camera in a scene, with ground truth",
        description="Simulate a scene (TOML, see sim/scenes/README.md) into a session with its "
        "ground truth (/gt), poses and calibration; or events from posed images.",
    )
    p.add_argument(
        "scene",
        nargs="?",
        help="the scene file (.toml), or the name of an example scene that ships with evcap "
        "(single_object, multi_object, charuco_board, noisy_sensor, demo_orbit, demo_calibration)",
    )
    p.add_argument("-o", "--output", required=True, help="the session file to write (.h5)")
    p.add_argument("--fixture", metavar="DIR", help="also write a hardware-replay fixture")
    p.add_argument("--seed", type=int, help="random seed (default: the scene's)")
    p.add_argument(
        "--from-images",
        metavar="TRANSFORMS",
        help="a NeRF-style transforms.json: events from its posed images, in their order",
    )
    p.add_argument(
        "--held-out",
        metavar="TRANSFORMS",
        help="--from-images: a second transforms file whose views are the held-out views "
        "(never used for events); default: every 8th view of the path",
    )
    p.add_argument(
        "--background",
        type=float,
        default=1.0,
        help="--from-images: the gray level (linear, 0-1) RGBA images are composited over "
        "(default 1: white, the NeRF-Synthetic convention)",
    )
    p.add_argument("--fps", type=float, default=30.0, help="--from-images: images per second")
    p.add_argument(
        "--color-filter",
        default="RGBG",
        choices=["RGBG", "MONO"],
        help="--from-images: the simulated sensor's filter",
    )
    p.add_argument("--threshold", type=float, default=0.2, help="--from-images: contrast threshold")
    p.add_argument(
        "--scale", type=float, default=1.0, help="--from-images: resize the images by this factor"
    )
    p.add_argument("-f", "--force", action="store_true", help="overwrite the output file")
    p.set_defaults(run=_cmd_simulate)

    p = sub.add_parser(
        "calibrate",
        help="measure the sensor: intrinsics, thresholds, hot pixels, noise",
        description="Measure what a recording allows about its sensor and write it to the "
        "session's /calibration: intrinsics and distortion from a ChArUco board in the APS "
        "frames (or in frames made from the events when there are none), per-pixel ON and OFF "
        "contrast thresholds from the APS frames against the events, hot pixels, the "
        "background activity and shot noise rates, and the refractory period.",
    )
    p.add_argument("session", nargs="?", help="the session file (.h5) to calibrate")
    p.add_argument(
        "--board",
        metavar="charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT",
        help="the ChArUco board filmed (default: the board of --print-board, "
        "charuco:7x5:0.04:0.03:DICT_4X4_50)",
    )
    p.add_argument(
        "--apply-to",
        nargs="+",
        metavar="S2",
        help="also write the calibration to these sessions (same camera and biases)",
    )
    p.add_argument(
        "--skip",
        action="append",
        choices=["intrinsics", "thresholds"],
        help="do not measure this part; keep what the session holds (repeatable)",
    )
    p.add_argument("--report", metavar="OUT.png", help="write maps of the calibration")
    p.add_argument("--print-board", metavar="OUT.png", help="write the board as an image to print")
    p.add_argument("--dpi", type=int, default=300, help="--print-board's resolution")
    p.set_defaults(run=_cmd_calibrate)

    p = sub.add_parser(
        "poses",
        help="estimate the camera's path from the events",
        description="Make intensity frames from the session's events, register them by "
        "structure from motion (pycolmap) with the calibrated intrinsics fixed, and write "
        "the camera-to-world transforms to /poses (replacing what was there; scale arbitrary).",
    )
    p.add_argument("session", help="the session file (.h5), with /calibration")
    p.add_argument(
        "--frames",
        default="filter",
        choices=["filter", "timesurface", "e2vid", "firenet"],
        help="filter: a per-pixel high-pass filter, no weights (default); timesurface: a "
        "decayed time surface of either polarity, which keeps its look when the motion reverses "
        "(more frames register, less accurate: docs/poses.md); e2vid, firenet: the recurrent "
        "networks, from --weights",
    )
    p.add_argument(
        "--weights",
        metavar="FILE",
        help="the network's checkpoint (e.g. E2VID_lightweight.pth.tar); read as weights only",
    )
    p.add_argument(
        "--rate", type=float, metavar="HZ", help="frames per second (default: from the event rate)"
    )
    p.add_argument("--export-frames", metavar="DIR", help="also write the frames as PNG files")
    p.add_argument(
        "--aps",
        default="auto",
        choices=["auto", "on", "off"],
        help="whether the filter's frames lean on the APS frames (a complementary filter); auto "
        "(default): when the camera turns at most 2 deg between two of them (by the IMU; "
        "without it, when they come at 20 Hz or more)",
    )
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        metavar="N",
        help="structure from motion's threads (default 1: the same session gives the same "
        "poses bit for bit; more are faster, but COLMAP then varies a little from run to run; "
        "0: every core)",
    )
    p.add_argument(
        "--no-gyro",
        action="store_true",
        help="keep structure from motion's orientations (by default, when the session has IMU "
        "samples, the orientations are the gyroscope's, tied to the frames' by one rotation and "
        "the gyroscope's bias, and the positions are adjusted to them)",
    )
    p.add_argument(
        "--no-gravity",
        action="store_true",
        help="leave the world's orientation as structure from motion gives it (by default it "
        "is turned so that z is up when the session has IMU samples)",
    )
    p.set_defaults(run=_cmd_poses)

    p = sub.add_parser(
        "reconstruct",
        help="recover the scene from a session's events, as 3D Gaussians",
        description="Fit 3D Gaussians to a session's events (its calibration and poses are "
        "used), then their material and the light, and write OUT/gaussians.ply, OUT/renders/ "
        "(radiance, depth, normals; material/: base color, roughness, shading normals), "
        "OUT/environment.png, OUT/checkpoint/, OUT/config.toml and OUT/metrics.json (with the "
        "ground truth of a simulated session). Ctrl-C stops at the end of the current step and "
        "writes what was learnt so far; the same command then goes on from that step (the "
        "training's state is also saved every 2 minutes).",
    )
    p.add_argument("session", help="the session file (.h5), with /calibration and /poses")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="the folder to write")
    p.add_argument(
        "--stage",
        default="all",
        choices=STAGES,
        help="radiance: stage I (geometry, radiance); material: stage II (base color, "
        "roughness, normals, light) from OUT's stage-I checkpoint; all: both (default)",
    )
    p.add_argument(
        "--preset",
        default="fast",
        choices=PRESET_NAMES,
        help="tiny: a smoke test; fast: minutes on a laptop CPU (default); paper: the method's "
        "reference run, for a GPU",
    )
    p.add_argument("--device", default="cpu", choices=DEVICES, help="default: cpu")
    p.add_argument(
        "--backend",
        choices=BACKENDS,
        help="the rasterizer: cpu (compiled, the default on the CPU), torch (the pure-PyTorch "
        "reference, any device), gsplat (CUDA; the default on cuda when it is installed)",
    )
    p.add_argument(
        "--resolution", type=float, metavar="R", help="render scale relative to the sensor"
    )
    p.add_argument("--iterations", type=int, metavar="N", help="stage I steps")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--zero-events",
        choices=ZERO_EVENTS,
        help="a pixel without events means no change (target) or |change| < C (bound)",
    )
    p.add_argument("--material-iterations", type=int, metavar="N", help="stage II steps")
    for effect, what in (("visibility", "shadows"), ("indirect", "light from other surfaces")):
        p.add_argument(
            f"--{effect}",
            choices=EFFECT_MODES,
            help=f"model {what} (default auto: when the scene has occluders)",
        )
    p.add_argument(
        "--without",
        action="append",
        choices=[*ABLATION_FLAGS, "visibility", "indirect"],
        help="leave a term of stage II out (the method's ablations); repeatable",
    )
    p.add_argument(
        "--relight",
        metavar="ENV",
        help="also render the views under this environment (latitude-longitude image, z up)",
    )
    p.add_argument(
        "--refine-poses",
        default="auto",
        choices=REFINE_POSES,
        help="stage I corrects the camera's path with the events and writes it to "
        "OUT/poses.h5 (default auto: when `evcap poses` estimated it)",
    )
    p.add_argument(
        "--write-poses",
        action="store_true",
        help="also replace the session's /poses with the refined path",
    )
    p.add_argument(
        "-f",
        "--force",
        action="store_true",
        help="start over: replace the reconstruction in OUT, finished or interrupted",
    )
    p.set_defaults(run=_cmd_reconstruct)

    p = sub.add_parser(
        "report",
        help="one self-contained HTML page of a reconstruction",
        description="Write OUT/report.html: the session's summary, its calibration maps, the "
        "trajectory, the event edge maps, the recovered maps beside the truth where there is "
        "one, relit views, the metrics and the accuracy-versus-time plot. Images are embedded: "
        "it opens without a network.",
    )
    p.add_argument("output", metavar="OUT", help="a folder made by `evcap reconstruct`")
    p.add_argument("--session", help="the session (default: the one OUT was made from)")
    p.set_defaults(run=_cmd_report)

    from evcap.batch.steps import STEPS

    p = sub.add_parser(
        "batch",
        help="many recordings through every step, on a Ray cluster",
        description="Run each recording a manifest names (TOML: [[group]] tables with "
        "recordings = [paths or globs] and the calibration recording to apply) through the "
        "steps, as the single commands do, into OUT/<recording>/, with OUT/index.html and "
        "OUT/summary.csv/.json side by side. Each step is a Ray task (Ray started here, or "
        "the cluster at --address); without Ray (pip install 'evcap[cluster]') the recordings "
        "run one after the other here. Steps already done are skipped on a rerun; a recording "
        "that fails is listed with its error and the others go on.",
    )
    p.add_argument("manifest", metavar="MANIFEST", help="the manifest (TOML)")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="the output folder")
    p.add_argument("--address", help="an existing Ray cluster's address (host:port)")
    p.add_argument(
        "--steps",
        nargs="+",
        default=list(STEPS),
        choices=STEPS,
        help="the steps to run (default: all of them, in this order)",
    )
    p.add_argument("--preset", default="fast", choices=PRESET_NAMES, help="default: fast")
    p.add_argument("--device", default="cpu", choices=DEVICES, help="cuda: a GPU per task")
    p.add_argument("--seed", type=int, default=0, help="the reconstructions' seed")
    p.add_argument("--cpus", type=int, default=1, help="cores per step's task (default 1)")
    p.add_argument(
        "--workers", type=int, help="cores of the Ray started here (default: all of them)"
    )
    p.add_argument(
        "--in-process", action="store_true", help="without Ray, one recording after the other"
    )
    p.set_defaults(run=_cmd_batch)

    p = sub.add_parser(
        "demo",
        help="the whole pipeline on a bundled capture (no camera needed)",
        description="Replay a bundled capture of a simulated color scene through the driver, "
        "calibrate it from a bundled calibration recording, estimate its poses from the "
        "events, reconstruct it (both stages) and write DIR/report.html. Each step is saved "
        "as it ends: run the same command again after Ctrl-C to go on.",
    )
    p.add_argument(
        "-o", "--output", default="evcap-demo", metavar="DIR", help="default: evcap-demo"
    )
    p.add_argument(
        "--preset",
        default="tiny",
        choices=["tiny", "fast"],
        help="tiny: minutes on a CPU (default); fast: the reconstruction's laptop preset",
    )
    p.add_argument("--fixtures", metavar="DIR", help="where the demo's captures are")
    p.add_argument("-f", "--force", action="store_true", help="start a demo folder over")
    p.set_defaults(run=_cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except InputError as e:
        print(f"evcap: error: {e}", file=sys.stderr)
        return 2
    except EvcapError as e:
        print(f"evcap: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as e:
        print(f"evcap: interrupted{f': {e}' if str(e) else ''}", file=sys.stderr)
        return 130
