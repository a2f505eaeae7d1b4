"""The commands of the steps' floor, one step each: simulate, calibrate, poses, reconstruct,
report, export, view. Calibrate, poses, reconstruct and report parse their flags and run the
step as the pipeline does (evcap.pipeline.steps: each step wired once), then say what it made."""

from __future__ import annotations

import argparse
from pathlib import Path

from evcap.app.command import Command
from evcap.app.reconstruct_flags import (
    add_bounds_argument,
    add_reconstruct_arguments,
    options_from,
    show_settings,
)
from evcap.errors import InputError

# light: the reconstruction's names and choices, without torch
from evcap.recon.config import STAGES
from evcap.recon.mesh.config import MeshConfig


def _simulate_arguments(p: argparse.ArgumentParser) -> None:
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
        "--sensor",
        metavar="PROFILE",
        help="a named sensor's thresholds and effects in place of the scene's: davis346 (a "
        "DAVIS346 as published and measured, sim/scenes/README.md) or ideal",
    )
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


def _simulate(args: argparse.Namespace) -> int:
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
                profile=args.sensor,
                scale=args.scale,
                seed=args.seed or 0,
                overwrite=args.force,
                progress=update,
            )
        print(f"{args.output}: {n:,} events from {args.from_images}")
        return 0
    from evcap.sim.scene import example_scene, load_scene, with_sensor_profile
    from evcap.sim.simulate import simulate

    scene = load_scene(example_scene(args.scene))
    if args.sensor:
        scene = with_sensor_profile(scene, args.sensor)
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


SIMULATE = Command(
    "simulate",
    help="simulate a color event camera in a scene, with ground truth",
    description="Simulate a scene (TOML, see sim/scenes/README.md) into a session with its "
    "ground truth (/gt), poses and calibration; or events from posed images.",
    arguments=_simulate_arguments,
    run=_simulate,
)


def _calibrate_arguments(p: argparse.ArgumentParser) -> None:
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
    p.add_argument(
        "--intrinsics",
        metavar="FILE",
        help="take the intrinsics and distortion from a calibration made with another tool, in "
        "place of a board: a Kalibr camchain (with its camera-IMU transform and time shift, "
        "which `evcap poses` then uses), ROS camera_info or VINS YAML, or DV's calibration XML; "
        "the thresholds, hot pixels and noise are measured from the recording as ever",
    )
    p.add_argument(
        "--camera",
        metavar="NAME",
        help="the camera to take of an --intrinsics file holding several: cam0, cam1, ... or "
        "its name in the file (default: the first, cam0)",
    )
    p.add_argument(
        "--export",
        metavar="FILE",
        help="write the session's calibration to FILE.yaml (as --format says) or FILE.xml "
        "(DV's); alone it measures nothing, after --intrinsics it writes what was imported",
    )
    p.add_argument(
        "--format",
        choices=["kalibr", "ros", "vins"],
        help="--export's YAML: kalibr (the default: a camchain, the one that holds both "
        "distortion models and the camera-IMU transform), ros (camera_info) or vins",
    )
    p.add_argument("-f", "--force", action="store_true", help="replace --export's file")


def _calibrate(args: argparse.Namespace) -> int:
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
    measure = _calibrate_flags_checked(args)
    if args.export:
        from evcap.calib.export import check_export

        # before minutes of work (and before the session's calibration is replaced)
        check_export(args.export, args.format, args.force, args.intrinsics, args.camera)
    if measure:
        from evcap._progress import progress_bar
        from evcap.pipeline import calibrate_step

        targets = [args.session, *(args.apply_to or ())]
        cal = calibrate_step(
            args.session,
            board=board,
            also=args.apply_to or (),
            skip=frozenset(args.skip or ()),
            intrinsics=args.intrinsics,
            camera=args.camera,
            say=print,
            progress=progress_bar,
        )
        print(cal.summary())
        print(f"written to /calibration of {', '.join(str(p) for p in targets)}")
        if args.report:
            from evcap.calib.report import write_report

            write_report(cal, args.report)
            print(f"{args.report}: maps of the thresholds, hot pixels and reprojection errors")
    if args.export:
        from evcap.calib.export import export_calibration
        from evcap.importers.calibration_files import FORMATS

        fmt, left_out = export_calibration(
            args.session, args.export, args.format, overwrite=args.force
        )
        print(f"{args.export}: the calibration of {args.session} as a {FORMATS[fmt]}")
        for part in left_out:
            print(f"not written: {part}")
    return 0


