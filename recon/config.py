"""The reconstruction's choices that a caller names as strings (the stages, presets, devices,
rasterizers...), without torch: the command line reads them to build its flags. The settings
themselves are in recon/presets.py and beside each component."""

from __future__ import annotations

from typing import Literal, get_args

# each checked where it enters (the options, the configs, pick_device, pick_backend) with an
# error that lists them
Stage = Literal["radiance", "material", "all"]  # stage I, stage II, both
Preset = Literal["tiny", "small", "fast", "paper"]
Device = Literal["cpu", "cuda"]
Backend = Literal["cpu", "torch", "gsplat"]  # the rasterizer (recon/raster/rasterize.py)
ZeroEvents = Literal["target", "bound"]  # what a pixel without events says
EffectMode = Literal["auto", "on", "off"]  # stage II's visibility and indirect light
Ablation = Literal["anchor", "tv", "distill"]  # stage II's terms that can be left out
RefinePoses = Literal["auto", "on", "off"]  # auto: when the poses were estimated by evcap
NormalsFrom = Literal["planes", "gaussians"]  # stage II's starting normals
STAGES: tuple[Stage, ...] = get_args(Stage)
PRESET_NAMES: tuple[Preset, ...] = get_args(Preset)
DEVICES: tuple[Device, ...] = get_args(Device)
BACKENDS: tuple[Backend, ...] = get_args(Backend)
ZERO_EVENTS: tuple[ZeroEvents, ...] = get_args(ZeroEvents)
EFFECT_MODES: tuple[EffectMode, ...] = get_args(EffectMode)
ABLATIONS: tuple[Ablation, ...] = get_args(Ablation)
REFINE_POSES: tuple[RefinePoses, ...] = get_args(RefinePoses)
# the command line's names of the ablations (`evcap reconstruct --without NAME`)
ABLATION_FLAGS: dict[str, Ablation] = {
    "anchor": "anchor",
    "edge-tv": "tv",
    "distillation": "distill",
}
