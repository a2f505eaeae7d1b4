"""The ChArUco calibration board: its definition, the CLI form that names it, a printable image.

A board is ``cols`` x ``rows`` chessboard squares with an ArUco marker in every white square;
its inner corners, identified by the markers around them, are what calibration measures. The
CLI names a board as ``charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT[:legacy]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from evcap.errors import InputError

BOARD_FORM = (
    "charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT[:legacy], e.g. charuco:7x5:0.04:0.03:DICT_4X4_50"
)
"""The CLI form of a board, as error messages show it."""

_DICTIONARIES = {n: getattr(cv2.aruco, n) for n in dir(cv2.aruco) if n.startswith("DICT_")}
_MM_PER_INCH = 25.4


def _mm(metres: float) -> str:
    return f"{metres * 1000:.4g}"


@dataclass(frozen=True)
class Board:
    """A ChArUco board. Construction checks it (InputError)."""

    cols: int  # squares across (OpenCV's size[0], x)
    rows: int  # squares down (OpenCV's size[1], y)
    square_m: float  # side of a chessboard square, metres
    marker_m: float  # side of an ArUco marker (black border included), metres; < square_m
    dictionary: str  # OpenCV's predefined dictionary, e.g. "DICT_4X4_50"
    legacy: bool = False  # OpenCV's layout before 4.6 for an even row count (setLegacyPattern)

    def __post_init__(self) -> None:
        if self.dictionary not in _DICTIONARIES:
            raise InputError(f"unknown dictionary {self.dictionary!r} (OpenCV's DICT_... names)")
        if self.cols < 2 or self.rows < 2:
            raise InputError(f"a board needs at least 2x2 squares, not {self.cols}x{self.rows}")
        if not (0 < self.square_m < math.inf and 0 < self.marker_m < math.inf):
            raise InputError(
                f"square and marker sizes must be positive (metres), not {self.square_m} and "
                f"{self.marker_m}"
            )
        if self.marker_m >= self.square_m:
            raise InputError(
                f"the marker ({self.marker_m} m) must be smaller than the square "
                f"({self.square_m} m)"
            )
        capacity = self.cv_dictionary().bytesList.shape[0]
        if self.markers > capacity:
            raise InputError(
                f"a {self.cols}x{self.rows} board has {self.markers} markers but "
                f"{self.dictionary} holds only {capacity}"
            )

    @property
    def markers(self) -> int:
        """How many markers the board carries (one per white square)."""
        return self.cols * self.rows // 2

    @property
    def corners(self) -> int:
        """How many inner (ChArUco) corners the board has."""
        return (self.cols - 1) * (self.rows - 1)

    def cv_dictionary(self) -> cv2.aruco.Dictionary:
        return cv2.aruco.getPredefinedDictionary(_DICTIONARIES[self.dictionary])

    def cv(self) -> cv2.aruco.CharucoBoard:
        """The board as OpenCV's CharucoBoard."""
        board = cv2.aruco.CharucoBoard(
            (self.cols, self.rows), self.square_m, self.marker_m, self.cv_dictionary()
        )
        if self.legacy:
            board.setLegacyPattern(True)
        return board

    def describe(self) -> str:
        """A short description, e.g. 'ChArUco 7x5, 40 mm squares, 30 mm markers, DICT_4X4_50'."""
        legacy = ", legacy layout" if self.legacy else ""
        return (
            f"ChArUco {self.cols}x{self.rows}, {_mm(self.square_m)} mm squares, "
            f"{_mm(self.marker_m)} mm markers, {self.dictionary}{legacy}"
        )

    def spec(self) -> str:
        """The CLI form that parse_board reads back."""
        legacy = ":legacy" if self.legacy else ""
        return (
            f"charuco:{self.cols}x{self.rows}:{self.square_m:g}:{self.marker_m:g}:"
            f"{self.dictionary}{legacy}"
        )

    def to_attrs(self) -> dict[str, object]:
        """The board as plain values, for HDF5 attributes."""
        return {
            "board": "charuco",
            "board_cols": int(self.cols),
            "board_rows": int(self.rows),
            "board_square_m": float(self.square_m),
            "board_marker_m": float(self.marker_m),
            "board_dictionary": self.dictionary,
            "board_legacy": bool(self.legacy),
        }