def _calibrate_flags_checked(args: argparse.Namespace) -> bool:
    """Whether to calibrate (not only --export); InputError for flags that do not go together."""
    if args.camera and not args.intrinsics:
        raise InputError("--camera picks a camera of an --intrinsics file: give the file")
    if args.format and not args.export:
        raise InputError("--format goes with --export FILE.yaml")
    if args.intrinsics and args.board:
        raise InputError(
            "--board is the board to measure the intrinsics on; --intrinsics takes "
            "them from a file: give one of them"
        )
    if (
        args.intrinsics
        and args.export
        and Path(args.export).resolve() == Path(args.intrinsics).resolve()
    ):
        raise InputError(f"--export {args.export} would replace the --intrinsics file itself")
    if args.export and not args.intrinsics:
        measuring = [
            f
            for f, v in (
                ("--board", args.board),
                ("--skip", args.skip),
                ("--apply-to", args.apply_to),
                ("--report", args.report),
            )
            if v
        ]
        if measuring:
            raise InputError(
                f"--export alone writes the calibration {args.session} holds; "
                f"{', '.join(measuring)} measure one: calibrate first, then --export (or "
                "--intrinsics FILE --export OUT)"
            )
        return False
    return True


CALIBRATE = Command(
    "calibrate",
    help="measure the sensor: intrinsics, thresholds, hot pixels, noise",
    description="Measure what a recording allows about its sensor and write it to the "
    "session's /calibration: intrinsics and distortion from a ChArUco board in the APS "
    "frames (or in frames made from the events when there are none), or from a calibration "
    "file of another tool (--intrinsics: Kalibr, ROS, VINS, DV), per-pixel ON and OFF "
    "contrast thresholds from the APS frames against the events, hot pixels, the "
    "background activity and shot noise rates, and the refractory period. --export writes "
    "the session's calibration for those tools.",
    arguments=_calibrate_arguments,
    run=_calibrate,
)


def _poses_arguments(p: argparse.ArgumentParser) -> None:
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


def _poses(args: argparse.Namespace) -> int:
    from evcap._progress import progress_bar
    from evcap.pipeline import poses_step

    result = poses_step(
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
        progress=progress_bar,
    )
    print(result.summary())
    print(f"written to /poses of {args.session} ({result.seconds:.0f} s of structure from motion)")
    return 0


POSES = Command(
    "poses",
    help="estimate the camera's path from the events",
    description="Make intensity frames from the session's events, register them by "
    "structure from motion (pycolmap) with the calibrated intrinsics fixed, and write "
    "the camera-to-world transforms to /poses (replacing what was there; scale arbitrary).",
    arguments=_poses_arguments,
    run=_poses,
)


def _reconstruct_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "session", nargs="?", help="the session file (.h5), with /calibration and /poses"
    )
    p.add_argument("-o", "--output", metavar="OUT", help="the folder to write")
    p.add_argument(
        "--stage",
        default="all",
        choices=STAGES,
        help="radiance: stage I (geometry, radiance); material: stage II (base color, "
        "roughness, normals, light) from OUT's stage-I checkpoint; all: both (default)",
    )
    add_reconstruct_arguments(p)
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
    p.add_argument(
        "--show-settings",
        action="store_true",
        help="print every setting these flags resolve to, by its dotted name (for --set and "
        "--settings), with what it is, and stop",
    )


def _reconstruct(args: argparse.Namespace) -> int:
    from evcap._progress import progress_bar
    from evcap.pipeline import reconstruct_step

    resume = "start over" if args.force else "go on"
    fixed = {"stage": args.stage, "write_poses": args.write_poses}
    options = options_from(args, resume=resume, **fixed)
    if args.show_settings:
        print(show_settings(options))
        return 0
    if args.session is None or args.output is None:
        raise InputError("give the session and the folder to write: SESSION -o OUT")
    result = reconstruct_step(args.session, args.output, options, say=print, progress=progress_bar)
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
    figures = "  ".join(f"{k} {v:.3f}" for k, v in result.figures.shown().items())
    if figures:
        print(f"held-out views: {figures}")
    return 0


RECONSTRUCT = Command(
    "reconstruct",
    help="recover the scene from a session's events, as 3D Gaussians",
    description="Fit 3D Gaussians to a session's events (its calibration and poses are "
    "used), then their material and the light, and write OUT/gaussians.ply, OUT/renders/ "
    "(radiance, depth, normals; material/: base color, roughness, shading normals), "
    "OUT/environment.png, OUT/checkpoint/, OUT/config.toml and OUT/metrics.json (with the "
    "ground truth of a simulated session). Ctrl-C stops at the end of the current step and "
    "writes what was learnt so far; the same command then goes on from that step (the "
    "training's state is also saved every 2 minutes).",
    arguments=_reconstruct_arguments,
    run=_reconstruct,
)


def _report_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("output", metavar="OUT", help="a folder made by `evcap reconstruct`")
    p.add_argument("--session", help="the session (default: the one OUT was made from)")


