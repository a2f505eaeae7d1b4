"""The presets: `paper` is the method's reference run, its settings read against
reference/method.md (tests/recon/test_reconstruct.py runs it end to end, its steps cut
short); every preset resolves to the settings it had before they were nested by component."""

import json
import re
from pathlib import Path

import pytest

from evcap.recon.config import PRESET_NAMES
from evcap.recon.presets import preset
from evcap.recon.scene.event_stereo import StereoConfig
from evcap.recon.scene.support_plane import SupportConfig
from evcap.recon.settings import names
from evcap.sim.scene import SensorSpec

# each preset's settings as the code before issue 69 resolved them (its flat RadianceConfig
# and MaterialConfig, written by that code), and where each flat name went
BEFORE = json.loads((Path(__file__).parent / "presets_before_issue_69.json").read_text())
STAGE_ONE = {
    "coarse_until": "coarse.until",
    "coarse_resolution": "coarse.resolution",
    "init_gaussians": "init.gaussians",
    "init_on_points": "init.on_points",
    "init_size_px": "init.size_px",
    "max_gaussians": "densify.max_gaussians",
    "frame_interval_ms": "windows.frame_interval_ms",
    "max_frames": "windows.max_frames",
    "max_window_frames": "windows.max_window_frames",
    "views_per_step": "windows.views_per_step",
    "refractory_bound": "windows.refractory_bound",
    "noise_filter_ms": "windows.noise_filter_ms",
    "log_eps": "event_loss.log_eps",
    "zero_events": "event_loss.zero_events",
    "silent_weight": "event_loss.silent_weight",
    "noise_rates": "event_loss.noise_rates",
    "anchor_weight": "loss.anchor.weight",
    "anchor_level": "loss.anchor.level",
    "normal_weight": "loss.normal.weight",
    "normal_from": "loss.normal.start",
    "opacity_reg": "loss.opacity.weight",
    "spread_weight": "loss.spread.weight",
    "alpha_weight": "loss.alpha.weight",
    "binary_weight": "loss.binary.weight",
    "binary_from": "loss.binary.start",
    "flatten_weight": "loss.flatten.weight",
    "smooth_weight": "loss.smooth.weight",
    "smooth_step": "loss.smooth.step",
    "curvature_weight": "loss.curvature.weight",
    "quiet_tv_weight": "loss.quiet_tv.weight",
    "background_tv_weight": "loss.background_tv.weight",
    "confine": "densify.confine",
    "background_first": "background.first",
    "background_size": "background.size",
    "known_background": "background.known",
    "densify_from": "densify.start",
    "densify_until": "densify.stop",
    "densify_every": "densify.every",
    "grad_threshold": "densify.grad_threshold",
    "percent_dense": "densify.percent_dense",
    "min_opacity": "densify.min_opacity",
    "opacity_reset_every": "densify.reset_every",
    "pose_keyframe_ms": "poses.keyframe_ms",
    "pose_from": "poses.start",
    "lr_pose_rotation": "poses.lr_rotation",
    "lr_pose_shift": "poses.lr_shift",
    "pose_smooth_weight": "poses.smooth_weight",
    # before, the preset's False was always replaced by reconstruct()'s refine_poses, "auto"
    # unless asked otherwise; now that choice is the setting
    "refine_poses": "poses.refine",
}
STAGE_ONE |= {f"lr_{k}": f"lr.{k}" for k in ("means", "means_final", "scales", "quats")}
STAGE_ONE |= {f"lr_{k}": f"lr.{k}" for k in ("opacity", "sh", "background")}
# settings the code before did not have, and the values that do what it did: every term but
# the normal's and the binary's counted from the start
NEW = {f"loss.{t}.start": 0.0 for t in ("anchor", "spread", "smooth", "curvature", "quiet_tv")}
NEW |= {f"loss.{t}.start": 0.0 for t in ("background_tv", "alpha", "opacity", "flatten")}
# none started on the events' stereo, whose own settings then do nothing
NEW |= {"init.on_events": 0.0} | {f"init.stereo.{k}": v for k, v in names(StereoConfig())}
# none started on a support plane, whose own settings then do nothing
NEW |= {"init.on_support": 0.0} | {f"init.support.{k}": v for k, v in names(SupportConfig())}
# none asked the stereo's points to block their rays
NEW |= {"loss.block.weight": 0.0, "loss.block.start": 0.0, "loss.block.tolerance": 0.03}
NEW |= {"loss.block.opaque": 1.0}
# none pruned by its largest blending weight, nor held in a given box
NEW |= {"densify.min_weight": 0.0, "densify.bounds": None}
# 3D Gaussians, not surfels
NEW |= {"surfels": False}
STAGE_TWO = {
    "distill_weight": "loss.distill",
    "anchor_weight": "loss.anchor",
    "tv_weight": "loss.tv",
    "tv_normal_weight": "loss.tv_normals",
    "edge_beta": "loss.edge_beta",
    "edge_slice_ms": "edges.slice_ms",
    "edge_frames": "edges.frames",
}
STAGE_TWO |= {f"lr_{k}": f"lr.{k}" for k in ("base_color", "roughness", "normals")}
STAGE_TWO |= {f"lr_{k}": f"lr.{k}" for k in ("indirect", "light")}


