"""Pinhole camera with skew and Brown-Conrady distortion (paper eq. 5/7, Table 1).

Image coordinates: u right, v down, origin top-left, pixel centres at integers (as OpenCV).
Camera frame c: z along the optical axis, x toward +u, y toward +v.

    x, y = X/Z, Y/Z;  r² = x² + y²;  radial = 1 + k1 r² + k2 r⁴ + k3 r⁶
    xd = x·radial + 2 p1 x y + p2 (r² + 2x²);   yd = y·radial + p1 (r² + 2y²) + 2 p2 x y
    u = fx xd + skew yd + u0;                   v = fy yd + v0

This is OpenCV's model plus the skew term (the paper's r in eq. 5); at skew 0 it equals
cv2.projectPoints. Distortion coefficients act on normalised coordinates.

Resolution: Table 1's principal point (645.3, 508.3) is the centre of a 1280x1024 sensor and lies
outside a 640x480 image, so the intrinsics can only belong to 1280x1024; that is the default.
The text's 640x480 video mode would need `scaled()` intrinsics from a calibration at that mode.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from host.geometry.transforms import ArrayLike, FloatArray

BoolArray = npt.NDArray[np.bool_]

MIN_DEPTH_MM = 1.0  # points closer than this to the camera plane (or behind it) are invalid
UNDISTORT_ITERATIONS = 20  # fixed-point passes; converges to <1e-12 for Table 1 within the image
TABLE1 = {
    "fx": 3676.462,
    "fy": 3676.478,
    "skew": 0.263,
    "u0": 645.342,
    "v0": 508.259,
    "k1": 1.30,
    "k2": 1.88,
}
CONFIG_KEYS = ("fx", "fy", "skew", "u0", "v0", "k1", "k2", "p1", "p2", "k3", "width", "height")


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics in pixels, distortion on normalised coordinates, resolution in pixels."""

    fx: float = TABLE1["fx"]
    fy: float = TABLE1["fy"]
    skew: float = TABLE1["skew"]
    u0: float = TABLE1["u0"]
    v0: float = TABLE1["v0"]
    k1: float = TABLE1["k1"]
    k2: float = TABLE1["k2"]
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    width: int = 1280
    height: int = 1024

    @property
    def K(self) -> FloatArray:
        """3x3 intrinsic matrix of eq. 5."""
        return np.array([[self.fx, self.skew, self.u0], [0.0, self.fy, self.v0], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> FloatArray:
        """Distortion in OpenCV order (k1, k2, p1, p2, k3)."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) as OpenCV expects image sizes."""
        return (self.width, self.height)

    def to_config(self) -> dict[str, Any]:
        """Plain dict for the [camera] config section."""
        return {k: getattr(self, k) for k in CONFIG_KEYS}

    @classmethod
    def from_config(cls, d: dict[str, Any]) -> CameraModel:
        """Build from a [camera] section; missing keys take the defaults, unknown keys fail."""
        unknown = set(d) - set(CONFIG_KEYS)
        if unknown:
            raise ValueError(f"unknown camera keys: {sorted(unknown)}")
        base = cls()
        vals = {k: type(getattr(base, k))(v) for k, v in d.items()}  # int for sizes, else float
        return dataclasses.replace(base, **vals)

    def scaled(self, factor: float) -> CameraModel:
        """The same optics read out binned/scaled by `factor` (pixel-centre convention kept)."""
        # Pixel centres sit at integers, so pixel edges (u + 0.5) are what scale.
        return CameraModel(
            self.fx * factor, self.fy * factor, self.skew * factor,
            (self.u0 + 0.5) * factor - 0.5, (self.v0 + 0.5) * factor - 0.5,
            self.k1, self.k2, self.p1, self.p2, self.k3,
            round(self.width * factor), round(self.height * factor),
        )  # fmt: skip

    def distort(self, x: ArrayLike, y: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Apply distortion to normalised coordinates."""
        x_, y_ = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        r2 = x_ * x_ + y_ * y_
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xy = x_ * y_
        xd = x_ * radial + 2.0 * self.p1 * xy + self.p2 * (r2 + 2.0 * x_ * x_)
        yd = y_ * radial + self.p1 * (r2 + 2.0 * y_ * y_) + 2.0 * self.p2 * xy
        return xd, yd

    def one_to_one_radius(self) -> float:
        """The undistorted normalised radius up to which the radial distortion maps radii one
        to one (inf where it always does). Beyond it the polynomial turns back and folds far
        points into the image, where no lens shows them: they lie outside its field of view."""
        # d/dr of r (1 + k1 r² + k2 r⁴ + k3 r⁶) = 1 + 3 k1 u + 5 k2 u² + 7 k3 u³ with u = r²
        roots = np.roots([7.0 * self.k3, 5.0 * self.k2, 3.0 * self.k1, 1.0])
        turns = [r.real for r in roots if abs(r.imag) < 1e-12 and r.real > 0.0]
        return math.sqrt(min(turns)) if turns else math.inf

    def project(self, points_c: ArrayLike) -> tuple[FloatArray, BoolArray]:
        """Camera-frame points (...,3) to pixels (...,2); points behind the camera give NaN."""
        p = np.asarray(points_c, dtype=np.float64)
        z = p[..., 2]
        valid = z >= MIN_DEPTH_MM
        zs = np.where(valid, z, 1.0)
        xd, yd = self.distort(p[..., 0] / zs, p[..., 1] / zs)
        uv = np.stack([self.fx * xd + self.skew * yd + self.u0, self.fy * yd + self.v0], axis=-1)
        uv[~valid] = np.nan
        return uv, valid

    def project_world(self, T_c_w: ArrayLike, points_w: ArrayLike) -> tuple[FloatArray, BoolArray]:
        """Project world points through extrinsics T_c_w."""
        T = np.asarray(T_c_w, dtype=np.float64)
        p = np.asarray(points_w, dtype=np.float64)
        return self.project(p @ T[:3, :3].T + T[:3, 3])

    def normalized(self, uv: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Pixels to distorted normalised coordinates (inverse of K, skew included)."""
        q = np.asarray(uv, dtype=np.float64)
        yd = (q[..., 1] - self.v0) / self.fy
        xd = (q[..., 0] - self.u0 - self.skew * yd) / self.fx
        return xd, yd

    def undistort_normalized(
        self, uv: ArrayLike, iterations: int = UNDISTORT_ITERATIONS
    ) -> FloatArray:
        """Pixels to undistorted normalised coordinates (...,2) by fixed-point iteration."""
        xd, yd = self.normalized(uv)
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
            dx = 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
            dy = self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
            x = (xd - dx) / radial
            y = (yd - dy) / radial
        return np.stack([x, y], axis=-1)

    def undistort_pixels(self, uv: ArrayLike) -> FloatArray:
        """Pixels to the pixels an ideal (distortion-free) camera with the same K would see."""
        n = self.undistort_normalized(uv)
        u = self.fx * n[..., 0] + self.skew * n[..., 1] + self.u0
        return np.stack([u, self.fy * n[..., 1] + self.v0], axis=-1)

    def rays(self, uv: ArrayLike) -> FloatArray:
        """Unit viewing rays (...,3) in the camera frame for pixels."""
        n = self.undistort_normalized(uv)
        r = np.concatenate([n, np.ones((*n.shape[:-1], 1))], axis=-1)
        out: FloatArray = r / np.linalg.norm(r, axis=-1, keepdims=True)
        return out


class Projector:
    """Allocation-free projection of a fixed point set, for the per-frame path.

    Holds the points transposed (3, N) so each coordinate is one contiguous row, and reuses
    work buffers across frames; results are views valid until the next call.
    """

    def __init__(self, camera: CameraModel, points: ArrayLike) -> None:
        self.camera = camera
        self._P = np.ascontiguousarray(np.asarray(points, dtype=np.float64).T)
        n = self._P.shape[1]
        self._pc = np.empty((3, n))
        self._r2 = np.empty(n)
        self._rad = np.empty(n)
        self._tmp = np.empty(n)
        self._uv = np.empty((2, n))
        self._valid = np.empty(n, dtype=np.bool_)
        self._invalid = np.empty(n, dtype=np.bool_)
        self._tangential = camera.p1 != 0.0 or camera.p2 != 0.0

    @property
    def points_c(self) -> FloatArray:
        """Camera-frame points (3, N) of the last call."""
        return self._pc

    def project(self, T_c_w: ArrayLike) -> tuple[FloatArray, BoolArray]:
        """Pixels (2, N) and validity (N,) of the points seen from T_c_w."""
        T = np.asarray(T_c_w, dtype=np.float64)
        pc, c = self._pc, self.camera
        np.matmul(T[:3, :3], self._P, out=pc)
        pc += T[:3, 3:4]
        x, y, z = pc[0], pc[1], pc[2]
        np.greater_equal(z, MIN_DEPTH_MM, out=self._valid)
        np.logical_not(self._valid, out=self._invalid)
        np.copyto(z, 1.0, where=self._invalid)  # keep the division finite for invalid points
        np.reciprocal(z, out=z)
        x *= z
        y *= z
        self._distort_inplace(x, y)
        u, v = self._uv[0], self._uv[1]
        np.multiply(y, c.skew, out=u)
        u += c.u0
        np.multiply(x, c.fx, out=self._tmp)
        u += self._tmp
        np.multiply(y, c.fy, out=v)
        v += c.v0
        np.copyto(self._uv, np.nan, where=self._invalid)
        return self._uv, self._valid

    def _distort_inplace(self, x: FloatArray, y: FloatArray) -> None:
        """Overwrite normalised x, y with their distorted values."""
        c, r2, rad, tmp = self.camera, self._r2, self._rad, self._tmp
        np.multiply(x, x, out=r2)
        np.multiply(y, y, out=tmp)
        r2 += tmp
        np.multiply(r2, c.k3, out=rad)  # Horner: 1 + r2 (k1 + r2 (k2 + r2 k3))
        rad += c.k2
        rad *= r2
        rad += c.k1
        rad *= r2
        rad += 1.0
        if not self._tangential:
            x *= rad
            y *= rad
            return
        xy = x * y
        dx = 2.0 * c.p1 * xy + c.p2 * (r2 + 2.0 * x * x)
        dy = c.p1 * (r2 + 2.0 * y * y) + 2.0 * c.p2 * xy
        x *= rad
        x += dx
        y *= rad
        y += dy
