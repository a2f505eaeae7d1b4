"""The settings by dotted name (recon/settings.py), the options record (recon/options.py) and the
command line's flags that make one (app/reconstruct_flags.py)."""

import argparse
import dataclasses

import pytest

from evcap.app.reconstruct_flags import add_reconstruct_arguments, options_from, show_settings
from evcap.errors import InputError
from evcap.recon.options import ReconstructOptions, read_settings_file
from evcap.recon.presets import ReconstructionSettings, preset
from evcap.recon.settings import NONE, describe, field_docs, parse_assignments, to_dict
from evcap.records import ReconstructionFolder


def configs(config):
    yield config
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            yield from configs(value)


def test_every_setting_says_what_it_is():
    settings = preset("fast")
    for config in configs(settings):
        docs = field_docs(type(config))
        missing = [f.name for f in dataclasses.fields(config) if not docs.get(f.name)]
        assert not missing, f"{type(config).__name__}: {missing} have no docstring"
    assert all(doc for _, _, doc in describe(settings))


def test_no_config_has_more_than_twenty_settings_of_its_own():
    for config in configs(preset("paper")):
        assert len(dataclasses.fields(config)) <= 20, type(config).__name__


def test_a_setting_is_replaced_by_its_dotted_name_and_checked():
    s = preset("tiny", {"stage1.densify.grad_threshold": 3e-4, "stage2.edges.frames": 8})
    assert s.stage1.densify.grad_threshold == 3e-4 and s.stage2.edges.frames == 8
    assert s.stage1.densify.every == preset("tiny").stage1.densify.every  # the rest kept
    assert preset("tiny", {"stage1.resolution": 1}).stage1.resolution == 1.0  # an int as float
    bad = [
        ({"densify.grad_threshold": 1e-4}, "did you mean stage1.densify.grad_threshold"),
        ({"stage1.densify.gradient": 1e-4}, "unknown setting 'stage1.densify.gradient'"),
        ({"stage1.iterations": 2.5}, "stage1.iterations = 2.5: expected int"),
        ({"stage1.event_loss.zero_events": "never"}, "expected 'target', 'bound'"),
        ({"stage1.densify": 3}, "is a group of settings"),
        ({"stage1.iterations": 0}, "at least 1"),
        ({"stage1.background.known": (1.0, 0.0, 1.0)}, "three numbers above 0"),
    ]
    for overrides, message in bad:
        with pytest.raises(InputError, match=message):
            preset("tiny", overrides)


def test_assignments_are_read_as_toml_values():
    assert parse_assignments(["a.b=2e-4", "c=true", "d=bound", 'e="x"', "f=[1, 1, 1]"]) == {
        "a.b": 2e-4,
        "c": True,
        "d": "bound",
        "e": "x",
        "f": [1, 1, 1],
    }
    with pytest.raises(InputError, match="expected NAME=VALUE"):
        parse_assignments(["densify.every"])


def test_a_reconstructions_config_is_a_settings_file_that_gives_its_settings(tmp_path):
    """config.toml as a reconstruction writes it, read back with --settings: the same
    settings (its [reconstruct] table, how the run was asked for, left out)."""
    for settings in (
        preset("small", {"stage1.background.known": (1.0, 1.0, 1.0)}),
        preset("paper"),  # its event loss's silent_weight is None
    ):
        folder = ReconstructionFolder(tmp_path)
        sections = {"reconstruct": {"preset": "small", "session": "s.h5"}}
        folder.write_config(sections | to_dict(settings, NONE))
        read = read_settings_file(folder.config)
        assert preset("fast", read) == settings
    with pytest.raises(InputError, match="no such settings file"):
        read_settings_file(tmp_path / "none.toml")
    (tmp_path / "bad.toml").write_text("[stage1\n")
    with pytest.raises(InputError, match="not a TOML file"):
        read_settings_file(tmp_path / "bad.toml")


def test_options_the_stages_run_do_not_read_are_refused():
    cases = [
        ({"stage": "material", "settings": {"stage1.iterations": 5}}, "stage1.iterations"),
        ({"stage": "material", "write_poses": True}, "--write-poses"),
        ({"stage": "radiance", "settings": {"stage2.iterations": 5}}, "stage2.iterations"),
        ({"stage": "radiance", "ablate": ("tv",)}, "--without"),
        ({"stage": "radiance", "relight": "sky.hdr"}, "--relight"),
        ({"preset": "huge"}, "unknown preset 'huge'"),
        ({"resume": "maybe"}, "unknown resume"),
        ({"ablate": ("light",)}, "unknown ablation"),
    ]
    for fields, message in cases:
        with pytest.raises(InputError, match=message):
            ReconstructOptions(**fields)
    ok = ReconstructOptions(stage="material", settings={"stage2.iterations": 5})
    assert ok.settings == (("stage2.iterations", 5),)


def parse(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_reconstruct_arguments(p)
    return p.parse_args(argv)


def test_the_flags_make_the_options_record(tmp_path):
    (tmp_path / "s.toml").write_text("[stage1.densify]\nevery = 20\n[stage1]\niterations = 9\n")
    args = parse(
        "--preset=tiny",
        f"--settings={tmp_path / 's.toml'}",
        "--set=stage1.iterations=12",
        "--noise-filter=5",
        "--refractory-bound",
        "--without=visibility",
        "--without=edge-tv",
        *("--bounds", "-1", "-1", "0", "1", "1", "2"),
    )
    options = options_from(args, stage="all")
    resolved = options.resolved()
    assert resolved.stage1.iterations == 12  # --set over the file
    assert resolved.stage1.densify.every == 20
    assert resolved.stage1.windows.noise_filter_ms == 5.0
    assert resolved.stage1.windows.refractory_bound
    assert resolved.stage2.visibility == "off" and options.ablate == ("tv",)
    assert "stage1.densify.every = 20" in show_settings(options)
    assert resolved.stage1.densify.bounds == (-1, -1, 0, 1, 1, 2)
    with pytest.raises(InputError, match=r"--bounds: each of the max corner .* must exceed"):
        options_from(parse("--bounds", "1", "-1", "0", "1", "1", "2"))
    with pytest.raises(InputError, match=r"stage1.densify.bounds is a box"):
        options_from(parse("--set=stage1.densify.bounds=[1, 2, 3]")).resolved()
    with pytest.raises(InputError, match="stage1.iterations: given both"):
        options_from(parse("--iterations=3", "--set=stage1.iterations=4"))
    with pytest.raises(InputError, match="--visibility and --without visibility"):
        options_from(parse("--visibility=on", "--without=visibility"))
    with pytest.raises(InputError, match="^--iterations [(]stage1.iterations[)]: stage I's"):
        options_from(parse("--iterations=3"), stage="material")


def test_the_root_names_both_stages():
    assert [f.name for f in dataclasses.fields(ReconstructionSettings)] == ["stage1", "stage2"]


def test_settings_are_checked_as_they_end_not_one_at_a_time():
    """fast starts on the events; moving that share to structure from motion's points passes
    through no state its checks refuse (each share alone would add up to more than 1)."""
    settings = preset("fast", {"stage1.init.on_points": 1.0, "stage1.init.on_events": 0.0})
    assert (settings.stage1.init.on_points, settings.stage1.init.on_events) == (1.0, 0.0)
    with pytest.raises(InputError, match="at most 1"):
        preset("fast", {"stage1.init.on_points": 1.0})
