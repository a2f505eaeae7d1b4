"""`evcap report`: the page of a small fake reconstruction folder and a handmade session."""

import base64
import dataclasses
import json
import re
import shutil
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from evcap.errors import InputError
from evcap.events import Events
from evcap.recon.material.stage import MaterialLog
from evcap.recon.radiance.stage import StepLog
from evcap.records import TruthViews
from evcap.report.html import SECTIONS, write_report
from evcap.report.images import colormap, gray_image, normal_image, png_data_uri
from evcap.report.svg import Series, Track, line_plot, nice_ticks, trajectory_views
from evcap.session import SensorInfo, SessionWriter, write_group

W, H = 40, 30


def look_at(centre: np.ndarray) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes, world z up) at ``centre`` looking at the origin."""
    forward = -centre / np.linalg.norm(centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, np.cross(forward, right), forward], 1)
    T[:3, 3] = centre
    return T


def path_poses(t_us: np.ndarray) -> np.ndarray:
    a = t_us / 1e6 * 2.0
    centres = np.stack([2 * np.cos(a), 2 * np.sin(a), 0.5 + 0.5 * a], 1)
    return np.stack([look_at(c) for c in centres])


def make_session(path: Path) -> Path:
    """0.3 s of a bar sweeping right (ON at its leading edge, OFF at its trailing edge),
    poses estimated at an arbitrary scale, the truth and a measured calibration."""
    xs, ys, ts, ps = [], [], [], []
    for ms in range(300):
        col = ms * (W - 4) // 300
        for row in range(H):
            for x, p in ((col + 3, 1), (col, 0)):
                xs.append(x)
                ys.append(row)
                ts.append(ms * 1000 + row * 10)
                ps.append(p)
    with SessionWriter(path, SensorInfo("simulated", W, H, "RGBG")) as w:
        w.append_events(Events(xs, ys, ts, ps, W, H, "RGBG"))
    t = np.arange(0, 300_001, 10_000, dtype=np.int64)
    truth = path_poses(t)
    # the estimate: the truth moved by a similarity, as structure from motion leaves it
    c, s = np.cos(0.5), np.sin(0.5)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    estimate = truth.copy()
    estimate[:, :3, :3] = R @ truth[:, :3, :3]
    estimate[:, :3, 3] = 0.3 * truth[:, :3, 3] @ R.T + [1.0, -2.0, 0.5]
    write_group(
        path,
        "poses",
        {"t": t, "T_world_cam": estimate},
        {"source": "evcap poses (test)", "scale": "arbitrary (structure from motion)"},
    )
    rng = np.random.default_rng(0)
    test_T = path_poses(np.array([50_000, 200_000]))
    depth = np.full((2, H, W), 2.0, np.float32)
    depth[:, :, :5] = 0  # no surface
    normal = np.zeros((2, H, W, 3), np.float32)
    normal[..., 2] = -1.0
    write_group(
        path,
        "gt",
        {
            "t": t,
            "T_world_cam": truth,
            "test_T_world_cam": test_T,
            "test_radiance": rng.uniform(0, 1, (2, H, W, 3)).astype(np.float32),
            "test_depth": depth,
            "test_normal": normal,
            "test_base_color": rng.uniform(0, 1, (2, H, W, 3)).astype(np.float32),
            "test_roughness": np.full((2, H, W), 0.4, np.float32),
        },
        {"source": "test"},
    )
    hot = np.zeros((H, W), np.uint8)
    hot[5, 7] = hot[20, 30] = 1
    write_group(
        path,
        "calibration",
        {
            "K": np.array([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]]),
            "dist": np.array([-0.1, 0.01, 0.0, 0.0]),
            "threshold_on": rng.normal(0.2, 0.02, (H, W)).astype(np.float32),
            "threshold_off": rng.normal(0.25, 0.02, (H, W)).astype(np.float32),
            "threshold_confidence": rng.uniform(0, 1, (H, W)).astype(np.float32),
            "hot_pixels": hot,
            "event_rate_hz": np.where(hot > 0, 300.0, 0.1).astype(np.float32),
        },
        {
            "source": "evcap calibrate",
            "distortion_model": "radtan",
            "rms_reprojection_px": float("nan"),
            "refractory_period_us": 100.0,
            "warnings": json.dumps(["recorded under other biases"]),
        },
    )
    return path


def make_reconstruction(out: Path, session: Path) -> Path:
    """What `evcap reconstruct` leaves, small: settings, metrics (one NaN, one null) with the
    training logs, the views' npz and PNGs, the light and relit views."""
    (out / "renders" / "material").mkdir(parents=True)
    (out / "renders" / "relit").mkdir()
    (out / "config.toml").write_text(
        f'[reconstruct]\nsession = "{session}"\nstage = "all"\npreset = "tiny"\n\n'
        "[stage2.edges]\nslice_ms = 10.0\n"
    )
    metrics = {
        "object_psnr_gain": 19.25,
        "object_psnr_constant": 17.0,
        "render_psnr": float("nan"),
        "render_psnr_gain": 21.5,
        "lpips": None,
        "gaussians": 1200,
        "effects": {"visibility": False, "tv": True},
        "views": "held-out test views",
        "history": [
            {"step": 10, "seconds": 1.0, "render_psnr_gain": 15.0, "render_psnr": 12.0},
            {"step": 20, "seconds": 2.0, "render_psnr_gain": float("nan"), "render_psnr": 13.0},
            {"step": 30, "seconds": 3.0, "render_psnr_gain": 19.0, "render_psnr": 14.0, "views": 2},
        ],
    }
    log = [StepLog(s, 1 / s, 0.8 / s, 0.01, 0.1, 500, s * 0.1) for s in range(10, 60, 10)]
    mlog = [MaterialLog(s, 0.3, 0.2, 0.05, 0.01, 0.1, s * 0.2) for s in (10, 20)]
    metrics["training_log"] = {
        "radiance": [vars(x) for x in log],
        "material": [dataclasses.asdict(x) for x in mlog],
    }
    (out / "metrics.json").write_text(json.dumps(metrics))  # NaN as JSON's NaN token
    rng = np.random.default_rng(1)
    views = {
        "radiance": rng.uniform(0, 1, (2, H, W, 3)).astype(np.float32),
        "depth": np.full((2, H, W), 1.9, np.float32),
        "normal": np.zeros((2, H, W, 3), np.float32),
        "alpha": np.ones((2, H, W), np.float32),
    }
    views["depth"][0, 0, 0] = np.nan  # no crash on a broken pixel
    np.savez_compressed(out / "renders" / "test.npz", **views)
    views["base_color"] = rng.uniform(0, 1, (2, H, W, 3)).astype(np.float32)
    views["roughness"] = np.full((2, H, W), np.inf, np.float32)
    np.savez_compressed(out / "renders" / "material" / "test.npz", **views)
    image = (rng.uniform(0, 255, (H, W, 3))).astype(np.uint8)
    for name in ("environment.png", "renders/relit/test_000.png", "renders/relit/environment.png"):
        cv2.imwrite(str(out / name), image)
    return out


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    return make_session(tmp_path_factory.mktemp("session") / "s.h5")