DEFAULT_BOARD = Board(7, 5, 0.04, 0.03, "DICT_4X4_50")
"""The board of the simulator's charuco_board scene (sim/scenes/charuco_board.toml)."""


def parse_board(spec: str) -> Board:
    """The board named by ``charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT[:legacy]``."""

    def bad(what: str) -> InputError:
        return InputError(f"bad board {spec!r}: {what}; expected {BOARD_FORM}")

    parts = spec.strip().split(":")
    if parts[0].lower() != "charuco":
        raise bad("it must start with 'charuco:'")
    if len(parts) not in (5, 6):
        raise bad(f"{len(parts)} ':'-separated fields, not 5 (or 6 with legacy)")
    legacy = len(parts) == 6
    if legacy and parts[5].lower() != "legacy":
        raise bad(f"the last field must be 'legacy', not {parts[5]!r}")
    size = parts[1].lower().split("x")
    try:
        cols, rows = (int(v) for v in size)
    except ValueError:
        raise bad(f"the size {parts[1]!r} is not COLSxROWS (squares)") from None
    try:
        square, marker = float(parts[2]), float(parts[3])
    except ValueError:
        raise bad(f"the sizes {parts[2]!r}, {parts[3]!r} are not numbers (metres)") from None
    dictionary = parts[4].upper()
    try:
        return Board(cols, rows, square, marker, dictionary, legacy)
    except InputError as e:
        raise bad(str(e)) from None


def write_board_image(board: Board, path: str | Path, dpi: int = 300) -> tuple[float, float]:
    """Write a printable PNG of ``board``: white margins, a caption with its description and
    printed size, and ``dpi`` as the file's physical resolution. Returns the board's
    (width_mm, height_mm)."""
    from PIL import Image, ImageDraw, ImageFont

    if not dpi > 0:
        raise InputError(f"dpi must be positive, not {dpi}")
    # A square must be a whole number of pixels; the resolution written into the file is moved
    # by that rounding (under 0.5 px a square) so that printing at 100 % gives square_m exactly.
    px_square = round(board.square_m / (_MM_PER_INCH / 1000) * dpi)
    bits = board.cv_dictionary().markerSize
    if px_square * board.marker_m / board.square_m < 2 * (bits + 2):
        raise InputError(
            f"{dpi} dpi is too coarse for {board.describe()}: a marker would be under "
            f"{2 * (bits + 2)} px"
        )
    dpi_exact = px_square * _MM_PER_INCH / 1000 / board.square_m
    width, height = board.cols * px_square, board.rows * px_square
    width_mm, height_mm = board.cols * board.square_m * 1000, board.rows * board.square_m * 1000
    pattern = board.cv().generateImage((width, height), marginSize=0, borderBits=1)

    margin = px_square // 2
    text_px = max(12, round(3.0 / _MM_PER_INCH * dpi))  # 3 mm high letters
    caption = (
        f"{board.describe()}; print at 100 %: {width_mm:.4g} x {height_mm:.4g} mm ({board.spec()})"
    )
    font = ImageFont.load_default(size=text_px)
    probe = ImageDraw.Draw(Image.new("L", (1, 1)))
    left, top, right, bottom = probe.textbbox((0, 0), caption, font=font)
    page_w = max(width + 2 * margin, right - left + 2 * margin)
    page_h = height + 2 * margin + (bottom - top) + margin
    page = np.full((page_h, page_w), 255, np.uint8)
    x0 = (page_w - width) // 2
    page[margin : margin + height, x0 : x0 + width] = pattern
    image = Image.fromarray(page)
    ImageDraw.Draw(image).text(
        ((page_w - (right - left)) // 2 - left, margin + height + margin // 2 - top),
        caption,
        fill=0,
        font=font,
    )
    try:
        image.save(Path(path), format="PNG", dpi=(dpi_exact, dpi_exact))
    except OSError as e:
        raise InputError(f"cannot write the board image {path}: {e.strerror or e}") from None
    return width_mm, height_mm
