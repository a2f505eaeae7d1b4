"""The ChArUco board: its CLI form, OpenCV's board, the printable image, and the simulator's."""

import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from evcap.calib.board import DEFAULT_BOARD, Board, parse_board, write_board_image
from evcap.calib.intrinsics import detect_board
from evcap.errors import InputError
from evcap.sim.scene import load_scene

SCENE = Path(__file__).resolve().parents[2] / "sim" / "scenes" / "charuco_board.toml"


def scene_board_params(objects: list[dict]) -> tuple:
    (board,) = [o for o in objects if o.get("type", "charuco") == "charuco"]
    return (
        board["squares_x"],
        board["squares_y"],
        board["square_length"],
        board["marker_length"],
        board["dictionary"],
        board.get("legacy", False),
    )


def default_params() -> tuple:
    b = DEFAULT_BOARD
    return (b.cols, b.rows, b.square_m, b.marker_m, b.dictionary, b.legacy)


def test_default_board_is_the_simulated_scenes_board():
    scene = load_scene(SCENE)
    objects = [dict(o.params, type=o.kind) for o in scene.objects if o.kind == "charuco"]
    assert scene_board_params(objects) == default_params()


def test_default_board_is_the_scene_files_board():
    """The same check without ../shared: the scene file's own [[objects]] table."""
    with open(SCENE, "rb") as f:
        objects = tomllib.load(f)["objects"]
    assert scene_board_params([o for o in objects if o["type"] == "charuco"]) == default_params()


def test_describe_and_attributes():
    assert DEFAULT_BOARD.describe() == "ChArUco 7x5, 40 mm squares, 30 mm markers, DICT_4X4_50"
    assert DEFAULT_BOARD.markers == 17 and DEFAULT_BOARD.corners == 24
    attrs = DEFAULT_BOARD.to_attrs()
    assert attrs["board_cols"] == 7 and attrs["board_square_m"] == 0.04
    assert attrs["board_dictionary"] == "DICT_4X4_50" and attrs["board_legacy"] is False
    assert all(isinstance(v, int | float | str | bool) for v in attrs.values())
    legacy = Board(6, 6, 0.025, 0.0175, "DICT_5X5_100", legacy=True)
    assert legacy.describe() == (
        "ChArUco 6x6, 25 mm squares, 17.5 mm markers, DICT_5X5_100, legacy layout"
    )


def test_cv_board_and_legacy_layout():
    cb = DEFAULT_BOARD.cv()
    assert tuple(cb.getChessboardSize()) == (7, 5) and len(cb.getIds()) == 17
    assert cb.getSquareLength() == pytest.approx(0.04) and not cb.getLegacyPattern()
    # the legacy layout differs only for an even number of rows
    new, old = Board(6, 6, 0.04, 0.03, "DICT_4X4_50"), Board(6, 6, 0.04, 0.03, "DICT_4X4_50", True)
    assert old.cv().getLegacyPattern()
    assert (new.cv().generateImage((240, 240)) != old.cv().generateImage((240, 240))).any()


@pytest.mark.parametrize(
    "spec, board",
    [
        ("charuco:7x5:0.04:0.03:DICT_4X4_50", DEFAULT_BOARD),
        ("charuco:7x5:0.04:0.03:dict_4x4_50", DEFAULT_BOARD),
        (" CharUco:7X5:4e-2:0.030:DICT_4X4_50 ", DEFAULT_BOARD),
        (
            "charuco:6x8:0.025:0.018:DICT_5X5_100:legacy",
            Board(6, 8, 0.025, 0.018, "DICT_5X5_100", True),
        ),
        (
            "charuco:10x14:0.02:0.015:DICT_APRILTAG_36H11",
            Board(10, 14, 0.02, 0.015, "DICT_APRILTAG_36H11"),
        ),
    ],
)
def test_parse_board(spec, board):
    assert parse_board(spec) == board
    assert parse_board(board.spec()) == board


