"""Synthetic camera for the simulator: renders the true scene with the true optics.

Frames keep their ground truth (true T_w_c, true projected points). Model edges are subdivided
before projection so distortion bends them as a real lens would. The chessboard is ray-cast: each
pixel is undistorted once (cached per camera), intersected with the board plane and sampled from
a fine board texture, so corners carry the true distortion for calibration tests. A pixel shows
the mean of the board over its footprint, as a sensor's pixel integrates its area: the texture is
prefiltered by a box the size of a pixel's footprint on it (`_area_texture`) before the sample at
the pixel's centre, so boards far away or seen steeply do not alias. A
ChArUco board (an OpenCV `CharucoBoard`, the same object the installer's detector uses) is
ray-cast the same way, can sit in the hall behind the model, and can be smeared by the motion
during the exposure (the mean of renders along the path, as a sensor integrates). `FrameClock`
stamps frames as a camera does: at delivery, late by the readout and a jitter, unless triggered.
Deterministic for a given seed. Imports only the shared math in host.geometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from host.geometry.camera import CameraModel
from host.geometry.model import Wireframe
from host.geometry.transforms import FloatArray, interpolate_T, invert_T, transform_points

UInt8Image = npt.NDArray[np.uint8]

BACKGROUND_BGR = (110, 110, 110)
EDGE_BGR = (0, 200, 255)  # orange-yellow, distinct from the host overlay's green
EDGE_SUBDIVISIONS = 8  # pieces per model edge, so distortion curves them
NOISE_SIGMA_DN = 1.5  # Gaussian pixel noise, grey levels
TEXTURE_PX_PER_SQUARE = 256  # board texture resolution: 2-4 texels a pixel in the views planned
POINT_TEXTURE_PX_PER_SQUARE = 64  # ... of the point-sampled renderer (`area_sampled=False`)
FOOTPRINT_GRID_PX = 32  # a pixel's footprint on the texture is measured on this grid of pixels
FOOTPRINT_STEP_TEXELS = 0.05  # prefiltered textures are kept for footprints rounded to this
AREA_TEXTURES_KEPT = 8  # prefiltered textures cached (a still or slow rig reuses one)
BOARD_MARGIN_SQUARES = 1.0  # white border around the squares, in squares
TEXTURED_POINT_RADIUS_PX = 3
# Photogrammetry targets on the workpiece's feature points: a white dot in a black ring, drawn
# at a fixed size in pixels (they are small; a real target's size only changes its area).
TARGET_DOT_PX = 3.5
TARGET_RING_PX = 7.0
TARGET_DOT_BGR = (245, 245, 245)
TARGET_RING_BGR = (15, 15, 15)
_NO_MAP = np.empty((0, 0), np.float32)  # remap's second map: the first holds (x, y)
W_MIN = 1e-6  # a ray this near parallel to the board's plane meets it far beyond the texture
BLUR_SAMPLES = 9  # sub-exposure renders averaged into one blurred frame
NOISE_BANK_FRAMES = 2  # seeded noise drawn once, this many frames' worth (`_noisy`)
# A camera without a trigger stamps a frame when it arrives: readout plus transfer late
# (about 20 ms for 1280x1024 at 30 fps), with a millisecond of USB/driver jitter.
DELIVERY_S = 0.020
DELIVERY_JITTER_S = 0.001


@dataclass(frozen=True)
class SceneFrame:
    """A rendered frame and its ground truth."""

    image: UInt8Image
    T_w_c: FloatArray
    vertices_uv: FloatArray  # (N,2) true pixels of the model vertices, NaN if behind
    points_uv: FloatArray  # (P,2) true pixels of the textured points, NaN if behind


@dataclass(frozen=True)
class ChessboardFrame:
    """A rendered chessboard view and its ground truth."""

    image: UInt8Image
    T_c_b: FloatArray
    corners_uv: FloatArray  # (rows*cols, 2) inner corners in OpenCV's order, row-major
    visible: bool  # every inner corner inside the image and in front of the camera


@dataclass(frozen=True)
class BoardFrame:
    """A rendered ChArUco view and its ground truth."""

    image: UInt8Image
    T_c_b: FloatArray  # at the middle of the exposure
    corners_uv: FloatArray  # (N,2) true pixels of every ChArUco corner, by corner id
    in_view: npt.NDArray[np.bool_]  # (N,) corner in front of the camera and inside the image


@dataclass(frozen=True)
class PlacedBoard:
    """A ChArUco board fixed in the hall: the board and its pose T_w_b."""

    board: cv2.aruco.CharucoBoard
    T_w_b: FloatArray


@dataclass
class FrameClock:
    """Frame stamps as a camera gives them: exposure time, or delivery time plus jitter."""

    triggered: bool = False
    delivery_s: float = DELIVERY_S
    jitter_s: float = DELIVERY_JITTER_S
    seed: int = 0
    _rng: np.random.Generator = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def stamp_ns(self, exposure_ns: int) -> int:
        """The stamp the host sees for a frame exposed at `exposure_ns`."""
        if self.triggered:  # the trigger line's edge is the exposure, timed by the host
            return exposure_ns
        late_s = self.delivery_s + abs(float(self._rng.normal(0.0, self.jitter_s)))
        return exposure_ns + round(late_s * 1e9)


@dataclass
class SyntheticCamera:
    """Renders scenes and chessboards through a true camera model, seeded noise."""

    camera: CameraModel
    seed: int = 0
    noise_sigma_dn: float = NOISE_SIGMA_DN
    blur_samples: int = BLUR_SAMPLES
    # False: each pixel the texture at its centre's ray, as before area sampling (a coarser
    # texture, not prefiltered), kept for the corner-bias diagnostic and the test telling the two
    # apart
    area_sampled: bool = True
    _rng: np.random.Generator = field(init=False, repr=False)
    _rays: npt.NDArray[np.float32] | None = field(default=None, init=False, repr=False)
    # the last noiseless scene: (what it showed, its image), reused while nothing moved
    _still: tuple[tuple[Any, ...], UInt8Image] | None = field(default=None, init=False, repr=False)
    _bank: npt.NDArray[np.int16] | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def render_scene(
        self,
        T_w_c: FloatArray,
        model: Wireframe,
        T_w_p: FloatArray,
        textured_points_p: FloatArray | None = None,
        board: PlacedBoard | None = None,
        targets_p: FloatArray | None = None,
    ) -> SceneFrame:
        """Grey background (and a board in the hall), model edges (frame p), textured points,
        photogrammetry targets (frame p)."""
        T_c_p = invert_T(T_w_c) @ T_w_p
        pts = np.zeros((0, 3)) if textured_points_p is None else textured_points_p
        pts_uv, _ = self.camera.project(transform_points(T_c_p, pts))
        verts_uv, _ = self.camera.project(transform_points(T_c_p, model.vertices))
        # A rig at rest shows the same scene frame after frame: only the noise is new. (Not
        # with textured points: their colours are drawn from the noise's generator.)
        shown = (model, board, _key(targets_p), _key(T_w_c), _key(T_w_p))
        if textured_points_p is None and self._still is not None and _same(self._still[0], shown):
            img = self._still[1]
        else:
            img = self._draw_scene(T_w_c, T_c_p, model, pts_uv, board, targets_p)
            self._still = (shown, img) if textured_points_p is None else None
        noisy = self._noisy(img)
        noisy = noisy.copy() if noisy is img else noisy  # the kept image stays untouched
        return SceneFrame(noisy, np.array(T_w_c, dtype=np.float64), verts_uv, pts_uv)

    def _draw_scene(
        self, T_w_c: FloatArray, T_c_p: FloatArray, model: Wireframe, pts_uv: FloatArray,
        board: PlacedBoard | None, targets_p: FloatArray | None,
    ) -> UInt8Image:  # fmt: skip
        """The scene without noise."""
        if board is None:
            img = np.empty((self.camera.height, self.camera.width, 3), dtype=np.uint8)
            img[:] = BACKGROUND_BGR
        else:
            grey = self._cast_charuco(invert_T(T_w_c) @ board.T_w_b, board.board)
            img = np.asarray(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR), dtype=np.uint8)
        self._draw_edges(img, T_c_p, model)
        self._draw_points(img, pts_uv)
        if targets_p is not None:
            targets_uv, _ = self.camera.project(transform_points(T_c_p, targets_p))
            self._draw_targets(img, targets_uv)
        return img

    def render_chessboard(
        self, T_c_b: FloatArray, pattern: tuple[int, int], square_mm: float
    ) -> ChessboardFrame:
        """A board of `pattern` = (cols, rows) inner corners, board frame at the first corner."""
        cols, rows = pattern
        px = self._texture_px()
        H = self._board_map(T_c_b, square_mm, px)
        tex = _board_texture(cols, rows, px)
        if self.area_sampled:
            tex = _area_texture(("chessboard", cols, rows), tex, H)
        img = cv2.remap(tex, H, _NO_MAP, cv2.INTER_LINEAR, borderValue=BACKGROUND_BGR[0])
        img3: UInt8Image = np.asarray(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), dtype=np.uint8)
        corners = chessboard_points(pattern, square_mm)
        pc = transform_points(T_c_b, corners)
        uv, valid = self.camera.project(pc)
        inside = (uv[:, 0] > 0) & (uv[:, 0] < self.camera.width - 1)
        inside &= (uv[:, 1] > 0) & (uv[:, 1] < self.camera.height - 1)
        visible = bool(np.all(valid & inside))
        return ChessboardFrame(self._noisy(img3), np.array(T_c_b, dtype=np.float64), uv, visible)

    def render_board(
        self,
        T_c_b: FloatArray,
        board: cv2.aruco.CharucoBoard,
        T_c_b_end: FloatArray | None = None,
    ) -> BoardFrame:
        """A ChArUco board at T_c_b; with T_c_b_end, blurred by the motion between the two."""
        if T_c_b_end is None:
            grey = self._cast_charuco(T_c_b, board)
            mid = np.array(T_c_b, dtype=np.float64)
        else:
            poses = interpolate_T(T_c_b, T_c_b_end, np.linspace(0.0, 1.0, self.blur_samples))
            acc = sum(self._cast_charuco(T, board).astype(np.float32) for T in poses)
            grey = np.clip(np.rint(np.asarray(acc) / self.blur_samples), 0, 255).astype(np.uint8)
            mid = np.asarray(interpolate_T(T_c_b, T_c_b_end, 0.5), dtype=np.float64)
        corners = np.asarray(board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
        uv, valid = self.camera.project(transform_points(mid, corners))
        inside = valid & (uv[:, 0] > 0) & (uv[:, 0] < self.camera.width - 1)
        inside &= (uv[:, 1] > 0) & (uv[:, 1] < self.camera.height - 1)
        img3 = np.asarray(cv2.cvtColor(self._noisy(grey), cv2.COLOR_GRAY2BGR), dtype=np.uint8)
        return BoardFrame(img3, mid, uv, inside)

    def _cast_charuco(self, T_c_b: FloatArray, board: cv2.aruco.CharucoBoard) -> UInt8Image:
        """Grey image of the board seen from T_c_b (no noise), background elsewhere."""
        square_mm = float(board.getSquareLength())
        px = self._texture_px()
        tex = _charuco_texture(board, px)
        H = self._board_map(T_c_b, square_mm, px, offset_px=BOARD_MARGIN_SQUARES * px)
        if self.area_sampled:
            tex = _area_texture((id(board),), tex, H)
        out = cv2.remap(tex, H, _NO_MAP, cv2.INTER_LINEAR, borderValue=BACKGROUND_BGR[0])
        return np.asarray(out, dtype=np.uint8)

    def _draw_edges(self, img: UInt8Image, T_c_p: FloatArray, model: Wireframe) -> None:
        """Draw subdivided edges, skipping pieces with an end behind the camera or outside the
        lens's field of view (where its distortion would fold them back into the image)."""
        v = model.vertices
        a, b = v[model.edges[:, 0]], v[model.edges[:, 1]]
        f = np.linspace(0.0, 1.0, EDGE_SUBDIVISIONS + 1)
        pts = transform_points(T_c_p, a[:, None, :] + f[None, :, None] * (b - a)[:, None, :])
        uv, valid = self.camera.project(pts)
        ok = valid & np.all(np.abs(uv) < 1e5, axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            radius = np.hypot(pts[..., 0], pts[..., 1]) / pts[..., 2]
        ok &= radius < self.camera.one_to_one_radius()
        pieces = np.stack([uv[:, :-1], uv[:, 1:]], axis=2)[ok[:, :-1] & ok[:, 1:]]
        if len(pieces):
            lines = list(np.rint(pieces * 16).astype(np.int32))
            cv2.polylines(img, lines, False, EDGE_BGR, 2, cv2.LINE_AA, 4)

    def _draw_points(self, img: UInt8Image, uv: FloatArray) -> None:
        """Small filled discs of seeded random colours at the textured points."""
        colors = self._rng.integers(0, 256, size=(len(uv), 3))
        for (u, v), c in zip(uv, colors, strict=True):
            if np.isfinite(u) and np.isfinite(v) and abs(u) < 1e5 and abs(v) < 1e5:
                center = (round(float(u) * 16), round(float(v) * 16))
                color = (int(c[0]), int(c[1]), int(c[2]))
                cv2.circle(img, center, TEXTURED_POINT_RADIUS_PX * 16, color, -1, cv2.LINE_AA, 4)

    def _draw_targets(self, img: UInt8Image, uv: FloatArray) -> None:
        """A white dot in a black ring at each target, anti-aliased at 1/16 px."""
        for u, v in uv:
            if np.isfinite(u) and np.isfinite(v) and abs(u) < 1e5 and abs(v) < 1e5:
                centre = (round(float(u) * 16), round(float(v) * 16))
                for radius, color in (
                    (TARGET_RING_PX, TARGET_RING_BGR),
                    (TARGET_DOT_PX, TARGET_DOT_BGR),
                ):
                    cv2.circle(img, centre, round(radius * 16), color, -1, cv2.LINE_AA, 4)

    def _noisy(self, img: UInt8Image) -> UInt8Image:
        """Add seeded Gaussian noise, truncated to whole grey levels and clipped to uint8.

        The noise is drawn as 16-bit uniform indices into a table of the quantised Gaussian
        (what the float noise truncated to uint8 gave, each level's probability to 1/65536),
        once, into a bank of `NOISE_BANK_FRAMES` frames' worth; a frame takes the run of the
        bank's samples that starts at a seeded random offset. Every pixel's noise has the same
        distribution and those of one frame are independent as before; two frames share samples
        only shifted by their offsets' difference, which no fit looks for. Drawing 16-bit
        indices and looking them up per frame took ~30 ms at 1280x1024x3, a fifth of a core at
        5 fps; taking a run of the bank, a quarter of that.
        """
        if self.noise_sigma_dn <= 0.0:
            return img
        bank = self._noise_bank(img.size)
        start = int(self._rng.integers(0, len(bank) - img.size + 1))
        noise = bank[start : start + img.size].reshape(img.shape)
        return np.asarray(cv2.add(img, noise, dtype=cv2.CV_8U), dtype=np.uint8)

    def _noise_bank(self, size: int) -> npt.NDArray[np.int16]:
        """The seeded noise samples frames take their runs from (drawn at the first frame)."""
        if self._bank is None or len(self._bank) < NOISE_BANK_FRAMES * size:
            table = _noise_table(self.noise_sigma_dn)
            draws = NOISE_BANK_FRAMES * size
            self._bank = table[np.frombuffer(self._rng.bytes(2 * draws), dtype=np.uint16)]
        return self._bank

    def _pixel_rays(self) -> npt.NDArray[np.float32]:
        """Undistorted normalised coordinates (H, W, 2) of every pixel, computed once."""
        if self._rays is None:
            u, v = np.meshgrid(np.arange(self.camera.width), np.arange(self.camera.height))
            n = self.camera.undistort_normalized(np.stack([u, v], axis=-1).astype(float))
            self._rays = np.ascontiguousarray(n, dtype=np.float32)
        return self._rays

    def _texture_px(self) -> int:
        """Texels per board square of the textures this camera samples."""
        return TEXTURE_PX_PER_SQUARE if self.area_sampled else POINT_TEXTURE_PX_PER_SQUARE

    def _board_map(
        self, T_c_b: FloatArray, square_mm: float, px_per_square: int,
        offset_px: float | None = None,
    ) -> npt.NDArray[np.float32]:  # fmt: skip
        """Texture coordinates (H, W, 2) of each pixel through the board-plane homography.

        `offset_px` is where the board origin sits in the texture (pixel edges); the default is
        the chessboard's, whose origin is the first inner corner.
        """
        n = self._pixel_rays()
        # Pixel ray (x, y, 1) meets the plane z_b = 0: H maps board (X, Y, 1) to the ray; the
        # texture's scale and offset go into the same matrix (one pass over the pixels).
        Hm = np.column_stack([T_c_b[:3, 0], T_c_b[:3, 1], T_c_b[:3, 3]])
        scale = px_per_square / square_mm
        edge = (BOARD_MARGIN_SQUARES + 1.0) * px_per_square if offset_px is None else offset_px
        off = edge - 0.5  # texture pixel centres sit at integers
        to_tex = np.array([[scale, 0.0, off], [0.0, scale, off], [0.0, 0.0, 1.0]])
        M = to_tex @ np.linalg.inv(Hm)
        M = (M / np.linalg.norm(M[2])).astype(np.float32)  # w of order 1 over the image
        out = np.asarray(cv2.perspectiveTransform(n, M), dtype=np.float32)
        # The ray meets the plane behind the camera (w ≤ 0), or beyond any texture (w → 0,
        # where perspectiveTransform gives 0 instead of a huge coordinate).
        w = cv2.transform(n, M[2:])
        out[w <= W_MIN] = -1e6
        return out


def chessboard_points(pattern: tuple[int, int], square_mm: float) -> FloatArray:
    """Inner corners (cols*rows, 3) in the board frame, row-major as OpenCV detects them."""
    cols, rows = pattern
    gx, gy = np.meshgrid(np.arange(cols), np.arange(rows))
    grid = np.stack([gx.ravel(), gy.ravel(), np.zeros(cols * rows)], axis=1)
    return grid.astype(np.float64) * square_mm


def _board_texture(cols: int, rows: int, px_per_square: int) -> UInt8Image:
    """Grey-level board: (cols+1) x (rows+1) squares with a white margin."""
    s, m = px_per_square, int(BOARD_MARGIN_SQUARES * px_per_square)
    iy, ix = np.indices((rows + 1, cols + 1))
    squares = np.where((ix + iy) % 2 == 0, 20, 235).astype(np.uint8)
    tex = np.kron(squares, np.ones((s, s), dtype=np.uint8))
    return np.pad(tex, m, constant_values=235)


# (id, texels a square) → (board, texture): holding the board keeps its id from being reused
_CHARUCO_TEXTURES: dict[tuple[int, int], tuple[cv2.aruco.CharucoBoard, UInt8Image]] = {}


def _charuco_texture(board: cv2.aruco.CharucoBoard, px_per_square: int) -> UInt8Image:
    """The board's printed image, `px_per_square` a square and a white margin (cached)."""
    key = (id(board), px_per_square)
    if key not in _CHARUCO_TEXTURES:
        cols, rows = board.getChessboardSize()
        m, s = int(BOARD_MARGIN_SQUARES * px_per_square), px_per_square
        img = board.generateImage((cols * s + 2 * m, rows * s + 2 * m), marginSize=m)
        # printed black and white are not 0 and 255: keep the sensor's headroom for noise
        tex = (20 + np.asarray(img, np.float32) * (215 / 255)).astype(np.uint8)
        _CHARUCO_TEXTURES[key] = (board, tex)
    return _CHARUCO_TEXTURES[key][1]


# (texture's key, footprint in steps along x and y) → the prefiltered texture, oldest first
_AREA_TEXTURES: dict[tuple[Any, ...], UInt8Image] = {}


def _area_texture(key: tuple[Any, ...], tex: UInt8Image, H: npt.NDArray[np.float32]) -> UInt8Image:
    """`tex` averaged over a pixel's footprint, for sampling through the map `H` (cached).

    A pixel integrates the board over its footprint, the parallelogram its square maps to on the
    texture (sides the map's derivatives along u and v). The texture is filtered by a separable
    box whose widths along the texture's x and y are that footprint's (the root sum of squares
    of its sides' components: the box has the footprint's variance along each axis), taken as
    the median over a grid of the pixels that see the board: one box for the whole view, as the
    footprint changes little over a board that fills part of the image. The bilinear sample at
    the pixel's centre then adds a tent one texel wide, a fraction of a pixel. A footprint under
    a texel (the board nearer than the texture is fine) leaves the texture as it is.
    """
    wx, wy = _footprint_texels(H, tex.shape[1], tex.shape[0])
    nx, ny = round(wx / FOOTPRINT_STEP_TEXELS), round(wy / FOOTPRINT_STEP_TEXELS)
    if max(nx, ny) * FOOTPRINT_STEP_TEXELS <= 1.0:
        return tex
    k = (*key, nx, ny)
    if k not in _AREA_TEXTURES:
        kx, ky = _box(nx * FOOTPRINT_STEP_TEXELS), _box(ny * FOOTPRINT_STEP_TEXELS)
        out = cv2.sepFilter2D(tex, -1, kx, ky, borderType=cv2.BORDER_REPLICATE)
        _AREA_TEXTURES[k] = np.asarray(out, dtype=np.uint8)
        while len(_AREA_TEXTURES) > AREA_TEXTURES_KEPT:
            del _AREA_TEXTURES[next(iter(_AREA_TEXTURES))]
    return _AREA_TEXTURES[k]


def _footprint_texels(H: npt.NDArray[np.float32], width: int, height: int) -> tuple[float, float]:
    """Median extent (x, y) on the texture of a pixel that sees it, texels; (0, 0) if none does."""
    g = FOOTPRINT_GRID_PX
    at = H[:-1:g, :-1:g]
    du = H[:-1:g, 1::g][:, : at.shape[1]] - at
    dv = H[1::g, :-1:g][: at.shape[0]] - at
    on = (at[..., 0] >= 0) & (at[..., 0] < width) & (at[..., 1] >= 0) & (at[..., 1] < height)
    if not on.any():
        return 0.0, 0.0
    ext = np.hypot(du[on], dv[on])  # (n, 2): per texture axis, over the footprint's two sides
    return float(np.median(ext[:, 0])), float(np.median(ext[:, 1]))


def _box(width: float) -> npt.NDArray[np.float32]:
    """A normalised box filter `width` taps wide, its end taps weighted by the fraction over."""
    full = math.floor((width - 1.0) / 2.0)  # whole taps either side of the centre
    end = (width - (2 * full + 1)) / 2.0
    taps = np.ones(2 * full + 3)
    taps[0] = taps[-1] = end
    return np.asarray(taps / taps.sum(), dtype=np.float32)


_NOISE_TABLES: dict[float, npt.NDArray[np.int16]] = {}


def _noise_table(sigma_dn: float) -> npt.NDArray[np.int16]:
    """floor(σ·z) at the 65536 mid-quantiles of the standard normal: uint16 → noise (cached).

    Level k is taken where Φ(k/σ) ≤ quantile < Φ((k+1)/σ): a few erf calls, not 65536.
    """
    if sigma_dn not in _NOISE_TABLES:
        reach = math.ceil(5.0 * sigma_dn) + 1  # beyond the table's 4.3σ
        levels = np.arange(-reach, reach + 1)
        edges = np.array([0.5 * (1.0 + math.erf(k / (sigma_dn * math.sqrt(2.0)))) for k in levels])
        quantiles = (np.arange(65536) + 0.5) / 65536
        at = np.searchsorted(edges, quantiles, side="right") - 1
        _NOISE_TABLES[sigma_dn] = levels[at].astype(np.int16)
    return _NOISE_TABLES[sigma_dn]


STILL_TOL = 1e-6  # mm and rad: a pose this near the last one renders the same image


def _key(a: FloatArray | None) -> FloatArray | None:
    """A pose or point set as compared for `_same` (a copy: callers may reuse their arrays)."""
    return None if a is None else np.array(a, dtype=np.float64)


def _same(a: tuple[Any, ...], b: tuple[Any, ...]) -> bool:
    """The same model, board and targets, and poses within STILL_TOL."""
    for x, y in zip(a, b, strict=True):
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if x is None or y is None or x.shape != y.shape:
                return False
            if not np.allclose(x, y, rtol=0.0, atol=STILL_TOL):
                return False
        elif x is not y:
            return False
    return True
