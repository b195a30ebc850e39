"""The calibration board: a ChArUco board described by its printed dimensions, and its detection.

A ChArUco board is a chessboard with ArUco markers in its white squares, so each detected corner
carries its id: a board partly out of view, tilted or near an edge still gives usable corners,
which is what a view plan covering the image corners and steep tilts needs. Detection is
OpenCV's `cv2.aruco.CharucoDetector` (4.7+). Blur is measured as the widest edge over eight
directions (contrast over the steepest gradient, in pixels): motion smears edges along one
direction only, and unlike the variance of the Laplacian the width neither depends on the board's
size in the image nor on pixel noise, so one threshold refuses blurred views at any distance.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from host.geometry.transforms import FloatArray

UInt8Image = npt.NDArray[np.uint8]

DICTIONARIES = {
    "DICT_4X4_50": cv2.aruco.DICT_4X4_50,
    "DICT_5X5_100": cv2.aruco.DICT_5X5_100,
    "DICT_6X6_250": cv2.aruco.DICT_6X6_250,
}
MIN_CORNERS = 12  # fewer corners than this constrain a view's pose too weakly to keep it
# A sharp rendered or well-focused edge measures 3.3-3.8 px with this estimator (the 0.8 px
# denoising blur and the 3x3 Sobel included); 2.5 px of motion during the exposure gives ~4.7.
MAX_EDGE_WIDTH_PX = 4.5
DENOISE_SIGMA_PX = 0.8
EDGE_DIRECTIONS = 8
GRADIENT_PERCENTILE = 99.5


@dataclass(frozen=True)
class BoardSpec:
    """Squares (cols, rows), their edge and the markers' edge in mm, the ArUco dictionary."""

    squares_x: int = 9
    squares_y: int = 7
    square_mm: float = 80.0
    marker_mm: float = 60.0
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self) -> None:
        if self.squares_x < 3 or self.squares_y < 3:
            raise ValueError(
                f"board: need at least 3x3 squares, got {self.squares_x}x{self.squares_y}"
            )
        if not 0.0 < self.marker_mm < self.square_mm:
            raise ValueError(
                f"board: marker_mm = {self.marker_mm} must lie in (0, square_mm = {self.square_mm})"
            )
        if self.dictionary not in DICTIONARIES:
            raise ValueError(f"board: dictionary {self.dictionary!r} not in {sorted(DICTIONARIES)}")

    def make(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board object (the simulator renders it, the detector finds it)."""
        d = cv2.aruco.getPredefinedDictionary(DICTIONARIES[self.dictionary])
        size = (self.squares_x, self.squares_y)
        return cv2.aruco.CharucoBoard(size, self.square_mm, self.marker_mm, d)

    @property
    def corner_count(self) -> int:
        """Inner corners of the chessboard."""
        return (self.squares_x - 1) * (self.squares_y - 1)

    @property
    def centre_mm(self) -> FloatArray:
        """The board's centre in its own frame (origin at the outer top-left corner)."""
        return np.array(
            [self.squares_x * self.square_mm / 2, self.squares_y * self.square_mm / 2, 0.0]
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain values for a report or a request."""
        return dict(vars(self))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BoardSpec:
        """From `to_dict` output; unknown keys fail with their names."""
        unknown = set(d) - set(vars(cls()))
        if unknown:
            raise ValueError(f"board: unknown keys {sorted(unknown)}")
        return cls(**d)


@dataclass(frozen=True)
class Detection:
    """Corners of one image: ids (N,), board points (N,3), pixels (N,2), edge width (px)."""

    ids: npt.NDArray[np.int32]
    object_points: FloatArray
    image_points: FloatArray
    edge_width_px: float

    @property
    def count(self) -> int:
        """Number of corners found."""
        return int(self.ids.size)

    @property
    def sharp(self) -> bool:
        """Edges narrow enough for the corners to be trusted."""
        return self.edge_width_px <= MAX_EDGE_WIDTH_PX


class BoardDetector:
    """Finds a board's ChArUco corners in images."""

    def __init__(self, spec: BoardSpec) -> None:
        self.spec = spec
        self.board = spec.make()
        self._detector = cv2.aruco.CharucoDetector(self.board)
        self._points = np.asarray(self.board.getChessboardCorners(), np.float64).reshape(-1, 3)

    def detect(self, image: UInt8Image) -> Detection | None:
        """The corners found (None when fewer than MIN_CORNERS)."""
        gray = np.asarray(
            cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image, np.uint8
        )
        corners, ids, _, _ = self._detector.detectBoard(gray)
        if ids is None or len(ids) < MIN_CORNERS:
            return None
        idx = np.asarray(ids, np.int32).ravel()
        uv = np.asarray(corners, np.float64).reshape(-1, 2)
        return Detection(idx, self._points[idx], uv, edge_width_px(gray, uv))


def edge_width_px(gray: UInt8Image, uv: FloatArray) -> float:
    """Widest edge over EDGE_DIRECTIONS inside the corners' bounding box, pixels."""
    lo = np.floor(uv.min(axis=0)).astype(int)
    hi = np.ceil(uv.max(axis=0)).astype(int) + 1
    h, w = gray.shape[:2]
    roi = gray[max(lo[1], 0) : min(hi[1], h), max(lo[0], 0) : min(hi[0], w)]
    if min(roi.shape[:2], default=0) < 8:
        return float("inf")
    smooth = cv2.GaussianBlur(roi.astype(np.float32), (0, 0), DENOISE_SIGMA_PX)
    contrast = float(np.percentile(smooth, 95) - np.percentile(smooth, 5))
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3) / 8.0  # grey levels per pixel
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    widths = []
    for a in np.linspace(0.0, np.pi, EDGE_DIRECTIONS, endpoint=False):
        steepest = float(
            np.percentile(np.abs(np.cos(a) * gx + np.sin(a) * gy), GRADIENT_PERCENTILE)
        )
        widths.append(contrast / steepest if steepest > 0 else float("inf"))
    return max(widths)