@pytest.mark.parametrize(
    "spec, what",
    [
        ("charuco:7x5:0.04:0.03:DICT_4X4_51", "unknown dictionary 'DICT_4X4_51'"),
        ("charuco:7x5:0.04:0.04:DICT_4X4_50", "must be smaller than the square"),
        ("charuco:7x5:0.03:0.04:DICT_4X4_50", "must be smaller than the square"),
        ("charuco:7x5:0:0.03:DICT_4X4_50", "must be positive"),
        ("charuco:7x5:0.04:-0.03:DICT_4X4_50", "must be positive"),
        ("charuco:7x5:nan:0.03:DICT_4X4_50", "must be positive"),
        ("charuco:7x5:inf:0.03:DICT_4X4_50", "must be positive"),
        ("charuco:1x5:0.04:0.03:DICT_4X4_50", "at least 2x2 squares, not 1x5"),
        ("charuco:11x10:0.04:0.03:DICT_4X4_50", "55 markers but DICT_4X4_50 holds only 50"),
        ("charuco:7x5:0.04:0.03", "4 ':'-separated fields"),
        ("charuco:7x5:0.04:0.03:DICT_4X4_50:old", "the last field must be 'legacy'"),
        ("charuco:7by5:0.04:0.03:DICT_4X4_50", "is not COLSxROWS"),
        ("charuco:7x5:4cm:3cm:DICT_4X4_50", "are not numbers"),
        ("aruco:7x5:0.04:0.03:DICT_4X4_50", "must start with 'charuco:'"),
        ("", "must start with 'charuco:'"),
    ],
)
def test_bad_board_specs(spec, what):
    with pytest.raises(InputError) as e:
        parse_board(spec)
    message = str(e.value)
    assert what in message
    assert "expected charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT" in message and "\n" not in message


def test_board_image_prints_at_the_boards_size(tmp_path):
    path = tmp_path / "board.png"
    assert write_board_image(DEFAULT_BOARD, path, dpi=300) == pytest.approx((280.0, 200.0))
    with Image.open(path) as png:
        dpi = png.info["dpi"]
        page = np.asarray(png.convert("L"))
    # a square is a whole number of pixels: 472 at 300 dpi, the file's resolution following
    assert dpi[0] == pytest.approx(300, rel=2e-3) and dpi[0] == pytest.approx(dpi[1])
    assert 472 / dpi[0] * 25.4 == pytest.approx(40.0, abs=0.01)
    rows, cols = np.nonzero(page < 128)
    top, left = rows.min(), cols.min()
    # the squares: 7 x 472 by 5 x 472 pixels inside a white margin, the caption under them
    assert top > 0 and left > 0 and rows.max() < page.shape[0] - 1
    assert (page[top : top + 5 * 472, left + 7 * 472 + 2 :] > 128).all()
    assert (page[top + 5 * 472 + 2 :] < 128).any()
    # it is the board: every corner is found (at a camera's scale)
    small = cv2.resize(page, None, fx=0.1, fy=0.1, interpolation=cv2.INTER_AREA)
    _, ids = detect_board(small, DEFAULT_BOARD)
    assert len(ids) == DEFAULT_BOARD.corners


def test_board_image_at_another_dpi(tmp_path):
    board = Board(5, 4, 0.03, 0.022, "DICT_6X6_50")
    size = write_board_image(board, tmp_path / "b.png", dpi=150)
    assert size == pytest.approx((150.0, 120.0))
    with Image.open(tmp_path / "b.png") as png:
        assert png.info["dpi"][0] == pytest.approx(150, rel=5e-3)


def test_board_image_errors(tmp_path):
    with pytest.raises(InputError, match="cannot write the board image"):
        write_board_image(DEFAULT_BOARD, tmp_path / "missing" / "board.png")
    with pytest.raises(InputError, match="too coarse"):
        write_board_image(DEFAULT_BOARD, tmp_path / "b.png", dpi=5)
    with pytest.raises(InputError, match="dpi must be positive"):
        write_board_image(DEFAULT_BOARD, tmp_path / "b.png", dpi=0)
