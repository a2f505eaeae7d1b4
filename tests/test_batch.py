"""`evcap batch`: a manifest of three tiny recordings, one of them corrupt, in this process and
on a local Ray cluster (a head and one worker on the loopback address)."""

import csv
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from evcap.batch.manifest import read_manifest
from evcap.batch.run import run_batch
from evcap.errors import InputError, InputNotFoundError
from evcap.recon.options import ReconstructOptions
from evcap.sim.scene import load_scene
from evcap.sim.simulate import simulate

TINY = ReconstructOptions(preset="tiny")

STEPS = ("reconstruct", "report")
BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def collection(tiny_scene, tmp_path_factory) -> Path:
    """MANIFEST.toml beside a/ (two tiny simulated recordings) and broken.h5 (not HDF5)."""
    root = tmp_path_factory.mktemp("collection")
    (root / "a").mkdir()
    for name, seed in (("left", 3), ("right", 4)):
        simulate(load_scene(tiny_scene(seed=seed)), root / "a" / f"{name}.h5")
    (root / "broken.h5").write_bytes(b"not a session " * 100)
    (root / "MANIFEST.toml").write_text('[[group]]\nrecordings = ["a/*.h5", "broken.h5"]\n')
    return root / "MANIFEST.toml"


@pytest.fixture(scope="module")
def in_process(collection, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("in-process")
    run_batch(read_manifest(collection), out, steps=STEPS, options=TINY, use_ray=False)
    return out


def summary(out: Path) -> dict[str, dict]:
    return {r["name"]: r for r in json.loads((out / "summary.json").read_text())["recordings"]}


def test_two_done_and_the_corrupt_one_failed_with_its_message(in_process):
    rows = summary(in_process)
    assert [rows[n]["status"] for n in ("left", "right", "broken")] == ["done", "done", "failed"]
    assert "broken.h5" in rows["broken"]["error"] and "reconstruct" in rows["broken"]["error"]
    assert rows["broken"]["steps"]["report"]["status"] == "not run"
    for name in ("left", "right"):
        assert (in_process / name / "report.html").exists()
        assert rows[name]["figures"]["object_psnr_gain"] > 0
    with (in_process / "summary.csv").open() as f:
        table = {r["name"]: r for r in csv.DictReader(f)}
    assert table["broken"]["status"] == "failed" and float(table["left"]["object_psnr_gain"]) > 0
    page = (in_process / "index.html").read_text()
    assert 'href="left/report.html"' in page and "broken.h5" in page


def test_a_rerun_skips_what_is_done(collection, in_process):
    before = {n: (in_process / n / "report.html").stat().st_mtime_ns for n in ("left", "right")}
    rows = run_batch(
        read_manifest(collection), in_process, steps=STEPS, options=TINY, use_ray=False
    )
    statuses = {r.name: [s.status for s in r.steps.values()] for r in rows}
    assert statuses["left"] == statuses["right"] == ["done before", "done before"]
    assert statuses["broken"] == ["failed", "not run"]
    after = {n: (in_process / n / "report.html").stat().st_mtime_ns for n in ("left", "right")}
    assert after == before


def test_a_step_run_again_makes_those_after_it_again(collection, in_process, tmp_path):
    out = tmp_path / "again"
    shutil.copytree(in_process, out)
    shutil.rmtree(out / "left" / "reconstruction")
    rows = run_batch(read_manifest(collection), out, steps=STEPS, options=TINY, use_ray=False)
    left = next(r for r in rows if r.name == "left")
    assert [s.status for s in left.steps.values()] == ["done", "done"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# a cluster on the loopback address alone: no token (Ray makes one at its first start in the
# user's home, which a later head and worker in other folders did not agree on), no statistics
RAY_ENV = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "disabled"}


@pytest.fixture
def ray_cluster():
    """A Ray head and one worker node, each with one core, on 127.0.0.1 only."""
    pytest.importorskip("ray")
    port = free_port()
    # Ray's sockets live in its temp folder, whose path must stay short
    temp = tempfile.mkdtemp(prefix="ray", dir="/tmp")
    env = RAY_ENV
    common = ["--num-cpus=1", "--disable-usage-stats"]
    ray = str(BIN / "ray")
    head = [ray, "start", "--head", "--node-ip-address=127.0.0.1", f"--port={port}"]
    head += ["--include-dashboard=false", f"--temp-dir={temp}", *common]
    worker = [ray, "start", f"--address=127.0.0.1:{port}", "--node-ip-address=127.0.0.1"]
    try:
        for command in (head, [*worker, *common]):
            run = subprocess.run(command, env=env, capture_output=True, text=True, timeout=180)
            assert run.returncode == 0, f"{' '.join(command)}:\n{run.stdout}\n{run.stderr}"
        yield f"127.0.0.1:{port}"
    finally:
        subprocess.run([ray, "stop", "--force"], env=env, capture_output=True, timeout=120)
        shutil.rmtree(temp, ignore_errors=True)


def test_a_ray_cluster_gives_what_the_process_gives(collection, in_process, ray_cluster, tmp_path):
    out = tmp_path / "cluster"
    command = [str(BIN / "evcap"), "batch", str(collection), "-o", str(out)]
    command += ["--address", ray_cluster, "--preset", "tiny", "--steps", *STEPS]
    run = subprocess.run(command, capture_output=True, text=True, timeout=600, env=RAY_ENV)
    assert run.returncode == 1, run.stderr  # one recording failed
    assert "2 of 3 recordings done" in run.stdout
    assert "broken: failed" in run.stderr
    rows, expected = summary(out), summary(in_process)
    assert {n: r["status"] for n, r in rows.items()} == {
        n: r["status"] for n, r in expected.items()
    }
    assert rows["broken"]["error"] == expected["broken"]["error"]
    for name in ("left", "right"):
        assert rows[name]["figures"] == pytest.approx(expected[name]["figures"], rel=1e-6)
    # the rerun on the cluster skips the two done
    again = subprocess.run(command, capture_output=True, text=True, timeout=600, env=RAY_ENV)
    assert again.returncode == 1, again.stderr
    for name in ("left", "right"):
        steps = summary(out)[name]["steps"]
        assert {s["status"] for s in steps.values()} == {"done before"}


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "missing group"),
        ("[[group]]\nrecordings = []\n", "recordings must be a list"),
        ('[[group]]\nrecordings = ["nothing/*.h5"]\n', "no recording matches"),
        ('[[group]]\nrecordings = ["a/*.h5"]\ncalibration = "c.h5"\n', "c.h5 not found"),
        ('[[group]]\nrecordings = ["a/*.h5"]\nboard = 3\n', "board must be a string"),
        ('[[group]]\nrecording = ["a/*.h5"]\n', "missing recordings"),
    ],
)
def test_manifest_errors_name_the_problem(collection, tmp_path, text, message):
    path = collection.parent / "bad.toml"
    path.write_text(text)
    with pytest.raises((InputError, InputNotFoundError), match=message):
        read_manifest(path)