# settings a preset changed since, by measurement (each preset's TUNED_ON says on what)
CHANGED = {
    "fast": {
        "init.on_events": 1.0,
        "loss.alpha.weight": 0.1,
        "init.stereo.aperture": 0.1,
        "init.on_support": 0.3,
        "loss.quiet_tv.weight": 0.3,
    }
}


def as_before(config, renamed: dict[str, str], changed: dict | None = None) -> dict:
    """The nested config's settings under the flat names they had before, but for those
    ``changed`` since (checked to be as changed, then left out)."""
    now = {name: value for name, value in names(config)}
    for name, value in (changed or {}).items():
        assert now.pop(name) == value, name
    for name, value in NEW.items():
        if name in now:
            assert now.pop(name) == value, name
    back = {old: now.pop(new) for old, new in renamed.items() if new in now}
    back |= now  # the names that did not change
    back = {k: list(v) if isinstance(v, tuple) else v for k, v in back.items()}
    if back.get("refine_poses") == "auto":
        back["refine_poses"] = False
    return back


@pytest.mark.parametrize("name", PRESET_NAMES)
def test_every_preset_resolves_to_the_settings_it_had(name):
    settings = preset(name)
    changed = CHANGED.get(name, {})
    # a changed setting's value before is left out with it
    was = {old for old, new in STAGE_ONE.items() if new in changed}
    before = {k: v for k, v in BEFORE[name]["stage1"].items() if k not in was}
    assert as_before(settings.stage1, STAGE_ONE, changed) == before
    assert as_before(settings.stage2, STAGE_TWO) == BEFORE[name]["stage2"]


def number(text: str, pattern: str) -> float:
    found = re.search(pattern, text)
    assert found, f"method.md no longer says {pattern!r}"
    return float(found.group(1).replace(",", ""))


def test_paper_is_the_methods_stage_one(method_summary):
    method = method_summary
    paper = preset("paper").stage1
    loss = re.search(r"Stage I: L = L_event \+ ([\d.]+) L_GW \+ ([\d.]+) L_normal", method)
    assert loss, "method.md no longer states stage I's loss"
    assert paper.loss.anchor.weight == float(loss.group(1))
    assert paper.loss.normal.weight == float(loss.group(2))
    assert paper.loss.anchor.level == number(method, r"pulled to g = ([\d.]+)")
    assert paper.iterations == number(method, r"Stage I ([\d,]+) iterations")
    assert paper.lr.opacity == number(method, r"opacity lr ([\d.]+)")
    assert paper.resolution == 1.0  # "800x800 input": the sensor at its own size
    assert paper.densify.reset_every > 0  # "standard 3DGS ... opacity reset"
    # a pixel without events is "no change" over every pixel: the method's plain sum
    assert paper.event_loss.zero_events == "target" and paper.event_loss.silent_weight is None
    # and nothing the method does not have
    ours = ("spread", "alpha", "binary", "flatten", "smooth", "curvature", "quiet_tv")
    ours += ("background_tv", "opacity")
    assert all(getattr(paper.loss, name).weight == 0 for name in ours)
    assert paper.background.first == 0 and paper.densify.confine == 0
    assert paper.densify.min_weight == 0


def test_paper_is_the_methods_stage_two(method_summary):
    method = method_summary
    paper = preset("paper").stage2
    loss = re.search(
        r"Stage II: L = L_event \+ ([\d.]+) L_rad \+ ([\d.]+) L_GW \+ ([\d.]+) L_TV, "
        r"beta = ([\d.]+), lambda_n = ([\d.]+)",
        method,
    )
    assert loss, "method.md no longer states stage II's loss"
    distill, anchor, tv, beta, lambda_n = (float(x) for x in loss.groups())
    assert (paper.loss.distill, paper.loss.anchor, paper.loss.tv) == (distill, anchor, tv)
    assert (paper.loss.edge_beta, paper.loss.tv_normals) == (beta, lambda_n)
    assert paper.iterations == number(method, r"Stage II ([\d,]+) more")
    assert paper.lr.normals > 0  # the normals are learnt (fast freezes them)
    assert paper.normals_from == "planes"  # and the normals start as they always did


def test_the_simulators_threshold_is_the_methods(method_summary):
    c = number(method_summary, r"C = ([\d.]+)\.")
    assert SensorSpec().threshold_on == SensorSpec().threshold_off == c
