"""The synthetic camera area-samples boards: a pixel shows the board's mean over its footprint.

The references are computed here, not by the renderer: 6x6 rays a pixel through a distortion-free
pinhole onto the printed board (512 texels a square, nearest texel), averaged. Each test also
renders with `area_sampled=False` (each pixel the texture at its centre's ray) and checks that
this breaks the bound, so the bound tells the two apart.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from hil_sim.camera import SyntheticCamera
from host.calibration.board import BoardDetector, BoardSpec
from host.geometry.camera import CameraModel
from host.geometry.transforms import FloatArray, euler_zyx, make_T, transform_points

SPEC = BoardSpec(squares_x=8, squares_y=6, square_mm=70.0, marker_mm=52.0)  # the demo's board
BLACK, WHITE = 20.0, 235.0  # the simulator's printed levels
PINHOLE = CameraModel(
    fx=700.0, fy=700.0, skew=0.0, u0=127.5, v0=95.5, k1=0.0, k2=0.0, width=256, height=192
)
REF_TEXELS = 512
REF_RAYS = 6
# An area-sampled pixel crossed by an edge shows the board's mean over its footprint up to the
# misfit of the axis-aligned box to the footprint's shape and the tent of the texture's bilinear
# sample, which move the edge within the pixel by well under 0.1 px: its value is within 0.1 of
# the contrast on average. A point-sampled pixel is one side's level or the other by where its
# centre falls: off by a uniform fraction in [0, 1/2] of the contrast, a quarter on average.
EDGE_PIXEL_MEAN_BOUND_DN = 0.1 * (WHITE - BLACK)
# A corner detected in an area-sampled image of a far board (37-51 px a square) is off the
# exact projection by the detector's own error on a sharp image: 0.08-0.09 px RMS here with an
# 8x8-supersampled render (scripts/diagnostics/corner_bias.py's ideal renderer). The point-sampled
# renderer aliases the minified texture: 0.20-0.27 px RMS at these poses.
FAR_CORNER_RMS_BOUND_PX = 0.13


@functools.cache
def printed_board() -> FloatArray:
    """The board as printed, REF_TEXELS a square, one square of margin, grey levels."""
    board = SPEC.make()
    cols, rows = board.getChessboardSize()
    s = REF_TEXELS
    img = board.generateImage(((cols + 2) * s, (rows + 2) * s), marginSize=s)
    return BLACK + np.asarray(img, np.float64) * ((WHITE - BLACK) / 255.0)


def footprint_means(T_c_b: FloatArray) -> tuple[FloatArray, np.ndarray]:
    """Each pixel's mean of the printed board over its footprint, and where it sees only board."""
    tex, cam, k = printed_board(), PINHOLE, REF_RAYS
    off = (np.arange(k) + 0.5) / k - 0.5
    u = (np.arange(cam.width)[:, None] + off).ravel()
    v = (np.arange(cam.height)[:, None] + off).ravel()
    gu, gv = np.meshgrid(u, v)
    x, y = (gu - cam.u0) / cam.fx, (gv - cam.v0) / cam.fy
    # the ray (x, y, 1) meets the plane z_b = 0 where [r1 r2 t] (X, Y, 1) is parallel to it
    Hi = np.linalg.inv(np.column_stack([T_c_b[:3, 0], T_c_b[:3, 1], T_c_b[:3, 3]]))
    w = Hi[2, 0] * x + Hi[2, 1] * y + Hi[2, 2]
    X = (Hi[0, 0] * x + Hi[0, 1] * y + Hi[0, 2]) / w
    Y = (Hi[1, 0] * x + Hi[1, 1] * y + Hi[1, 2]) / w
    scale = REF_TEXELS / SPEC.square_mm
    i = np.floor(X * scale + REF_TEXELS).astype(int)  # the margin is one square
    j = np.floor(Y * scale + REF_TEXELS).astype(int)
    on = (w > 0) & (i >= 0) & (i < tex.shape[1]) & (j >= 0) & (j < tex.shape[0])
    val = np.zeros(X.shape)
    val[on] = tex[j[on], i[on]]
    shape = (cam.height, k, cam.width, k)
    return val.reshape(shape).mean(axis=(1, 3)), on.reshape(shape).all(axis=(1, 3))


def facing(angles: tuple[float, float, float], distance_mm: float) -> FloatArray:
    """T_c_b with the board's centre on the optical axis."""
    R = euler_zyx(*angles)
    return make_T(R, np.array([0.0, 0.0, distance_mm]) - R @ SPEC.centre_mm)


def edge_pixel_error_dn(T_c_b: FloatArray, area_sampled: bool) -> float:
    """Mean |rendered - footprint mean| over the pixels an edge crosses, grey levels."""
    ref, board_only = footprint_means(T_c_b)
    edge = board_only & (np.abs(ref - BLACK) > 1.0) & (np.abs(ref - WHITE) > 1.0)
    assert edge.sum() > 2000  # the markers' cells are a few pixels wide: many edges
    sim = SyntheticCamera(PINHOLE, noise_sigma_dn=0.0, area_sampled=area_sampled)
    img = sim.render_board(T_c_b, SPEC.make()).image[..., 0].astype(np.float64)
    return float(np.abs(img - ref)[edge].mean())


@pytest.mark.parametrize(
    ("angles", "distance_mm"),
    [((0.3, 0.0, 0.0), 3500.0), ((0.1, 0.9, -0.3), 2500.0)],  # 18 px a square; 20, tilted 52°
)
def test_a_pixel_shows_the_boards_mean_over_its_footprint(
    angles: tuple[float, float, float], distance_mm: float
) -> None:
    T = facing(angles, distance_mm)
    assert edge_pixel_error_dn(T, area_sampled=True) < EDGE_PIXEL_MEAN_BOUND_DN
    assert edge_pixel_error_dn(T, area_sampled=False) > EDGE_PIXEL_MEAN_BOUND_DN


def far_corner_rms_px(T_c_b: FloatArray, area_sampled: bool) -> float:
    """RMS distance of the detected corners from the true lens's projection, px (noiseless)."""
    det, lens = BoardDetector(SPEC), CameraModel()  # Table 1, with its distortion and skew
    sim = SyntheticCamera(lens, noise_sigma_dn=0.0, area_sampled=area_sampled)
    found = det.detect(sim.render_board(T_c_b, det.board).image)
    assert found is not None
    assert found.count == SPEC.corner_count
    points = np.asarray(det.board.getChessboardCorners(), np.float64).reshape(-1, 3)
    uv, _ = lens.project(transform_points(T_c_b, points))
    err = found.image_points - uv[found.ids]
    return float(np.sqrt((err**2).sum(axis=1).mean()))


@pytest.mark.parametrize(
    ("tilt_rad", "distance_mm"),
    [(0.35, 7000.0), (0.7, 5000.0)],  # 37 and 51 px a square
)
def test_far_board_corners_are_detected_where_the_lens_projects_them(
    tilt_rad: float, distance_mm: float
) -> None:
    T = facing((0.2, tilt_rad, 0.1), distance_mm)
    assert far_corner_rms_px(T, area_sampled=True) < FAR_CORNER_RMS_BOUND_PX
    assert far_corner_rms_px(T, area_sampled=False) > FAR_CORNER_RMS_BOUND_PX
