"""The reconstruction's flags, one set for every command that reconstructs (`evcap reconstruct`,
`evcap demo`, `evcap batch`), read into the one options record (recon/options.py): a flag for
each common setting, `--set NAME=VALUE` and `--settings FILE.toml` for any other."""

from __future__ import annotations

import argparse
import re
from collections.abc import Sequence

# light: the reconstruction's names and choices, without torch
from evcap.recon.config import (
    ABLATION_FLAGS,
    BACKENDS,
    DEVICES,
    EFFECT_MODES,
    PRESET_NAMES,
    REFINE_POSES,
    ZERO_EVENTS,
    Preset,
)
from evcap.recon.options import ReconstructOptions, Resume, read_settings_file

# the flags that name one setting: flag's destination -> the setting's dotted name
SHORTHANDS = {
    "resolution": "stage1.resolution",
    "iterations": "stage1.iterations",
    "zero_events": "stage1.event_loss.zero_events",
    "noise_filter": "stage1.windows.noise_filter_ms",
    "refine_poses": "stage1.poses.refine",
    "bounds": "stage1.densify.bounds",
    "material_iterations": "stage2.iterations",
    "visibility": "stage2.visibility",
    "indirect": "stage2.indirect",
}


def add_bounds_argument(p: argparse._ActionsContainer, text: str) -> None:
    """``--bounds X0 Y0 Z0 X1 Y1 Z1``: a box in the scene (reconstruct's and export's)."""
    p.add_argument(
        "--bounds", type=float, nargs=6, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"), help=text
    )


def add_reconstruct_arguments(
    p: argparse.ArgumentParser,
    *,
    preset: Preset = "fast",
    presets: Sequence[Preset] = PRESET_NAMES,
) -> None:
    """The reconstruction's flags (``preset``: the default; ``presets``: those offered)."""
    g = p.add_argument_group("reconstruction")
    g.add_argument(
        "--preset",
        default=preset,
        choices=presets,
        help="tiny: a smoke test; small: a minute or two on a CPU (`evcap demo`'s); fast: "
        "minutes on a laptop CPU; paper: the method's reference run, for a GPU "
        f"(default: {preset})",
    )
    g.add_argument("--device", default="cpu", choices=DEVICES, help="default: cpu")
    g.add_argument(
        "--backend",
        choices=BACKENDS,
        help="the rasterizer: cpu (compiled, the default on the CPU), torch (the pure-PyTorch "
        "reference, any device), gsplat (CUDA; the default on cuda when it is installed)",
    )
    g.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    g.add_argument("--iterations", type=int, metavar="N", help="stage I steps")
    g.add_argument(
        "--resolution", type=float, metavar="R", help="render scale relative to the sensor"
    )
    g.add_argument(
        "--zero-events",
        choices=ZERO_EVENTS,
        help="a pixel without events means no change (target) or |change| < C (bound)",
    )
    g.add_argument(
        "--refractory-bound",
        action="store_true",
        help="a window whose pixel fired within twice the calibration's refractory period "
        "bounds the change's size from below instead of giving it (the period's change is lost)",
    )
    g.add_argument(
        "--noise-filter",
        type=float,
        metavar="MS",
        help="leave out the events no neighbouring pixel's event came within MS ms before (a "
        "background-activity filter, for dim light; 5 is a start; default: none)",
    )
    g.add_argument(
        "--refine-poses",
        choices=REFINE_POSES,
        help="stage I corrects the camera's path with the events and writes it to "
        "OUT/poses.h5 (default auto: when `evcap poses` estimated it)",
    )
    add_bounds_argument(
        g,
        "the object's box (scene units, as `evcap export --bounds`): Gaussians that leave it "
        "are pruned, what lies beyond is the background's (default: none)",
    )
    g.add_argument("--material-iterations", type=int, metavar="N", help="stage II steps")
    for effect, what in (("visibility", "shadows"), ("indirect", "light from other surfaces")):
        g.add_argument(
            f"--{effect}",
            choices=EFFECT_MODES,
            help=f"model {what} (default auto: when the scene has occluders)",
        )
    g.add_argument(
        "--without",
        action="append",
        choices=[*ABLATION_FLAGS, "visibility", "indirect"],
        help="leave a term of stage II out (the method's ablations); repeatable",
    )
    g.add_argument(
        "--relight",
        metavar="ENV",
        help="also render the views under this environment (latitude-longitude image, z up)",
    )
    g.add_argument(
        "--set",
        action="append",
        dest="assignments",
        metavar="NAME=VALUE",
        help="any setting by its dotted name, e.g. stage1.densify.grad_threshold=2e-4 (the "
        "value as TOML reads it); repeatable; `evcap reconstruct --show-settings` lists them",
    )
    g.add_argument(
        "--settings",
        metavar="FILE.toml",
        help="settings from a TOML file ([stage1.densify] grad_threshold = 2e-4; a "
        "reconstruction's OUT/config.toml is one); --set and the flags above go over it",
    )


def options_from(
    args: argparse.Namespace, *, resume: Resume = "go on", **fixed: object
) -> ReconstructOptions:
    """The options record of the parsed flags (``fixed``: fields a command sets itself, as
    `evcap reconstruct`'s stage). Settings from --settings, then --set, then the flags that
    name one; a setting named twice is refused."""
    from evcap.errors import InputError
    from evcap.recon.settings import parse_assignments

    settings: dict[str, object] = {}
    if args.settings:
        settings.update(read_settings_file(args.settings))
    given = parse_assignments(args.assignments or [])
    flags = {name: getattr(args, dest) for dest, name in SHORTHANDS.items()}
    flags = {name: value for name, value in flags.items() if value is not None}
    if args.refractory_bound:
        flags["stage1.windows.refractory_bound"] = True
    without = set(args.without or ())
    for effect in ("visibility", "indirect"):
        if effect in without:
            if getattr(args, effect) is not None:
                raise InputError(f"--{effect} and --without {effect} say different things")
            flags[f"stage2.{effect}"] = "off"
    if args.bounds and not all(
        a < b for a, b in zip(args.bounds[:3], args.bounds[3:], strict=True)
    ):
        raise InputError(
            f"--bounds: each of the max corner {args.bounds[3:]} must exceed the min "
            f"{args.bounds[:3]}"
        )
    twice = sorted(set(given) & set(flags))
    if twice:
        raise InputError(f"{', '.join(twice)}: given both by --set and by its own flag")
    settings.update(given)
    settings.update(flags)
    try:
        return ReconstructOptions(
            preset=args.preset,
            device=args.device,
            backend=args.backend,
            seed=args.seed,
            settings=settings,
            ablate=tuple(ABLATION_FLAGS[w] for w in sorted(without) if w in ABLATION_FLAGS),
            relight=args.relight,
            resume=resume,
            **fixed,  # type: ignore[arg-type]
        )
    except InputError as e:  # said by the flags the user gave
        message = str(e)
        for dest, name in SHORTHANDS.items():
            if name in flags and name not in given:
                flag = "--" + dest.replace("_", "-")
                message = re.sub(rf"\b{re.escape(name)}\b", f"{flag} ({name})", message)
        raise InputError(message) from None


def show_settings(options: ReconstructOptions) -> str:
    """Every setting the options resolve to, by its dotted name, with what it is."""
    from evcap.recon.settings import describe

    settings = options.resolved()
    lines = [f"# preset {options.preset}, with {len(options.settings)} setting(s) given"]
    for name, value, doc in describe(settings):
        lines.append(f"{name} = {value!r}")
        if doc:
            lines.append(f"    {doc}")
    return "\n".join(lines)
