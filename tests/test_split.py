"""bench/split.toml: settings are chosen on the tuning set, figures reported on another; each
preset says what it was tuned on (recon.presets.TUNED_ON), and none names what is reported."""

import tomllib
from pathlib import Path

import pytest

from evcap.recon.presets import MATERIAL_PRESETS, PRESETS, TUNED_ON, TunedOn

SPLIT = Path(__file__).parents[1] / "bench" / "split.toml"


def split() -> dict:
    return tomllib.loads(SPLIT.read_text())


def reported_in(tuned: TunedOn, split: dict) -> list[str]:
    """What of ``tuned`` the split reports: its seeds and scenes among the reporting ones."""
    reporting = split["reporting"]
    found = [f"seed {s}" for s in tuned.seeds if s in reporting["seeds"]]
    found += [f"scene {s}" for s in tuned.scenes if s in reporting["scenes"]]
    return found


def test_the_split_keeps_tuning_and_reporting_apart():
    s = split()
    assert not set(s["tuning"]["seeds"]) & set(s["reporting"]["seeds"])
    assert not set(s["tuning"]["scenes"]) & set(s["reporting"]["scenes"])
    assert s["reporting"]["seeds"] == [0, 1, 2]


def test_every_preset_says_what_it_was_tuned_on_and_none_names_a_reported_seed():
    s = split()
    assert set(TUNED_ON) == set(PRESETS) == set(MATERIAL_PRESETS)
    for name, tuned in TUNED_ON.items():
        assert tuned.note, name
        assert reported_in(tuned, s) == [], name
        assert set(tuned.scenes) <= set(s["tuning"]["scenes"]), name


@pytest.mark.parametrize(
    "tuned, found",
    [
        (TunedOn(("demo-scene",), (0, 3), "seed 0 among them"), ["seed 0"]),
        (
            TunedOn(("nerf-synthetic-mic",), (5,), "the reported scene"),
            ["scene nerf-synthetic-mic"],
        ),
        (TunedOn(("single_object",), (5, 10), "tuning seeds only"), []),
    ],
)
def test_a_preset_tuned_on_a_reporting_seed_or_scene_is_caught(tuned, found):
    assert reported_in(tuned, split()) == found
