"""What a reconstruction is run with, in one frozen record: `evcap reconstruct`'s flags, the
pipeline's settings (`evcap demo`, `evcap batch`) and the Python API all make one, so every
option reaches every way of running. Without torch: the command line and the pipeline hold one
before any step runs; ``settings()`` resolves the preset and the named settings (that imports
the stages' configs)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal, get_args

from evcap.errors import InputError
from evcap.recon.config import (
    ABLATIONS,
    BACKENDS,
    DEVICES,
    PRESET_NAMES,
    STAGES,
    Ablation,
    Backend,
    Device,
    Preset,
    Stage,
)

if TYPE_CHECKING:
    from evcap.recon.presets import ReconstructionSettings

# what is done with what OUT holds: "go on" with an interrupted stage that fits, refusing
# anything else OUT holds (a finished reconstruction, a state that does not fit); "start over",
# replacing it all; "go on or start over": go on where a state fits, else start over (the
# pipeline's: a rerun of `evcap demo` goes on, or redoes what it must)
Resume = Literal["go on", "start over", "go on or start over"]
RESUMES: tuple[Resume, ...] = get_args(Resume)


@dataclass(frozen=True)
class ReconstructOptions:
    """A reconstruction's options. ``settings``: the stages' settings by dotted name over the
    preset's (``{"stage1.iterations": 200}``; recon/presets.py's ReconstructionSettings names
    them), kept as (name, value) pairs in the order given."""

    preset: Preset = "fast"
    stage: Stage = "all"
    device: Device = "cpu"
    backend: Backend | None = None  # None: the device's default (recon/raster/rasterize.py)
    seed: int = 0
    settings: tuple[tuple[str, object], ...] = ()
    ablate: tuple[Ablation, ...] = ()  # stage II's terms left out
    relight: str | None = None  # an environment image the views are also lit by
    write_poses: bool = False  # the refined path also made the session's /poses
    resume: Resume = "go on"

    def __post_init__(self) -> None:
        if isinstance(self.settings, Mapping):
            object.__setattr__(self, "settings", tuple(self.settings.items()))
        object.__setattr__(self, "ablate", tuple(self.ablate))
        for name, value, choices in (
            ("preset", self.preset, PRESET_NAMES),
            ("stage", self.stage, STAGES),
            ("device", self.device, DEVICES),
            ("resume", self.resume, RESUMES),
        ):
            if value not in choices:
                raise InputError(f"unknown {name} {value!r}; expected one of {', '.join(choices)}")
        if self.backend is not None and self.backend not in BACKENDS:
            raise InputError(
                f"unknown backend {self.backend!r}; expected one of {', '.join(BACKENDS)}"
            )
        unknown = sorted(set(self.ablate) - set(ABLATIONS))
        if unknown:
            raise InputError(f"unknown ablation(s) {', '.join(unknown)}")
        self._refuse_what_the_stage_ignores()

    def _refuse_what_the_stage_ignores(self) -> None:
        """An option the stages run do not read is refused, not dropped without a word."""
        names = [name for name, _ in self.settings]
        if self.stage == "material":
            ignored = [n for n in names if n.split(".")[0] == "stage1"]
            if ignored:
                raise InputError(
                    f"{', '.join(ignored)}: stage I's settings do nothing with --stage material "
                    "(stage I is read from OUT's checkpoint, as it was fitted); leave them out, or "
                    "run --stage all"
                )
            if self.write_poses:
                raise InputError(
                    "--write-poses with --stage material: stage I refines the poses; run it"
                )
        if self.stage == "radiance":
            ignored = [n for n in names if n.split(".")[0] == "stage2"]
            if ignored or self.ablate or self.relight:
                what = ", ".join(
                    [*ignored, *(["--without"] if self.ablate else [])]
                    + (["--relight"] if self.relight else [])
                )
                raise InputError(
                    f"{what}: stage II's options do nothing with --stage radiance; leave them "
                    "out, or run --stage all"
                )

    def settings_dict(self) -> dict[str, object]:
        return dict(self.settings)

    def resolved(self) -> ReconstructionSettings:
        """Both stages' settings: the preset's with ``settings`` over them (an unknown name,
        or a value of the wrong kind, refused by name)."""
        from evcap.recon.presets import preset

        return preset(self.preset, self.settings_dict())

    def held(self) -> dict:
        """The options as plain values (what a pipeline's state file holds)."""
        return {
            "preset": self.preset,
            "stage": self.stage,
            "device": self.device,
            "backend": self.backend,
            "seed": self.seed,
            "settings": {k: list(v) if isinstance(v, tuple) else v for k, v in self.settings},
            "ablate": list(self.ablate),
            "relight": self.relight,
            "write_poses": self.write_poses,
        }


def _silent(line: str) -> None:
    pass


@dataclass(frozen=True)
class Feedback:
    """What a reconstruction tells as it goes: ``say`` a line, ``progress(done, total,
    status)`` after each training step."""

    say: Callable[[str], None] = _silent
    progress: Callable[[int, int, str], None] | None = field(default=None)


def read_settings_file(path: str | Path) -> dict[str, object]:
    """A TOML file of settings, its tables the dotted names' parts ([stage1.densify]
    grad_threshold = 2e-4), as {dotted name: value}. A reconstruction's config.toml is one: its
    [reconstruct] table (how the run was asked for, not settings) is left out."""
    import tomllib

    from evcap.recon.settings import flatten

    path = Path(path)
    try:
        table = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: no such settings file") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not a TOML file ({e})") from None
    table.pop("reconstruct", None)
    return flatten(table)
