"""Homogeneous transforms, Euler angles (paper eq. 3), rotation vectors and quaternions.

Every function is vectorised over leading axes and works in float64. Poses are 4x4 matrices
`T_a_b` mapping points in frame b into frame a. Quaternions are scalar-first `(w, x, y, z)`.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
ArrayLike = npt.ArrayLike

GIMBAL_EPS = 1e-9  # |cos β| below this is treated as gimbal lock in euler_zyx_from_R
SMALL_ANGLE_RAD = 1e-12  # below this the rotation-vector maps use their series expansion


def _f64(x: ArrayLike) -> FloatArray:
    """Convert to a float64 array without copying when already float64."""
    return np.asarray(x, dtype=np.float64)


def make_T(R: ArrayLike, t: ArrayLike) -> FloatArray:
    """Build 4x4 transforms from rotations (...,3,3) and translations (...,3)."""
    R_ = _f64(R)
    t_ = _f64(t)
    shape = np.broadcast_shapes(R_.shape[:-2], t_.shape[:-1])
    T = np.zeros((*shape, 4, 4))
    T[..., :3, :3] = R_
    T[..., :3, 3] = t_
    T[..., 3, 3] = 1.0
    return T


def invert_T(T: ArrayLike) -> FloatArray:
    """Invert rigid transforms (...,4,4) using the transpose of the rotation."""
    T_ = _f64(T)
    Rt = np.swapaxes(T_[..., :3, :3], -1, -2)
    t = -np.einsum("...ij,...j->...i", Rt, T_[..., :3, 3])
    return make_T(Rt, t)


def transform_points(T: ArrayLike, points: ArrayLike) -> FloatArray:
    """Apply one transform (4,4) to points (...,3)."""
    T_ = _f64(T)
    p = _f64(points)
    out: FloatArray = p @ T_[:3, :3].T + T_[:3, 3]
    return out


def rot_x(angle: ArrayLike) -> FloatArray:
    """Rotation matrices about x, shape angle.shape + (3, 3)."""
    a = _f64(angle)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([o, z, z, z, c, -s, z, s, c], axis=-1).reshape(*a.shape, 3, 3)


def rot_y(angle: ArrayLike) -> FloatArray:
    """Rotation matrices about y, shape angle.shape + (3, 3)."""
    a = _f64(angle)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([c, z, s, z, o, z, -s, z, c], axis=-1).reshape(*a.shape, 3, 3)


def rot_z(angle: ArrayLike) -> FloatArray:
    """Rotation matrices about z, shape angle.shape + (3, 3)."""
    a = _f64(angle)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([c, -s, z, s, c, z, z, z, o], axis=-1).reshape(*a.shape, 3, 3)


def euler_zyx(alpha: ArrayLike, beta: ArrayLike, gamma: ArrayLike) -> FloatArray:
    """Rotation R = Rz(γ) Ry(β) Rx(α) of paper eq. 3 (α about x, β about y, γ about z)."""
    return rot_z(gamma) @ rot_y(beta) @ rot_x(alpha)


def euler_zyx_from_R(R: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Inverse of euler_zyx: (α, β, γ) with β in [-π/2, π/2]; at gimbal lock γ is set to 0."""
    R_ = _f64(R)
    beta = np.arcsin(np.clip(-R_[..., 2, 0], -1.0, 1.0))
    cb = np.cos(beta)
    locked = np.abs(cb) < GIMBAL_EPS
    alpha = np.arctan2(R_[..., 2, 1], R_[..., 2, 2])
    gamma = np.arctan2(R_[..., 1, 0], R_[..., 0, 0])
    # At β = ±π/2 only α ∓ γ is observable; put it all in α (γ = 0) from the top-right block.
    alpha_locked = np.arctan2(np.sign(-R_[..., 2, 0]) * R_[..., 0, 1], R_[..., 1, 1])
    alpha = np.where(locked, alpha_locked, alpha)
    gamma = np.where(locked, 0.0, gamma)
    return alpha, beta, gamma


def nearest_rotation(M: ArrayLike) -> FloatArray:
    """Closest rotation (Frobenius norm, det +1) to a 3x3 matrix, via SVD."""
    U, _, Vt = np.linalg.svd(_f64(M))
    d = np.sign(np.linalg.det(U @ Vt))
    U[..., :, 2] *= d[..., None]
    out: FloatArray = U @ Vt
    return out


def rotvec_to_R(rv: ArrayLike) -> FloatArray:
    """Rodrigues: rotation vectors (...,3) to matrices (...,3,3)."""
    r = _f64(rv)
    theta = np.linalg.norm(r, axis=-1)
    small = theta < SMALL_ANGLE_RAD
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(th) / th)
    b = np.where(small, 0.5, (1.0 - np.cos(th)) / (th * th))
    K = _skew(r)
    eye = np.broadcast_to(np.eye(3), K.shape)
    out: FloatArray = eye + a[..., None, None] * K + b[..., None, None] * (K @ K)
    return out