@pytest.fixture(scope="module")
def page(session, tmp_path_factory) -> tuple[Path, str]:
    out = make_reconstruction(tmp_path_factory.mktemp("recon") / "out", session)
    path = write_report(out)
    return path, path.read_text()


def test_writes_every_section(page):
    path, text = page
    assert path.name == "report.html" and path.exists()
    for k, (_, title) in enumerate(SECTIONS, start=1):
        assert f"<h2>{k}. {title}</h2>" in text
    assert "<svg" in text
    # it opens with the recovered object beside the truth; the figures after, then the making
    where = {key: text.index(f'<section id="{key}">') for key, _ in SECTIONS}
    assert where["maps"] < where["relit"] < where["metrics"] < where["session"]


def test_is_self_contained(page):
    _, text = page
    for ref in ("http://", "https://", 'src="/', "src='/", "<script", "<link", "@import"):
        assert ref not in text
    sources = re.findall(r'<img src="([^"]*)"', text)
    assert len(sources) > 20
    assert all(s.startswith("data:image/png;base64,") for s in sources)
    png = base64.b64decode(sources[0].split(",", 1)[1])
    assert cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED) is not None


def test_shows_what_it_found(page):
    _, text = page
    assert "0.299 s" in text  # the session's duration, from evcap info's summary
    assert "2 hot pixels circled" in text
    assert "recorded under other biases" in text
    assert "poses, aligned (similarity)" in text  # the arbitrary scale was aligned away
    assert "rotation error" in text and "translation error" in text
    assert "edge map, motion-compensated" in text
    assert "<th>truth</th>" in text and "<th>base color</th>" in text
    assert "the new light (--relight)" in text
    assert "stage I: training loss" in text and "stage II: training loss" in text
    assert "stage I: PSNR on held-out views" in text
    assert "scored on its first 2 held-out views only" in text  # not the table's definition
    assert "nan" not in re.sub(r'src="[^"]*"', "", text).lower()