def _report(args: argparse.Namespace) -> int:
    from evcap.pipeline import report_step

    page = report_step(args.output, args.session)
    print(f"{page}: open it in a browser (self-contained, no network needed)")
    return 0


REPORT = Command(
    "report",
    help="one self-contained HTML page of a reconstruction",
    description="Write OUT/report.html: the session's summary, its calibration maps, the "
    "trajectory, the event edge maps, the recovered maps beside the truth where there is "
    "one, relit views, the metrics and the accuracy-versus-time plot. Images are embedded: "
    "it opens without a network.",
    arguments=_report_arguments,
    run=_report,
)


def _mesh_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--resolution",
        type=float,
        metavar="VOXEL",
        help="the voxel size of the depth fusion, in the scene's units (default: the "
        f"surface's extent / {MeshConfig.voxels_across})",
    )
    add_bounds_argument(
        p,
        "keep only the box between these corners (scene units, z up; `evcap view` "
        "shows the axes): the object without stage I's backdrop",
    )
    for flag, default, text in (
        ("--views", MeshConfig.views, "views along the camera path fused"),
        ("--texture-size", MeshConfig.texture_size, "the textures' side, pixels"),
        ("--triangles", MeshConfig.max_triangles, "the mesh simplified to about this many"),
    ):
        p.add_argument(flag, type=int, default=default, help=f"{text} (default %(default)s)")
    p.add_argument("--session", help="the session (default: the one OUT was made from)")


def _mesh_config(args: argparse.Namespace):

    for name in ("views", "texture_size", "triangles"):
        if getattr(args, name) < 1:
            raise InputError(f"--{name.replace('_', '-')} must be at least 1")
    if args.resolution is not None and not args.resolution > 0:
        raise InputError("--resolution must be a positive voxel size (scene units)")
    return MeshConfig(
        bounds=(tuple(args.bounds[:3]), tuple(args.bounds[3:])) if args.bounds else None,
        voxel=args.resolution,
        views=args.views,
        texture_size=args.texture_size,
        max_triangles=args.triangles,
    )


def _export_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("output", metavar="OUT", help="a folder made by `evcap reconstruct`")
    p.add_argument(
        "-o",
        "--asset",
        required=True,
        metavar="ASSET",
        help="the file to write: .glb (glTF 2.0), .obj (with .mtl and textures) or .ply",
    )
    _mesh_arguments(p)


def _export(args: argparse.Namespace) -> int:
    from evcap.recon.mesh.export import FORMATS, export_mesh

    if not args.asset.lower().endswith(FORMATS):
        raise InputError(f"{args.asset}: write .glb, .obj or .ply")
    asset = export_mesh(args.output, args.session, _mesh_config(args), print)
    written = asset.write(args.asset)
    print(asset.summary())
    print("wrote " + ", ".join(str(p) for p in written))
    return 0


EXPORT = Command(
    "export",
    help="a textured mesh of a reconstruction (.glb, .obj, .ply)",
    description="Fuse the reconstruction's depth along the camera path into a mesh (TSDF and "
    "marching cubes), drop its floaters and bake stage II's base color and roughness into "
    "textures: glTF's metallic-roughness material (metallic 0) is the method's BRDF. "
    "Positions in the session's units; the .glb is y up as glTF asks, .obj and .ply keep the "
    "world's z up. docs/reconstruction.md says more.",
    arguments=_export_arguments,
    run=_export,
)


def _view_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("output", metavar="OUT", help="a folder made by `evcap reconstruct`")
    p.add_argument("--no-open", action="store_true", help="write the page, open no browser")
    _mesh_arguments(p)


def _view(args: argparse.Namespace) -> int:
    from evcap.app.view import write_folder_viewer

    page = write_folder_viewer(args.output, args.session, _mesh_config(args))
    print(f"{page}: open it in a browser (self-contained, no network needed)")
    if not args.no_open:
        import webbrowser

        if not webbrowser.open(page.resolve().as_uri()):
            print("no browser found here: open the page by hand")
    return 0


VIEW = Command(
    "view",
    help="the reconstruction in 3D in a browser: mesh, Gaussians, path",
    description="Write OUT/viewer.html (one self-contained page, WebGL) with the textured "
    "mesh (OUT/mesh.glb, exported first when it is not there; its options as `evcap "
    "export`'s), the Gaussians' centres and the camera path, and open it in the browser. "
    "`evcap report` links it.",
    arguments=_view_arguments,
    run=_view,
)

# in the order `evcap --help` lists them
COMMANDS = (SIMULATE, CALIBRATE, POSES, RECONSTRUCT, REPORT, EXPORT, VIEW)
