"""Settings of the reconstruction, one preset per use (tiny: tests; small: `evcap demo`, a minute
or two on a CPU; fast: a laptop CPU in minutes; paper: the method's reference run, for a GPU)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal, get_args

from evcap.errors import InputError

# the choices a caller names as strings; each checked where it enters (reconstruct, preset,
# material_preset, check, pick_device, pick_backend) with an error that lists them
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


@dataclass
class RadianceConfig:
    """Stage I: the event-supervised Gaussian radiance field."""

    iterations: int = 1000  # optimisation steps
    resolution: float = 0.5  # render scale, relative to the sensor (1 = full)
    # coarse to fine: the first coarse_until of the run renders at coarse_resolution (0: never)
    coarse_until: float = 0.0
    coarse_resolution: float = 0.25
    sh_degree: int = 1  # view dependence of the Gaussians' radiance (0..3)
    init_gaussians: int = 5000  # random points inside the volume the cameras look at
    # the share of them started on structure from motion's points instead, when the poses come
    # with them (`evcap poses` writes them beside the poses)
    init_on_points: float = 0.0
    max_gaussians: int = 15_000  # densification stops growing beyond this
    init_size_px: float = 1.0  # largest starting size (sigma), in render pixels
    # events: the time grid the windows are aligned to, and the window lengths drawn
    frame_interval_ms: float = 5.0  # one rendered frame every this many ms at most
    max_frames: int = 4000  # the grid is made coarser for recordings longer than this
    max_window_frames: int = 150  # a window spans 1..this many frame intervals (long ones
    # carry the edges' changes across flat regions)
    views_per_step: int = 3  # renders per step; every two of them make a window
    log_eps: float = 1e-3  # added to the radiance before the log (the sensor's dark level)
    # a pixel without events: "target" (its change is 0) or "bound" (|change| < C)
    zero_events: ZeroEvents = "target"
    # share of the event loss for pixels without events; None: one mean over all pixels, as
    # the method's sum (losses.event_loss)
    silent_weight: float | None = 0.3
    # the calibration's noise rates in the event loss: each window's expected noise events
    # (background activity, shot noise) taken from its counts before they are compared
    noise_rates: bool = False
    # a window whose pixel fired crowded events (closer than twice the calibration's
    # refractory period) measures only part of its change: its C_on ON - C_off OFF is then a
    # lower bound on the change's size, in its direction, not the change itself
    refractory_bound: bool = False
    # a background-activity filter (noise_filter.py): only the events a neighbour's supports
    # within this many ms (0: all); for dim light, where noise is a sizeable share of the events
    noise_filter_ms: float = 0.0
    # loss weights (method.md): L = L_event + 0.1 L_GW + 0.05 L_normal
    anchor_weight: float = 0.1
    anchor_level: float = 0.5  # g: the mean rendered brightness
    normal_weight: float = 0.05
    normal_from: float = 0.0  # fraction of the run after which the normal loss starts
    # mean opacity, as gsplat's opacity_reg: where the events say nothing (a plain background,
    # the inside of a patch), the fewest Gaussians that explain them
    opacity_reg: float = 0.01
    # surfaces, not fog (candidates, measured in bench/geometry.py): the spread of the depths
    # along each ray (losses.depth_spread_loss); opacities pushed to 0 or 1 (mean o (1 - o))
    # from a fraction of the run on; Gaussians flattened (mean of the smallest over the
    # largest scale); Gaussians that leave the ball the cameras converge on, grown by this
    # factor, pruned at each densification (0: never); the mean rendered alpha (what the
    # environment map can explain, it should)
    spread_weight: float = 0.0
    alpha_weight: float = 0.0
    binary_weight: float = 0.0
    binary_from: float = 0.5
    flatten_weight: float = 0.0
    confine: float = 0.0
    # the environment map learnt first: for this fraction of the run the Gaussians are hidden
    # and only the background is fitted to the events
    background_first: float = 0.0
    # the background's log radiance alike between neighbouring texels (total variation of the
    # cube map): where no outline crosses it (a plain backdrop), the events leave it free
    background_tv_weight: float = 0.0
    # neighbouring normals alike where the depth is continuous (losses.normal_smoothness_loss;
    # smooth_step: the relative depth jump that counts as an outline)
    smooth_weight: float = 0.0
    smooth_step: float = 0.02
    curvature_weight: float = 0.0  # losses.depth_curvature_loss
    quiet_tv_weight: float = 0.0  # losses.quiet_variation_loss, where no event fired
    # Adam learning rates; positions scale with the scene's extent and decay to lr_means_final
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_opacity: float = 0.025
    lr_sh: float = 2.5e-3  # degree-0 coefficients; higher bands use a twentieth of it
    # the background must be learnt fast: where it lags, Gaussians grow in front of it
    lr_background: float = 0.1
    # densification (3DGS): from/until are fractions of the run
    densify_from: float = 0.05
    densify_until: float = 0.6
    densify_every: int = 100
    grad_threshold: float = 2e-4  # mean screen-space gradient (NDC units) that densifies
    percent_dense: float = 0.01  # clone below, split above this fraction of the scene extent
    min_opacity: float = 0.005  # pruned below
    opacity_reset_every: int = 0  # steps; 0: never (resets upset the event loss on short runs)
    background_size: int = 64  # texels along an edge of each face of the background cube map
    # the backdrop's radiance (linear RGB) when it is known, as a NeRF-Synthetic release's white
    # behind every view: held there, not learnt, it fixes the gain the anchor is for (the anchor
    # is then left out) and leaves no room for fog of its colour; None: the background is learnt
    known_background: tuple[float, float, float] | None = None
    # the trajectory refined by the event loss (recon/radiance/pose_refinement.py): a correction per
    # keyframe, one every pose_keyframe_ms, learnt from pose_from of the run on by Adam at these
    # rates (radians; fractions of the scene's extent), which decay tenfold by the end; their
    # second differences along the keyframes weighted by pose_smooth_weight
    refine_poses: bool = False
    pose_keyframe_ms: float = 100.0
    pose_from: float = 0.3
    lr_pose_rotation: float = 1e-4
    lr_pose_shift: float = 1e-4
    pose_smooth_weight: float = 1.0


@dataclass
class MaterialConfig:
    """Stage II: base color, roughness, normals and the light, geometry frozen (method.md)."""

    iterations: int = 400
    # L = L_event + 1.0 L_rad + 0.1 L_GW + 0.05 L_TV, TV weights exp(-beta M_edge), lambda_n
    distill_weight: float = 1.0
    anchor_weight: float = 0.1
    tv_weight: float = 0.05
    edge_beta: float = 10.0
    tv_normal_weight: float = 0.1
    # effects: "auto" models visibility (and with it indirect light, the bounce baked with it)
    # where stage II's starting base color varies least with it (material.base_variation),
    # "on", or "off"
    visibility: EffectMode = "auto"
    indirect: EffectMode = "auto"
    # the normals stage II starts from: "planes" (through each Gaussian's neighbours) or
    # "gaussians" (each Gaussian's flattest axis, what stage I's normal loss trained)
    normals_from: NormalsFrom = "planes"
    edge_slice_ms: float = 10.0  # the events warped into each edge map
    edge_frames: int = 48  # views with an edge map; the training frames of stage II
    lr_base_color: float = 0.05
    lr_roughness: float = 0.05
    lr_normals: float = 0.01
    lr_indirect: float = 0.02
    lr_light: float = 0.05


# fast keeps stage I's normals (measured on single_object, seed 5, bench/README.md: learning
# them took them from 21.7 to 27.6 deg and the base color from 22.2 to 21.6 dB). The base
# color's TV is the method's: 80 times it (once measured best corrected on single_object) left
# the base color as rendered below a constant color there (11.4 and 12.6 dB against 18.5 and
# 18.3, stage I seeds 5 and 0; corrected 23.7 / 19.9 against 23.1 / 19.8), and on a sphere
# under a coloured sun as flat as a constant (tests/recon/test_decomposition.py: 15.2 dB
# against 20.8, the radiance's 18.9)
FAST_MATERIAL = {"lr_normals": 0.0}
MATERIAL_PRESETS: dict[Preset, MaterialConfig] = {
    "tiny": MaterialConfig(iterations=60, edge_frames=16, **FAST_MATERIAL),
    # the Gaussians' own axes as the normals (TUNED_ON["small"]: stage II's normals 18.7 / 18.0
    # deg on seeds 3 / 4 against 19.6 / 18.0 from the plane fits, the relit object 16.3 / 16.3
    # dB against 16.3 / 16.1, the base color alike)
    "small": MaterialConfig(
        iterations=60, edge_frames=16, **FAST_MATERIAL, normals_from="gaussians"
    ),
    # after fast's 4,000 steps of stage I its Gaussians' own axes are the better normals
    # (single_object, stage I seed 5, stage II on it: normals 16.7 deg as stage I's against
    # 18.7 from the plane fits; physically based render 23.0 dB against 21.1, relit object
    # 23.9 against 23.4, base color 23.73 against 23.79)
    "fast": MaterialConfig(**FAST_MATERIAL, normals_from="gaussians"),
    "paper": MaterialConfig(iterations=10_000, edge_frames=200),
}


def material_preset(name: Preset, **overrides: object) -> MaterialConfig:
    """Stage II's settings of the named preset with some fields replaced (None values are
    ignored)."""
    if name not in MATERIAL_PRESETS:
        raise InputError(f"unknown preset {name!r}; expected one of {', '.join(PRESET_NAMES)}")
    unknown = set(overrides) - {f.name for f in dataclasses.fields(MaterialConfig)}
    if unknown:
        raise InputError(f"unknown stage-II setting(s): {', '.join(sorted(unknown))}")
    config = dataclasses.replace(
        MATERIAL_PRESETS[name], **{k: v for k, v in overrides.items() if v is not None}
    )
    if config.iterations < 0:
        raise InputError("material iterations must be at least 0")
    for effect in ("visibility", "indirect"):
        if getattr(config, effect) not in EFFECT_MODES:
            raise InputError(f'{effect} must be "auto", "on" or "off"')
    if config.normals_from not in get_args(NormalsFrom):
        raise InputError(f"normals_from must be one of {', '.join(get_args(NormalsFrom))}")
    return config


TINY = RadianceConfig(
    iterations=150,
    resolution=0.25,
    sh_degree=0,
    init_gaussians=1500,
    max_gaussians=4000,
    densify_every=50,
    background_size=16,
)
# fast's geometry terms (measured on runs of thousands of steps; bench/geometry.py)
GEOMETRY_TERMS = {"spread_weight": 10.0, "background_first": 0.1, "smooth_weight": 0.3}
PRESETS: dict[Preset, RadianceConfig] = {
    "tiny": TINY,
    # tiny's Gaussians for 550 steps at half scale (about a minute and a half here), with fast's
    # geometry terms and view dependence of degree 1, started on the points structure from
    # motion triangulated, positions learnt at 3 times 3DGS's rate (its rate is for 30,000
    # steps: in 1,000 the Gaussians barely move), the mean alpha weighted 0.1. First chosen
    # (2026-11) on the demo's capture with seeds 1 to 4, two of which are now reported; the
    # mean alpha, the positions' rate and the steps checked again on tuning seeds only
    # (TUNED_ON["small"]).
    "small": dataclasses.replace(
        TINY,
        iterations=550,
        resolution=0.5,
        sh_degree=1,
        init_on_points=1.0,
        lr_means=5e-4,
        lr_means_final=5e-6,
        alpha_weight=0.1,
        **GEOMETRY_TERMS,
    ),
    # the compiled rasterizer made a step ten times cheaper: 4000 steps at 0.75 of the
    # sensor's scale (10 minutes here) measured best within 15 minutes; 30k Gaussians and
    # full scale cost more time for less (bench/recon_pareto.py). The geometry terms
    # (bench/geometry.py: depth spread, the background first, normal smoothness) were measured
    # on runs this long only; on tiny's 150 steps the depth spread cost whole-image PSNR
    "fast": RadianceConfig(
        iterations=4000,
        resolution=0.75,
        **GEOMETRY_TERMS,
        # a plain backdrop makes no events: without these, fog fills it (TUNED_ON["fast"])
        alpha_weight=0.03,
        background_tv_weight=1.0,
    ),
    # the method's reference run (reference/method.md, checked by tests/recon/test_presets.py):
    # its losses alone, over every pixel, on the sensor at full scale
    "paper": RadianceConfig(
        iterations=30_000,
        silent_weight=None,
        opacity_reg=0.0,
        resolution=1.0,
        sh_degree=3,
        init_gaussians=100_000,
        max_gaussians=1_000_000,
        densify_from=500 / 30_000,
        densify_until=15_000 / 30_000,
        opacity_reset_every=10_000,
    ),
}


@dataclass(frozen=True)
class TunedOn:
    """What a preset's settings were chosen on: bench/split.toml's tuning set only (its scenes,
    the seeds of `evcap reconstruct --seed`); tests/test_split.py checks it."""

    scenes: tuple[str, ...]
    seeds: tuple[int, ...]
    note: str


TUNED_ON: dict[Preset, TunedOn] = {
    "tiny": TunedOn((), (), "not tuned: the shortest run the tests need"),
    "small": TunedOn(
        ("demo-scene",),
        (3, 4),
        "the demo's capture (its estimated poses), seeds 3 and 4, after one gain (2026-12-02): the "
        "mean alpha at 0.1 keeps 87 / 92 % of the backdrop clear against 82 / 84 % at 0.05, the "
        "object alike (17.8 / 17.9 dB against 17.9 / 17.9, a constant color 17.2), normals 18.7 / "
        "18.0 deg against 17.3 / 20.4; positions at 3 times 3DGS's rate: depth 4.3 / 5.1 % "
        "against 5.4 / 5.6 % at its rate; 550 steps: 700 gain 0.1 dB and 0.4 deg on average "
        "for 27 % more time; stage II's normals from the Gaussians (MATERIAL_PRESETS)",
    ),
    "fast": TunedOn(
        ("single_object", "plain_backdrop"),
        (5,),
        "the geometry terms (bench/geometry.py) and stage II's normals on single_object, seed "
        "5; the mean alpha (0.03) and the cube map's TV (1.0), first chosen on NeRF-Synthetic "
        "mic's release views, re-chosen on plain_backdrop, seed 5, stage I after one gain "
        "(2026-12-02): the backdrop seen through on 23 % of its pixels against 0.1 % without "
        "them, the whole image 25.0 dB against 20.0, the object 24.0 against 24.9 (a constant "
        "color 16.4), depth 8.0 % against 5.4 %; on single_object they cost 0.8 dB (26.3 against "
        "27.1 after a gain and offset, 2026-11)",
    ),
    "paper": TunedOn((), (), "not tuned: the method's reference run (reference/method.md)"),
}


def preset(name: Preset, **overrides: object) -> RadianceConfig:
    """The named preset with some fields replaced (None values are ignored)."""
    if name not in PRESETS:
        raise InputError(f"unknown preset {name!r}; expected one of {', '.join(PRESET_NAMES)}")
    unknown = set(overrides) - {f.name for f in dataclasses.fields(RadianceConfig)}
    if unknown:
        raise InputError(f"unknown stage-I setting(s): {', '.join(sorted(unknown))}")
    config = dataclasses.replace(
        PRESETS[name], **{k: v for k, v in overrides.items() if v is not None}
    )
    check(config)
    return config


def check(config: RadianceConfig) -> None:
    if config.iterations < 1:
        raise InputError("iterations must be at least 1")
    for name in ("resolution", "coarse_resolution"):
        if not 0 < getattr(config, name) <= 4:
            raise InputError(f"{name} is a render scale in (0, 4]; 1 is the sensor's")
    if not 0 <= config.coarse_until <= 1:
        raise InputError("coarse_until is a fraction of the run, in [0, 1]")
    if not 0 <= config.sh_degree <= 3:
        raise InputError("sh_degree must be 0..3")
    if config.zero_events not in ZERO_EVENTS:
        raise InputError('zero_events must be "target" or "bound"')
    if config.frame_interval_ms <= 0 or config.max_window_frames < 1:
        raise InputError("frame_interval_ms must be > 0 and max_window_frames >= 1")
    if config.noise_filter_ms < 0:
        raise InputError("noise_filter_ms must be 0 (no filter) or a positive time")
    if config.views_per_step < 2:
        raise InputError("views_per_step must be at least 2 (a window needs two views)")
    if not 0 <= config.init_on_points <= 1:
        raise InputError("init_on_points is a share of init_gaussians, in [0, 1]")
    if config.known_background is not None and (
        len(config.known_background) != 3 or not all(v > 0 for v in config.known_background)
    ):
        raise InputError("known_background is a radiance: three numbers above 0 (linear RGB)")
    if not 0 <= config.pose_from < 1 or config.pose_keyframe_ms <= 0:
        raise InputError("pose_from is a fraction of the run, in [0, 1); pose_keyframe_ms > 0")


def to_dict(config: RadianceConfig | MaterialConfig) -> dict:
    return dataclasses.asdict(config)


@dataclass(frozen=True)
class MeshConfig:
    """How the mesh is made from a reconstruction."""

    voxel: float | None = None  # scene units; None: the surface's extent / voxels_across
    # (min corner, max corner) of the box kept, scene units; None: all the views see
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    voxels_across: int = 192
    views: int = 60  # views along the camera path, fused and baked
    render_scale: float = 1.0  # of the sensor's focal length
    truncation_voxels: float = 4.0
    min_alpha: float = 0.5  # less opaque pixels see the background: empty space
    keep_share: float = 0.05  # parts with less of the largest part's area are floaters
    max_triangles: int = 40_000  # the mesh simplified to this many (about)
    texture_size: int = 1024
    depth_tolerance_voxels: float = 3.0  # a texel is what a view sees within this