def test_the_first_screen_judges_the_object_against_the_bar(page):
    """Above the sections: the object's figures against the bar (evcap/recovered.py),
    the object beside what a constant color scores; a figure not measured is left out."""
    _, text = page
    top = text[: text.index('<section id="maps">')]
    assert "1 of 1 figures miss their bar." in top
    assert "19.2 dB after one gain against 17 dB for a constant color: +2.25 dB" in top
    assert "<td>&gt;= 3 dB</td><td><b>missed</b></td>" in top
    assert "silhouette IoU" not in top


def test_the_first_screen_says_when_the_object_is_recovered():
    from evcap.records import Figures, ReconstructionResult
    from evcap.report.html import _glance

    figures = Figures(
        silhouette_iou=0.93,
        radiance_normal_mae_deg=4.6,
        depth_rel_err=0.006,
        object_psnr_gain=27.2,
        object_psnr_constant=17.15,
        background_clear=0.987,
    )
    text = _glance(ReconstructionResult(figures=figures))
    assert "The object is recovered: every figure measured meets its bar." in text
    assert "missed" not in text and text.count("<td>met</td>") == 5
    assert _glance(ReconstructionResult()) == ""  # no truth, no verdict


def test_nan_and_missing_metrics_show_na(page):
    _, text = page
    assert re.search(r"<td>render PSNR</td><td[^>]*>n/a</td>", text)
    assert re.search(r"<td>LPIPS \(AlexNet\)</td><td[^>]*>n/a</td>", text)
    assert re.search(r"<td>render PSNR, after one gain</td><td[^>]*>21.5</td>", text)
    assert re.search(r"<td>object PSNR, after one gain</td><td[^>]*>19.25</td>", text)
    assert "RMS reprojection error</th><td>n/a px" in text
    assert "visibility: off, tv: on" in text


def test_sections_without_data_say_so(session, tmp_path):
    bare = tmp_path / "bare.h5"
    shutil.copy(session, bare)
    with h5py.File(bare, "r+") as f:
        for name in ("calibration", "poses", "gt"):
            del f[name]
    out = tmp_path / "out"
    out.mkdir()
    (out / "config.toml").write_text(f'[reconstruct]\nsession = "{bare}"\n')
    text = write_report(out).read_text()
    assert "no /calibration group" in text
    assert "no /poses group" in text
    assert "There are no rendered views" in text
    assert "No environment map and no relit views" in text
    assert "metrics.json is not there" in text
    assert "No stage-I training log" in text


def test_a_corrupt_renders_file_is_named_and_the_page_kept(session, tmp_path):
    out = make_reconstruction(tmp_path / "out", session)
    (out / "renders" / "test.npz").write_bytes(b"PK\x03\x04 not a zip at all")
    text = write_report(out).read_text()
    assert "renders/test.npz is not readable" in text
    assert "stage II: material, shaded" in text  # the other stage's views still shown


def test_session_given_explicitly(session, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "metrics.json").write_text("{}")
    assert write_report(out, session).exists()


