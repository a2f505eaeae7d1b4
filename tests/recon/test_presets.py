"""The presets: `paper` is the method's reference run, its settings read against
reference/method.md (tests/recon/test_reconstruct.py runs it end to end, its steps cut
short)."""

import re

from evcap.recon import config as cfg
from evcap.sim.scene import SensorSpec


def number(text: str, pattern: str) -> float:
    found = re.search(pattern, text)
    assert found, f"method.md no longer says {pattern!r}"
    return float(found.group(1).replace(",", ""))


def test_paper_is_the_methods_stage_one(method_summary):
    method = method_summary
    paper = cfg.preset("paper")
    loss = re.search(r"Stage I: L = L_event \+ ([\d.]+) L_GW \+ ([\d.]+) L_normal", method)
    assert loss, "method.md no longer states stage I's loss"
    assert paper.anchor_weight == float(loss.group(1))
    assert paper.normal_weight == float(loss.group(2))
    assert paper.anchor_level == number(method, r"pulled to g = ([\d.]+)")
    assert paper.iterations == number(method, r"Stage I ([\d,]+) iterations")
    assert paper.lr_opacity == number(method, r"opacity lr ([\d.]+)")
    assert paper.resolution == 1.0  # "800x800 input": the sensor at its own size
    assert paper.opacity_reset_every > 0  # "standard 3DGS ... opacity reset"
    # a pixel without events is "no change" over every pixel: the method's plain sum
    assert paper.zero_events == "target" and paper.silent_weight is None
    # and nothing the method does not have
    ours = ("spread_weight", "alpha_weight", "binary_weight", "flatten_weight", "smooth_weight")
    ours += ("curvature_weight", "quiet_tv_weight", "background_tv_weight", "opacity_reg")
    assert all(getattr(paper, name) == 0 for name in ours)
    assert paper.background_first == 0 and paper.confine == 0 and not paper.refine_poses


def test_paper_is_the_methods_stage_two(method_summary):
    method = method_summary
    paper = cfg.material_preset("paper")
    loss = re.search(
        r"Stage II: L = L_event \+ ([\d.]+) L_rad \+ ([\d.]+) L_GW \+ ([\d.]+) L_TV, "
        r"beta = ([\d.]+), lambda_n = ([\d.]+)",
        method,
    )
    assert loss, "method.md no longer states stage II's loss"
    distill, anchor, tv, beta, lambda_n = (float(x) for x in loss.groups())
    assert (paper.distill_weight, paper.anchor_weight, paper.tv_weight) == (distill, anchor, tv)
    assert (paper.edge_beta, paper.tv_normal_weight) == (beta, lambda_n)
    assert paper.iterations == number(method, r"Stage II ([\d,]+) more")
    assert paper.lr_normals > 0  # the normals are learnt (fast freezes them)
    assert paper.normals_from == "planes"  # and the normals start as they always did


def test_the_simulators_threshold_is_the_methods(method_summary):
    c = number(method_summary, r"C = ([\d.]+)\.")
    assert SensorSpec().threshold_on == SensorSpec().threshold_off == c
