"""Stage II: the stage-I Gaussians, frozen, given a material (base color, roughness, a normal;
metallic 0), shaded under a learnt environment light (method.md):

    L = L_event + 1.0 L_rad + 0.1 L_GW + 0.05 L_TV

L_rad holds the physically based render to the frozen stage-I radiance of the same view; L_TV
smooths the rendered base color and normals except where the event edge map has an edge.
Visibility (baked from the geometry) and indirect light (its bounce, and learnt) are modelled
where they make the starting base color smoother (`auto`), or as the settings say.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from evcap.edge_maps import edge_map
from evcap.recon._threads import torch_on_one_thread
from evcap.recon.config import Ablation, Backend, EffectMode
from evcap.recon.events.loss import event_loss
from evcap.recon.material.config import MaterialConfig
from evcap.recon.material.shading import (
    DIFFUSE_DIRECTIONS,
    MIN_ROUGHNESS,
    diffuse_both_sides,
    fibonacci_directions,
    irradiance,
    shade,
)
from evcap.recon.material.visibility import Bounce, bake_occlusion
from evcap.recon.radiance.config import RadianceConfig
from evcap.recon.radiance.losses import anchor_loss, checked_loss
from evcap.recon.radiance.stage import CHECK_EVERY, RadianceField, TrainingData
from evcap.recon.radiance.terms import Term, total_loss
from evcap.recon.raster.rasterize import (
    Camera,
    Render,
    gaussian_normals,
    quat_to_rotmat,
    rasterize,
)
from evcap.recon.resume import Steps, digest, random_states, restore_random_states
from evcap.recon.scene.cube_map import cube_directions, cube_lookup, mip_chain
from evcap.recon.scene.gaussians import Background, Gaussians
from evcap.recon.scene.neighbours import nearest
from evcap.recon.scene.optics import RenderGrid
from evcap.recon.scene.sh import eval_sh
from evcap.recon.step_timer import UNTIMED, StepTimer
from evcap.records import Poses
from evcap.session import Session

# the channels of a stage-II render, in order
CHANNELS = {"radiance": 3, "base_color": 3, "roughness": 1, "shading_normal": 3}
# "auto" effects: the base color's variation at the start, in renders of this many views
# along the path, over pixels at least this opaque, each step between neighbouring pixels
# counted up to SMOOTH_STEP in log (summed over the channels): what shading explains changes
# gradually, an edge of the material counts no more than a small step (unbounded, visibility
# alone won on a ball on a floor whose radiance the bounce had made, by lowering the ball's
# contrast against the floor). On that ball (tests/recon/test_material.py) any bound from 0.01
# to 0.1 tells which effects made the radiance
START_VIEWS = 6
OPAQUE_PIXEL = 0.9
SMOOTH_STEP = 0.05
NEIGHBOUR_OPACITY = 0.1  # Gaussians fainter than this are not taken as the surface


def _logit(x: torch.Tensor) -> torch.Tensor:
    return torch.log(x) - torch.log1p(-x)


def relit_indirect(
    indirect: torch.Tensor,
    learnt: list[torch.Tensor],
    light: list[torch.Tensor],
    normals: torch.Tensor,
    directions: torch.Tensor,
) -> torch.Tensor:
    """The learnt light from other surfaces [N, 3] under another ``light``: it came off surfaces
    lit by the learnt light, so it changes as the light falling around the point does (the
    ratio of the two lights' open-sky irradiance at its normal). Kept as learnt, it would
    carry the first light's bounce into every relit view."""
    old = irradiance(learnt, normals, directions)
    new = irradiance(light, normals, directions)
    floor = 1e-3 * old.mean().clamp(min=1e-6)
    # where the learnt light hardly reaches a normal, the two lights' mean ratio
    overall = new.mean(0) / old.mean(0).clamp(min=1e-6)
    return indirect * torch.where(old > floor, new / old.clamp(min=floor), overall)


class MaterialField(torch.nn.Module):
    """Frozen Gaussians with a learnt material, and the light."""

    def __init__(
        self,
        gaussians: Gaussians,
        light: Background,
        normals: torch.Tensor,
        visibility: torch.Tensor | None,
        indirect: bool,
        backend: Backend = "cpu",
        bounce: Bounce | None = None,
        backdrop: torch.Tensor | None = None,
        surfels: bool = False,
    ) -> None:
        super().__init__()
        self.gaussians = gaussians.requires_grad_(False)
        # also what the camera sees where the Gaussians leave light through, unless the
        # background is known (stage I's backdrop [3])
        self.light = light
        self.register_buffer("backdrop", backdrop)
        n = len(gaussians)
        self.base_logits = torch.nn.Parameter(torch.zeros(n, 3))
        self.roughness_logits = torch.nn.Parameter(torch.zeros(n))
        self.normals = torch.nn.Parameter(normals.clone())
        self.indirect_sh = torch.nn.Parameter(torch.full((n, 4, 3), -8.0)) if indirect else None
        self.register_buffer("directions", fibonacci_directions(DIFFUSE_DIRECTIONS))
        self.register_buffer("visibility", visibility)  # [N, K] at the directions, or None
        # who sees whom where the light is blocked (Bounce), or None
        for name in ("receivers", "sources", "weights"):
            self.register_buffer(f"bounce_{name}", getattr(bounce, name, None))
        self.backend = backend
        self.surfels = surfels  # the Gaussians rendered as stage I rendered them
        self.register_buffer("surfel_discs", torch.tensor(surfels))  # saved with the state
        # base_variation at the start under each choice of effects, where "auto" chose them
        self.start_variation: dict[str, float] = {}

    @classmethod
    def from_state(cls, state: dict[str, torch.Tensor], backend: Backend = "cpu") -> MaterialField:
        """The field whose state_dict ``state`` is (a checkpoint's, a training state's): its
        visibility and light bounces as they were baked, nothing baked again."""
        prefix = "gaussians."
        gaussians = Gaussians.from_state(
            {k.removeprefix(prefix): v for k, v in state.items() if k.startswith(prefix)}
        )
        bounce = None
        if "bounce_receivers" in state:
            bounce = Bounce(*(state[f"bounce_{k}"] for k in ("receivers", "sources", "weights")))
        field = cls(
            gaussians,
            Background.from_faces(state["light.faces"]),
            state["normals"],
            state.get("visibility"),
            "indirect_sh" in state,
            backend,
            bounce,
            state.get("backdrop"),
            bool(state.get("surfel_discs", False)),
        )
        field.load_state_dict({"surfel_discs": torch.tensor(False), **state})
        return field

    @property
    def effects(self) -> dict[str, bool]:
        return {
            "visibility": self.visibility is not None,
            "indirect": self.indirect_sh is not None,
        }

    @property
    def bounce(self) -> Bounce | None:
        if self.bounce_receivers is None:
            return None
        return Bounce(self.bounce_receivers, self.bounce_sources, self.bounce_weights)

    @property
    def base_color(self) -> torch.Tensor:
        return torch.sigmoid(self.base_logits)

    @property
    def roughness(self) -> torch.Tensor:
        return MIN_ROUGHNESS + (1 - MIN_ROUGHNESS) * torch.sigmoid(self.roughness_logits)

    def shaded(self, center: torch.Tensor, light: list[torch.Tensor] | None = None):
        """(radiance [N, 3] towards a camera at ``center``, unit normals [N, 3] facing it)."""
        g = self.gaussians
        view = F.normalize(center - g.means, dim=1)
        n = F.normalize(self.normals, dim=1)
        n = torch.where((n * view).sum(1, keepdim=True) < 0, -n, n)  # two-sided
        vis = None if self.visibility is None else self.visibility.float()
        learnt = mip_chain(self.light.radiance_faces())
        indirect = None
        if self.indirect_sh is not None:
            indirect = F.softplus(eval_sh(1, self.indirect_sh, n))
            if light is not None:  # relit: see relit_indirect
                indirect = relit_indirect(indirect, learnt, light, n, self.directions)
        light = learnt if light is None else light
        bounce, bounced = self.bounce, None
        if bounce is not None:  # baked with the visibility: never without it
            leaving = diffuse_both_sides(
                self.base_color, F.normalize(self.normals, dim=1), light, self.directions, vis
            )
            bounced = bounce.irradiance(leaving, len(g))
        color = shade(
            self.base_color,
            self.roughness,
            n,
            view,
            light,
            self.directions,
            vis,
            indirect,
            bounced,
        )
        return color, n

    def render(
        self, T_world_cam: np.ndarray, grid: RenderGrid, light: list[torch.Tensor] | None = None
    ) -> Render:
        """Channels (CHANNELS): the physically based radiance, base color, roughness and the
        shading normals (camera frame); the light behind the Gaussians in the radiance."""
        device = self.gaussians.means.device
        viewmat = torch.as_tensor(np.linalg.inv(T_world_cam), dtype=torch.float32, device=device)
        return self.render_view(viewmat, grid, light)

    def render_view(
        self, viewmat: torch.Tensor, grid: RenderGrid, light: list[torch.Tensor] | None = None
    ) -> Render:
        """render() from ``viewmat`` [4, 4] (world to camera, on the field's device)."""
        cam = Camera(viewmat, grid.K, grid.width, grid.height)
        color, n = self.shaded(cam.center, light)
        features = torch.cat(
            [color, self.base_color, self.roughness[:, None], n @ viewmat[:3, :3].T], 1
        )
        if self.backdrop is not None:
            sky = self.backdrop.expand(grid.height, grid.width, 3)
        else:
            faces = self.light.radiance_faces() if light is None else light[0]
            sky = cube_lookup(faces, grid.directions(viewmat))
        bg = torch.cat([sky, sky.new_zeros(*sky.shape[:-1], 7)], -1)
        g = self.gaussians
        return rasterize(
            g.means,
            g.quats,
            g.scales,
            g.opacities,
            features,
            cam,
            background=bg,
            backend=self.backend,
            surfels=self.surfels,
        )


def new_material_field(
    radiance: RadianceField, data: TrainingData, config: MaterialConfig
) -> MaterialField:
    """Stage II's start: normals from the plane of each Gaussian's neighbours or the Gaussians'
    own (config.normals_from; facing the cameras), base color such that the shading under the
    stage-I background as light gives the stage-I radiance. Visibility (baked from the
    geometry) and indirect light (the bounce baked with the visibility): as the config says,
    or, "auto", the choice under which that base color varies least, seen along the path
    (`base_variation`; indirect light goes with the visibility, `effect_choices`)."""
    g = radiance.gaussians
    light = Background.from_faces(radiance.background.faces.data.cpu())
    if radiance.backdrop is not None:  # the learnt background was never used: a uniform start
        light.faces.data.copy_(torch.log(torch.expm1(radiance.backdrop.cpu()))[None, :, None, None])
    with torch.no_grad():
        if config.normals_from == "planes" and (g.opacities > NEIGHBOUR_OPACITY).sum() >= 3:
            normals = plane_normals(g.means, g.opacities)
        elif radiance.surfels:  # a disc's normal is its third axis
            normals = quat_to_rotmat(g.quats)[:, :, 2]
        else:
            normals = gaussian_normals(g.quats, g.scales)
        cams = torch.as_tensor(
            data.track.at(data.windows.frame_times)[:, :3, 3].mean(0), dtype=torch.float32
        ).to(g.means.device)
        normals = torch.where(
            ((cams - g.means) * normals).sum(1, keepdim=True) < 0, -normals, normals
        )
        target = g.radiance(cams, 0)
    choices = effect_choices(config.visibility, config.indirect)
    baked = None
    if any(visibility for visibility, _ in choices):
        directions = fibonacci_directions(DIFFUSE_DIRECTIONS).to(g.means.device)
        bounce = any(visibility and indirect for visibility, indirect in choices)
        baked = bake_occlusion(g, normals, directions, bounce=bounce)
    fields, variation = {}, {}
    for visibility, indirect in choices:
        field = MaterialField(
            g,
            light,
            normals.cpu(),
            baked.visibility if visibility else None,
            indirect,
            radiance.backend,
            baked.bounce if visibility and indirect else None,
            radiance.backdrop,
            radiance.surfels,
        ).to(g.means.device)
        start_material(field, target, cams)
        if len(choices) == 1:
            return field
        name = effects_name(visibility, indirect)
        fields[name], variation[name] = field, base_variation(field, data)
    field = fields[min(variation, key=variation.get)]  # on a tie the fewest effects
    field.start_variation = variation
    return field


def effect_choices(visibility: EffectMode, indirect: EffectMode) -> list[tuple[bool, bool]]:
    """The (visibility, indirect) pairs the modes leave open, the fewest effects first.
    "auto" indirect light goes with the visibility: what blocks a surface's light sends it
    light of its own (the bounce, baked with the visibility). On multi_object's true surfaces
    visibility without it fitted worst of the three though its start varied least
    (bench/README.md): the start cannot tell those two apart."""
    options = {"on": [True], "off": [False], "auto": [False, True]}
    return [
        (v, i)
        for v in options[visibility]
        for i in ([v] if indirect == "auto" else options[indirect])
    ]


def effects_name(visibility: bool, indirect: bool) -> str:
    on = [k for k, v in (("visibility", visibility), ("indirect", indirect)) if v]
    return "+".join(on) or "neither"


@torch.no_grad()
def start_material(field: MaterialField, target: torch.Tensor, cams: torch.Tensor) -> None:
    """Roughness 0.6, base color such that the shading seen from ``cams`` of a mid-gray
    surface, scaled, gives ``target`` [N, 3]."""
    field.base_logits.zero_()
    field.roughness_logits.fill_(_logit(torch.tensor((0.6 - MIN_ROUGHNESS) / (1 - MIN_ROUGHNESS))))
    color, _ = field.shaded(cams)
    field.base_logits.copy_(_logit((0.5 * target / color.clamp(min=1e-6)).clamp(0.03, 0.97)))


@torch.no_grad()
def base_variation(field: MaterialField, data: TrainingData, views: int = START_VIEWS) -> float:
    """Mean absolute step of the log base color between neighbouring opaque pixels of
    ``views`` renders along the path, each bounded by SMOOTH_STEP: the gradual variation the
    shading leaves to the material, where the cameras see it. An effect that explains the
    radiance (a shadow, a neighbour's color) lowers it; one that does not (misjudged normals
    that see into their own surface) raises it. In log, so that a light that is dimmer
    overall (as visibility makes it) does not count as variation."""
    viewmats = data.viewmats()
    frames = np.unique(np.linspace(0, len(viewmats) - 1, views).round().astype(int))
    total, count = 0.0, 0
    for f in frames:
        r = field.render_view(viewmats[int(f)], data.grid)
        opaque = r.alpha > OPAQUE_PIXEL
        log = torch.log((r.color[..., 3:6] / r.alpha[..., None].clamp(min=1e-6)).clamp(min=1e-3))
        for d, both in (
            (log[:, 1:] - log[:, :-1], opaque[:, 1:] & opaque[:, :-1]),
            (log[1:] - log[:-1], opaque[1:] & opaque[:-1]),
        ):
            total += float(d.abs().sum(-1).clamp(max=SMOOTH_STEP)[both].sum())
            count += int(both.sum())
    return total / count if count else 0.0


@torch.no_grad()
def plane_normals(
    means: torch.Tensor, opacity: torch.Tensor, k: int = 32, chunk: int = 65536
) -> torch.Tensor:
    """[N, 3] unsigned normal of the plane through each point's k nearest visible neighbours
    (the smallest principal axis of their spread): the surface the centres lie on, steadier
    than each Gaussian's own flattest axis (which measured a few degrees worse on the
    example scene)."""
    ref = means[opacity > NEIGHBOUR_OPACITY]
    k = min(k, len(ref))
    _, found = nearest(ref, means, k)
    found = torch.from_numpy(found).to(means.device)
    out = []
    for idx in found.split(chunk):
        nb = ref[idx] - ref[idx].mean(1, keepdim=True)
        # on the CPU: CUDA's batched eigh stopped stage II on an H100 (torch 2.11 + CUDA 13,
        # CUSOLVER_STATUS_INTERNAL_ERROR on 116k Gaussians); 3 x 3 matrices cost little here
        _, vectors = torch.linalg.eigh((nb.transpose(1, 2) @ nb).cpu().double())
        out.append(vectors[:, :, 0].to(means))
    return torch.cat(out)


@dataclass
class MaterialLog:
    step: int
    loss: float
    event: float
    distill: float
    anchor: float
    tv: float
    seconds: float


@dataclass
class MaterialFit:
    field: MaterialField
    log: list[MaterialLog]
    interrupted: bool
    steps: int = 0  # the steps done


def edge_frames(data: TrainingData, count: int) -> np.ndarray:
    """The frames stage II trains on: evenly spread over the recording."""
    return np.unique(np.linspace(0, len(data.windows) - 1, max(count, 2)).round().astype(int))


def edge_maps(
    session: Session, data: TrainingData, frames: np.ndarray, slice_ms: float, device: str
) -> dict[int, torch.Tensor]:
    """The event edge map [h, w] of each frame, on the render grid: the events of the slice
    before the frame's time, warped by contrast maximisation."""
    grid = data.grid
    # where each sensor pixel lies on the render (undistorted, scaled)
    g = data.grid.grid.reshape(-1, 2).cpu().numpy().astype(np.float64)
    u = (g[:, 0] + 1) / 2 * (grid.width - 1)
    v = (g[:, 1] + 1) / 2 * (grid.height - 1)
    out = {}
    for f in frames:
        t1 = int(data.windows.frame_times[f])
        t0 = t1 - round(slice_ms * 1000)
        ev = session.events(t0, t1)
        pix = ev.y.astype(np.int64) * data.optics.width + ev.x
        keep = ~data.optics.hot_pixels.ravel()[pix]
        xy = np.stack([u[pix[keep]], v[pix[keep]]], 1)
        m, _ = edge_map(xy, ev.t[keep], t1, grid.width, grid.height)
        out[int(f)] = torch.from_numpy(m).to(device)
    return out


def start_stage_two(
    radiance: RadianceField,
    data: TrainingData,
    session: Session,
    config: MaterialConfig,
    device: str,
) -> tuple[MaterialField, dict]:
    """Stage II's field at its start (new_material_field: its normals, visibility, light
    bounces and effects) and what else it derived, as its training state keeps it: the
    training frames, the TV's weights exp(-beta M_edge) of each (kept instead of the edge
    maps), stage I's render of each (the distillation's targets) and a digest of stage I's
    Gaussians and trajectory. torch on one thread throughout (recon/_threads.py)."""
    with torch_on_one_thread():
        field = new_material_field(radiance, data, config)
        frames = edge_frames(data, config.edges.frames)
        edges = edge_maps(session, data, frames, config.edges.slice_ms, device)
        with torch.no_grad():
            views = data.viewmats()
            targets = [radiance.render_view(views[f], data.grid).color for f in frames]
        tv_weights = [torch.exp(-config.loss.edge_beta * edges[int(f)]) for f in frames]
    return field, {
        "frames": torch.from_numpy(frames),
        "tv_weights": torch.stack(tv_weights),
        "targets": torch.stack(targets),
        "stage_one": stage_one_digest(radiance, data.track),
    }


def stage_one_digest(radiance: RadianceField, track: Poses) -> str:
    """A digest of what stage II starts from: stage I's Gaussians and the trajectory."""
    g = radiance.gaussians.state_dict()
    return digest(*(g[k] for k in sorted(g)), track.t, track.T_world_cam)


def resume_misfit(state: dict, radiance: RadianceField, track: Poses) -> str:
    """Why stage II cannot go on from a saved ``state`` with the stage I ``radiance`` and the
    path ``track`` (OUT's): it started from another stage I, or it does not hold what this
    evcap's stage II holds; "" when it can."""
    if state["start"]["stage_one"] != stage_one_digest(radiance, track):
        return (
            "it was started from another stage I than the one beside it (its Gaussians or the "
            "path it refined differ)"
        )
    try:
        MaterialField.from_state(state["material"])
    except (KeyError, RuntimeError) as e:
        return f"it does not hold what this evcap's stage II holds ({' '.join(str(e).split())})"
    return ""


def train_material(
    radiance: RadianceField,
    data: TrainingData,
    session: Session,
    stage1: RadianceConfig,
    config: MaterialConfig,
    *,
    seed: int = 0,
    device: str = "cpu",
    progress: Callable[[int, int, str], None] | None = None,
    clock: Callable[[], float] = time.perf_counter,
    ablate: frozenset[Ablation] = frozenset(),
    resume: dict | None = None,
    save_state: Callable[[dict], None] | None = None,
    save_every_s: float = 120.0,
    timer: StepTimer = UNTIMED,
) -> MaterialFit:
    """Fit stage II from a stage-I field; Ctrl-C ends it at the end of the step with what was
    learnt so far. ``ablate`` switches terms off: "anchor", "tv", "distill". ``resume`` and
    ``save_state`` as for train_radiance: what stage II derived at its start is taken from the
    state, nothing is baked or rendered again (``resume_misfit`` tells whether it fits)."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed + 2)
    radiance.requires_grad_(False)
    if resume is None:
        field, start = start_stage_two(radiance, data, session, config, device)
        derived = data.derived()
    else:
        start = resume["start"]
        derived = resume["data"]  # what ``data`` was loaded with (load_training_data)
        field = MaterialField.from_state(resume["material"], radiance.backend).to(device)
    frames_all = start["frames"].numpy()
    weights = {int(f): w.to(device) for f, w in zip(frames_all, start["tv_weights"], strict=True)}
    targets = {int(f): x.to(device) for f, x in zip(frames_all, start["targets"], strict=True)}
    groups = [
        {"params": [field.base_logits], "lr": config.lr.base_color},
        {"params": [field.roughness_logits], "lr": config.lr.roughness},
        {"params": [field.normals], "lr": config.lr.normals},
        {"params": [field.light.faces], "lr": config.lr.light},
    ]
    if field.indirect_sh is not None:
        groups.append({"params": [field.indirect_sh], "lr": config.lr.indirect})
    optimizer = torch.optim.Adam(groups, eps=1e-15)
    stride = max(len(data.windows) / len(frames_all), 1.0)
    # windows as long as stage I's, counted in stage II's coarser frames
    spacing = dataclasses.replace(
        stage1.windows, max_window_frames=max(1, int(stage1.windows.max_window_frames / stride))
    )
    terms = stage_two_terms(stage1, config, ablate)
    log: list[MaterialLog] = []
    loss = math.nan  # as last checked
    steps = Steps(config.iterations, save_state, save_every_s, clock, resume)
    if resume is not None:
        optimizer.load_state_dict(resume["optimizer"])
        field.start_variation = dict(resume.get("start_variation", {}))
        restore_random_states(rng, resume["random"])
        log = [MaterialLog(**x) for x in resume["log"]]

    def state() -> dict:
        checked_loss("stage II", steps.step, None, field.parameters())  # none saved broken
        return {
            "step": steps.step,
            "data": derived,
            "start": start,
            "material": field.state_dict(),
            "optimizer": optimizer.state_dict(),
            "random": random_states(rng),
            "log": [dataclasses.asdict(x) for x in log],
            "seconds": steps.seconds(),
            "start_variation": field.start_variation,
        }

    with steps.running(state):
        while steps.next():
            step = steps.step
            pick = spacing.draw(rng, len(frames_all))
            frames = frames_all[pick]
            with timer("render"):
                views = data.viewmats()
                renders = [field.render_view(views[int(f)], data.grid) for f in frames]
            with timer("loss"):
                seen = [data.grid.sample(r.color[..., :3]) for r in renders]
                inputs = StepInputs(data, frames, renders, seen, targets, weights, timer)
                total = total_loss(terms, inputs, step, background_alone=False)
            with timer("backward"):
                total.backward()
            with timer("optimizer"):
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
                with torch.no_grad():
                    field.normals.data = F.normalize(field.normals.data, dim=1)
            if step % CHECK_EVERY == 0 or step == config.iterations:
                loss = checked_loss("stage II", step, total, field.parameters())
                shown = {k: float(inputs.logged.get(k, 0.0)) for k in LOGGED}
                log.append(MaterialLog(step, loss, **shown, seconds=steps.seconds()))
            steps.end()
            if progress:
                shown = f"material loss {loss:.4f}" if math.isfinite(loss) else "material"
                progress(step, config.iterations, shown)
    return MaterialFit(field, log, steps.interrupted, steps.step)


LOGGED = ("event", "distill", "anchor", "tv")  # the terms a step's log shows


@dataclass
class StepInputs:
    """What stage II's terms read of a step: its renders at ``frames`` (their colors at the
    sensor's pixels in ``seen``), stage I's render of each frame (``targets``), exp(-beta
    M_edge) of each (``tv_weights``), and ``logged``, where the terms put what the log shows."""

    data: TrainingData
    frames: np.ndarray
    renders: list[Render]
    seen: list[torch.Tensor]
    targets: dict[int, torch.Tensor]
    tv_weights: dict[int, torch.Tensor]
    timer: StepTimer = UNTIMED
    logged: dict[str, torch.Tensor] = dataclasses.field(default_factory=dict)


def stage_two_terms(
    stage1: RadianceConfig, config: MaterialConfig, ablate: frozenset[Ablation]
) -> list[Term]:
    """L = L_event + 1.0 L_rad + 0.1 L_GW + 0.05 L_TV, in that order, without the terms
    ``ablate`` leaves out (and the anchor where the background is known)."""
    weights = config.loss

    def logged(name: str, value: Callable[[StepInputs], torch.Tensor]):
        def term(x: StepInputs) -> torch.Tensor:
            out = value(x)
            x.logged[name] = out.detach()
            return out

        return term

    def event(x: StepInputs) -> torch.Tensor:
        return event_loss(x.seen, x.frames, x.data, stage1.event_loss, x.timer)

    def distill(x: StepInputs) -> torch.Tensor:
        dl = 0
        for f, r in zip(x.frames, x.renders, strict=True):
            dl = dl + (r.color[..., :3] - x.targets[int(f)]).abs().mean()
        return dl / len(x.renders)

    def anchor(x: StepInputs) -> torch.Tensor:
        return anchor_loss(torch.cat(x.seen), stage1.loss.anchor.level)

    def tv(x: StepInputs) -> torch.Tensor:
        return sum(
            edge_tv(r.color, x.tv_weights[int(f)], weights.tv_normals)
            for f, r in zip(x.frames, x.renders, strict=True)
        ) / len(x.renders)

    terms = [Term("event", 1.0, 0, logged("event", event))]
    if "distill" not in ablate:
        terms.append(Term("distill", weights.distill, 0, logged("distill", distill)))
    if "anchor" not in ablate and stage1.background.known is None:
        terms.append(Term("anchor", weights.anchor, 0, logged("anchor", anchor)))
    if "tv" not in ablate:
        terms.append(Term("tv", weights.tv, 0, logged("tv", tv)))
    return terms


def edge_tv(maps: torch.Tensor, weight: torch.Tensor, normal_weight: float) -> torch.Tensor:
    """Mean of w (|grad base color|_1 + lambda_n |grad n|_1) over a stage-II render [h, w, C]
    (CHANNELS), w = exp(-beta M_edge) [h, w]."""
    base, normal = maps[..., 3:6], maps[..., 7:10]

    def grad(x: torch.Tensor) -> torch.Tensor:
        dx = (x[:, 1:] - x[:, :-1]).abs().sum(-1)
        dy = (x[1:] - x[:-1]).abs().sum(-1)
        return (weight[:, 1:] * dx).mean() + (weight[1:] * dy).mean()

    return grad(base) + normal_weight * grad(normal)


def environment_image(light: list[torch.Tensor], width: int = 256) -> np.ndarray:
    """The light as a latitude-longitude image [width / 2, width, 3] (z up, the simulator's
    convention: azimuth from +x, top row the zenith)."""
    h = width // 2
    v, u = torch.meshgrid(
        (torch.arange(h) + 0.5) / h, (torch.arange(width) + 0.5) / width, indexing="ij"
    )
    phi, lat = (u - 0.5) * 2 * math.pi, (0.5 - v) * math.pi
    d = torch.stack([lat.cos() * phi.cos(), lat.cos() * phi.sin(), lat.sin()], -1)
    with torch.no_grad():
        return cube_lookup(light[0], d.to(light[0].device)).cpu().numpy()


def light_from_image(image: np.ndarray, size: int, device: str = "cpu") -> list[torch.Tensor]:
    """A latitude-longitude environment image [H, W, 3] (linear RGB, z up) as a light."""
    d = cube_directions(size)
    u = (torch.atan2(d[..., 1], d[..., 0]) / (2 * math.pi) + 0.5) * 2 - 1
    v = (0.5 - torch.asin(d[..., 2].clamp(-1, 1)) / math.pi) * 2 - 1
    img = torch.as_tensor(np.ascontiguousarray(image), dtype=torch.float32).permute(2, 0, 1)
    faces = F.grid_sample(
        img[None].expand(6, -1, -1, -1),
        torch.stack([u, v], -1),
        align_corners=False,
        padding_mode="border",
    )
    return mip_chain(faces.clamp(min=0).to(device))