@pytest.mark.parametrize(
    ("setup", "session_arg", "message"),
    [
        ("missing", None, "no such folder"),
        ("empty", None, "not a reconstruction folder"),
        ("no-session", None, "--session"),
        ("gone", None, "gone.h5"),
        ("metrics", "nowhere.h5", "--session"),
    ],
)
def test_errors_say_what_to_do(tmp_path, setup, session_arg, message):
    out = tmp_path / "out"
    if setup != "missing":
        out.mkdir()
    if setup == "no-session":
        (out / "config.toml").write_text('[reconstruct]\nstage = "all"\n')
    if setup == "gone":
        (out / "config.toml").write_text(f'[reconstruct]\nsession = "{tmp_path / "gone.h5"}"\n')
    if setup == "metrics":
        (out / "metrics.json").write_text("{}")
    with pytest.raises(InputError, match=re.escape(message)) as e:
        write_report(out, session_arg)
    if setup == "gone":
        assert "--session" in str(e.value)


def test_svg_plots_skip_non_finite_values():
    assert np.allclose(nice_ticks(0, 1), [0, 0.2, 0.4, 0.6, 0.8, 1.0])
    assert np.allclose(nice_ticks(0.13, 0.91), [0, 0.2, 0.4, 0.6, 0.8, 1.0])
    assert nice_ticks(3, 3)  # an empty range still gets ticks
    x = np.array([0.0, 1.0, np.nan, 3.0, 4.0])
    y = np.array([1.0, np.inf, 2.0, 3.0, 0.0])
    svg = line_plot([Series("a", x, y)], title="t", x_label="x", y_label="y", log_y=True)
    assert "nan" not in svg.lower() and "inf" not in svg.lower()
    empty = line_plot([Series("a", [np.nan], [1.0])], title="t", x_label="x", y_label="y")
    assert "no finite values" in empty
    centres = np.array([[0.0, 0, 0], [1, 1, 1], [np.nan, 0, 0], [2, 0, 1]])
    views = trajectory_views([Track("p", centres, forward=np.tile([1.0, 0, 0], (4, 1)))])
    assert "nan" not in views.lower() and views.count("<svg") == 2


def test_images_mark_bad_values():
    rgb = colormap(np.array([[0.0, 1.0, np.nan]]), 0.0, 1.0)
    assert rgb.shape == (1, 3, 3) and tuple(rgb[0, 2]) == (255, 0, 255)
    assert not (rgb[0, 0] == rgb[0, 1]).all()
    n = normal_image(np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [np.nan, 0.0, 1.0]]]))
    assert tuple(n[0, 1]) == (128, 128, 0) and tuple(n[0, 2]) == (255, 0, 255)
    assert tuple(n[0, 0]) != tuple(n[0, 1])
    g = gray_image(np.array([[0.5, np.inf]]))
    assert tuple(g[0, 0]) == (128, 128, 128) and tuple(g[0, 1]) == (255, 0, 255)
    uri = png_data_uri(rgb)
    decoded = cv2.imdecode(np.frombuffer(base64.b64decode(uri.split(",")[1]), np.uint8), 1)
    assert (decoded[..., ::-1] == rgb).all()


def test_opens_in_a_headless_browser(page, screenshot):
    path, _ = page
    image = screenshot(path, 1200, 3000)
    assert image.shape[:2] == (3000, 1200)
    assert image.std() > 10  # not a blank page


def test_the_radiance_is_color_corrected_on_the_objects_pixels():
    from evcap.report.html import _view_table, srgb8

    rng = np.random.default_rng(0)
    truth = rng.uniform(0.1, 0.6, (1, H, W, 3)).astype(np.float32)
    depth = np.zeros((1, H, W), np.float32)
    depth[:, 5:25, 10:30] = 2.0  # the object
    # the render is the truth at half gain on the object, a flat wrong color around it: fitted
    # over the whole image the object would come out washed out
    render = np.where(depth[..., None] > 0, 0.5 * truth, 0.9).astype(np.float32)
    views = TruthViews(np.eye(4)[None], radiance=truth, depth=depth)
    table = _view_table(0, [("stage I", "test", {"radiance": render})], views)
    uri = re.search(r'src="data:image/png;base64,([^"]+)"', table).group(1)
    shown = cv2.imdecode(np.frombuffer(base64.b64decode(uri), np.uint8), cv2.IMREAD_COLOR)
    expected = srgb8(truth[0])[..., ::-1]  # OpenCV decodes BGR
    on = depth[0] > 0
    assert np.abs(shown[on].astype(int) - expected[on].astype(int)).max() <= 1