def test_recordings_named_alike_are_told_apart_by_their_folders(tmp_path):
    for folder in ("one", "two"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "vase.h5").write_bytes(b"")
    (tmp_path / "m.toml").write_text('[[group]]\nrecordings = ["*/vase.h5"]\n')
    assert [r.name for r in read_manifest(tmp_path / "m.toml").recordings] == [
        "one-vase",
        "two-vase",
    ]


def test_a_groups_calibration_is_applied_to_its_recordings(collection, tmp_path):
    """A calibration recording that holds its /calibration is applied as it is, to copies: the
    recordings themselves are only read."""
    import numpy as np

    from evcap.records import Calibration
    from evcap.session import Session

    board = tmp_path / "board.h5"
    shutil.copyfile(collection.parent / "a" / "left.h5", board)
    with Session.open(board) as s:
        w, h = s.sensor.width, s.sensor.height
    Calibration(w, h, "a test's", threshold_on=np.full((h, w), 0.33)).write(board)
    manifest = tmp_path / "m.toml"
    manifest.write_text(
        f'[[group]]\ncalibration = "board.h5"\nrecordings = ["{collection.parent}/a/*.h5"]\n'
    )
    out = tmp_path / "out"
    rows = run_batch(read_manifest(manifest), out, steps=("calibrate",), use_ray=False)
    assert [r.status for r in rows] == ["done", "done"]
    for name in ("left", "right"):
        with Session.open(out / name / "session.h5") as s:
            cal = Calibration.read(s)
        assert cal.source == "a test's" and np.all(cal.threshold_on == np.float32(0.33))
    with Session.open(collection.parent / "a" / "left.h5") as s:
        assert Calibration.read(s).source != "a test's"
    calibrations = json.loads((out / "summary.json").read_text())["calibrations"]
    assert [c["status"] for c in calibrations] == ["done"]


def test_ctrl_c_stops_cleanly_and_the_same_command_goes_on(
    collection, in_process, tmp_path, monkeypatch
):
    from evcap.batch.run import BatchInterrupted
    from evcap.pipeline import Pipeline

    out = tmp_path / "stopped"
    shutil.copytree(in_process, out)
    (out / "left" / "report.html").unlink()  # its report is made again, and Ctrl-C comes

    def interrupted(pipeline):
        raise KeyboardInterrupt

    monkeypatch.setattr(Pipeline, "_report", interrupted)
    with pytest.raises(BatchInterrupted, match="run the same command"):
        run_batch(read_manifest(collection), out, steps=STEPS, options=TINY, use_ray=False)
    left = summary(out)["left"]
    assert left["status"] == "stopped"
    assert left["steps"]["reconstruct"]["status"] == "done before"
    monkeypatch.undo()
    rows = run_batch(read_manifest(collection), out, steps=STEPS, options=TINY, use_ray=False)
    left = next(r for r in rows if r.name == "left")
    assert [s.status for s in left.steps.values()] == ["done before", "done"]
    assert (out / "left" / "report.html").exists()


def test_the_command_lines_settings_reach_every_recordings_stages(collection, tmp_path, capsys):
    """`evcap batch ... --set`: the options record carries them to each recording's
    reconstruction, as `evcap reconstruct` takes them."""
    from evcap.app.cli import main

    out = tmp_path / "out"
    argv = ["batch", str(collection), "-o", str(out), "--in-process", "--preset", "tiny"]
    argv += ["--steps", "reconstruct", "--set", "stage1.iterations=7", "--material-iterations=2"]
    assert main(argv) == 1  # broken.h5 fails, the others are done
    for name in ("left", "right"):
        metrics = json.loads((out / name / "reconstruction" / "metrics.json").read_text())
        assert (metrics["iterations"], metrics["material_iterations"]) == (7, 2)
    assert main([*argv, "--set", "stage1.densify.gradient=1"]) == 2
    assert "unknown setting 'stage1.densify.gradient'" in capsys.readouterr().err