def R_to_rotvec(R: ArrayLike) -> FloatArray:
    """Rotation matrices to rotation vectors, robust near 0 and π (through quaternions)."""
    q = quat_from_R(R)
    q = q * np.where(q[..., :1] < 0.0, -1.0, 1.0)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1)
    theta = 2.0 * np.arctan2(s, q[..., 0])
    scale = np.where(s < SMALL_ANGLE_RAD, 2.0, theta / np.where(s == 0.0, 1.0, s))
    out: FloatArray = v * scale[..., None]
    return out


def _skew(v: FloatArray) -> FloatArray:
    """Cross-product matrices of vectors (...,3)."""
    z = np.zeros_like(v[..., 0])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([z, -w, y, w, z, -x, -y, x, z], axis=-1).reshape(*v.shape[:-1], 3, 3)


def quat_from_R(R: ArrayLike) -> FloatArray:
    """Unit quaternions (w, x, y, z) from rotation matrices, largest-pivot method."""
    R_ = _f64(R)
    m = R_.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    # Candidate 4|q_i| for each pivot; pick the largest for numerical stability.
    diag = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    piv = np.argmax(np.stack([tr, *(2 * diag[:, 1:] - tr[:, None]).T], axis=1), axis=1)
    q = np.empty((m.shape[0], 4))
    for k in range(4):
        sel = piv == k
        if np.any(sel):
            q[sel] = _quat_pivot(m[sel], k)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q.reshape(*R_.shape[:-2], 4)


def _quat_pivot(m: FloatArray, k: int) -> FloatArray:
    """Quaternions for matrices whose largest quaternion component is index k."""
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2])
        cols = [0.25 * s, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]]
        return np.stack([cols[0], cols[1] / s, cols[2] / s, cols[3] / s], axis=1)
    i, j, n = k - 1, k % 3, (k + 1) % 3
    s = 2.0 * np.sqrt(1.0 + m[:, i, i] - m[:, j, j] - m[:, n, n])
    q = np.empty((m.shape[0], 4))
    q[:, 0] = (m[:, n, j] - m[:, j, n]) / s
    q[:, 1 + i] = 0.25 * s
    q[:, 1 + j] = (m[:, j, i] + m[:, i, j]) / s
    q[:, 1 + n] = (m[:, n, i] + m[:, i, n]) / s
    return q


def R_from_quat(q: ArrayLike) -> FloatArray:
    """Rotation matrices from quaternions (w, x, y, z); the input need not be unit length."""
    q_ = _f64(q)
    q_ = q_ / np.linalg.norm(q_, axis=-1, keepdims=True)
    w, x, y, z = q_[..., 0], q_[..., 1], q_[..., 2], q_[..., 3]
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return np.stack(rows, axis=-1).reshape(*q_.shape[:-1], 3, 3)


def slerp(q0: ArrayLike, q1: ArrayLike, f: ArrayLike) -> FloatArray:
    """Spherical interpolation between unit quaternions along the shorter arc, f in [0, 1]."""
    a, b, t = _f64(q0), _f64(q1), _f64(f)[..., None]
    dot = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(dot < 0.0, -b, b)  # q and -q are the same rotation: take the short way
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_t = np.sin(theta)
    near = sin_t < 1e-9
    safe = np.where(near, 1.0, sin_t)
    w0 = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / safe)
    w1 = np.where(near, t, np.sin(t * theta) / safe)
    q = w0 * a + w1 * b
    out: FloatArray = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return out


def interpolate_T(T0: ArrayLike, T1: ArrayLike, f: ArrayLike) -> FloatArray:
    """Interpolate poses: slerp on rotation, linear on translation (as ROS tf2 does)."""
    A, B = _f64(T0), _f64(T1)
    t = _f64(f)
    q = slerp(quat_from_R(A[..., :3, :3]), quat_from_R(B[..., :3, :3]), t)
    p = A[..., :3, 3] + t[..., None] * (B[..., :3, 3] - A[..., :3, 3])
    return make_T(R_from_quat(q), p)


def rotation_angle(R: ArrayLike) -> FloatArray:
    """Rotation angle in radians of each matrix (...,3,3), accurate near zero."""
    out: FloatArray = np.linalg.norm(R_to_rotvec(R), axis=-1)
    return out


def angle_median(angles: ArrayLike) -> FloatArray:
    """Median over the rows of angles (rad), each column taken the shorter way round from the
    first row: readings that straddle ±π (a pan stop there) have their median near ±π."""
    a = _f64(angles)
    turn = np.remainder(a - a[0] + np.pi, 2.0 * np.pi) - np.pi
    out: FloatArray = a[0] + np.median(turn, axis=0)
    return out
