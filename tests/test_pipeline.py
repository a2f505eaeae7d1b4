"""The pipeline's one rule for a rerun, its state file and its results, on steps that only
write a file each (the real steps run in tests/test_demo.py and tests/test_batch.py)."""

import json

import pytest

from evcap.errors import InputError
from evcap.pipeline import (
    Pipeline,
    PipelineInterrupted,
    Settings,
    StepDefinition,
    StepResult,
    Workspace,
)
from evcap.recon.options import ReconstructOptions


def pipeline(root, runs: list[str], settings=None, fail: str = "", stop: str = ""):
    """Three steps a, b, c, each making ROOT/NAME; ``runs`` records which ran."""
    p = Pipeline(Workspace(root), settings or Settings(), hint="start it over")

    def work(name: str):
        def run():
            runs.append(name)
            if name == fail:
                raise ValueError(f"{name} went wrong")
            if name == stop:
                return None
            (root / name).write_text(name)
            return f"made {name}", {"object_psnr_gain": 20.0}

        return run

    p.steps = [StepDefinition(n, work(n), (root / n).exists) for n in "abc"]
    return p


def test_a_rerun_skips_what_is_done_and_redoes_what_follows_a_step_run_again(tmp_path):
    runs: list[str] = []
    first = pipeline(tmp_path, runs).run()
    assert runs == ["a", "b", "c"] and [r.status for r in first] == ["done"] * 3
    state = json.loads((tmp_path / "pipeline.json").read_text())
    assert list(state["done"]) == ["a", "b", "c"]
    assert state["settings"]["reconstruct"]["preset"] == "fast"
    assert state["done"]["b"]["figures"] == {"object_psnr_gain": 20.0}

    runs.clear()
    again = pipeline(tmp_path, runs).run()
    assert runs == [] and [r.status for r in again] == ["done before"] * 3
    assert again[1].summary == "made b"

    (tmp_path / "b").unlink()  # its output gone: b runs again, and c after it
    runs.clear()
    pipeline(tmp_path, runs).run()
    assert runs == ["b", "c"]


def test_a_step_run_alone_unmarks_those_after_it(tmp_path):
    runs: list[str] = []
    pipeline(tmp_path, runs).run()
    (tmp_path / "a").unlink()
    p = pipeline(tmp_path, runs)
    assert p.attempt("a").status == "done"
    assert list(json.loads((tmp_path / "pipeline.json").read_text())["done"]) == ["a"]


def test_other_settings_and_a_damaged_state_are_refused(tmp_path):
    pipeline(tmp_path, []).run()
    with pytest.raises(InputError, match="--preset fast.*start it over"):
        pipeline(tmp_path, [], Settings(ReconstructOptions(preset="tiny"))).run()
    assert pipeline(tmp_path, [], Settings(cpus=2)).run()[0].status == "done before"
    (tmp_path / "pipeline.json").write_text("{")
    with pytest.raises(InputError, match="damaged; start it over"):
        pipeline(tmp_path, []).run()


def test_a_stopped_step_interrupts_the_run_and_keeps_those_before(tmp_path):
    runs: list[str] = []
    with pytest.raises(PipelineInterrupted, match="'b'"):
        pipeline(tmp_path, runs, stop="b").run()
    assert runs == ["a", "b"]
    assert list(json.loads((tmp_path / "pipeline.json").read_text())["done"]) == ["a"]


def test_run_step_turns_errors_into_results_and_waits_for_what_it_needs(tmp_path):
    p = pipeline(tmp_path, [], fail="a")
    failed = p.run_step("a")
    assert failed.status == "failed" and failed.error == "a went wrong" and not failed.ok
    skipped = p.run_step("b", before=failed)
    assert skipped.status == "not run" and skipped.error == "a failed"
    assert p.run_step("c", before=StepResult("b", "not run", error="a failed")).error == (
        "a failed"
    )
    with pytest.raises(ValueError, match="a went wrong"):
        pipeline(tmp_path, [], fail="a").run()  # the demo and the commands see the error
