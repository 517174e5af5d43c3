"""SE(3) and SO(3): exp/log maps, composition, inversion, on 4x4 homogeneous matrices.

Tangent vectors are xi = (rho, phi) in R^6, translation part first; gtsam's Pose3 orders them rotation first,
and `to_gtsam_tangent` converts. exp(xi) = [[so3_exp(phi), J(phi) rho], [0, 1]].
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-10


def hat(w: np.ndarray) -> np.ndarray:
    """(3,) -> (3,3) skew-symmetric matrix with hat(w) @ v = w x v."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _series(theta: float) -> tuple[float, float, float]:
    """(sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3), by Taylor series near 0 where the closed forms cancel."""
    if theta < 1e-3:
        t2 = theta * theta
        return (
            1.0 - t2 / 6.0 + t2 * t2 / 120.0,
            0.5 - t2 / 24.0 + t2 * t2 / 720.0,
            1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0,
        )
    return np.sin(theta) / theta, (1.0 - np.cos(theta)) / theta**2, (theta - np.sin(theta)) / theta**3


def _so3_terms(phi: np.ndarray) -> tuple[float, float, float, np.ndarray]:
    """(3,) rotation vector -> its series (a, b, c) and hat W, from which the rotation (_rodrigues) and the left
    Jacobian (_left) are made: `exp` needs both from one series and one hat (the bundle adjustment calls it for every
    free pose of every step), so3_exp and _left_jacobian one each."""
    phi = np.asarray(phi, dtype=float)
    return (*_series(float(np.linalg.norm(phi))), hat(phi))


def _rodrigues(a: float, b: float, W: np.ndarray) -> np.ndarray:
    return np.eye(3) + a * W + b * W @ W


def _left(b: float, c: float, W: np.ndarray) -> np.ndarray:
    return np.eye(3) + b * W + c * W @ W


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """(3,) rotation vector -> (3,3) rotation matrix (Rodrigues)."""
    a, b, _, W = _so3_terms(phi)
    return _rodrigues(a, b, W)


def so3_log(R: np.ndarray) -> np.ndarray:
    """(3,3) rotation matrix -> (3,) rotation vector with norm in [0, pi]."""
    R = np.asarray(R, dtype=float)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    cos_t = (np.trace(R) - 1.0) / 2.0
    # atan2 keeps full precision near 0 and pi, where arccos of the trace loses half the digits.
    theta = float(np.arctan2(0.5 * np.linalg.norm(v), cos_t))
    if np.pi - theta < 1e-2:
        # Near pi the antisymmetric part vanishes; read the axis off the symmetric part, which is
        # cos(t) I + (1 - cos(t)) a a^T exactly (the antisymmetric part must be dropped, else it leaks in).
        aat = (0.5 * (R + R.T) - np.cos(theta) * np.eye(3)) / (1.0 - np.cos(theta))
        k = int(np.argmax(np.diag(aat)))
        axis = aat[k] / np.sqrt(max(aat[k, k], _EPS))
        axis /= np.linalg.norm(axis)
        if np.dot(axis, v) < 0:
            axis = -axis
        return theta * axis
    return 0.5 / _series(theta)[0] * v


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    _, b, c, W = _so3_terms(phi)
    return _left(b, c, W)


def _left_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(phi))
    W = hat(phi)
    if theta < 1e-3:
        t2 = theta * theta
        coef = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    else:
        half = theta / 2.0
        coef = (1.0 - half * np.cos(half) / np.sin(half)) / theta**2
    return np.eye(3) - 0.5 * W + coef * W @ W


def exp(xi: np.ndarray) -> np.ndarray:
    """(6,) tangent (rho, phi) -> (4,4) pose."""
    xi = np.asarray(xi, dtype=float)
    a, b, c, W = _so3_terms(xi[3:])
    T = np.eye(4)
    T[:3, :3] = _rodrigues(a, b, W)
    T[:3, 3] = _left(b, c, W) @ xi[:3]
    return T


def log(T: np.ndarray) -> np.ndarray:
    """(4,4) pose -> (6,) tangent (rho, phi)."""
    phi = so3_log(T[:3, :3])
    rho = _left_jacobian_inv(phi) @ T[:3, 3]
    return np.concatenate([rho, phi])


def inv(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4,4) rigid transform, without a general matrix inverse."""
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def conjugate(T_a_b: np.ndarray, M_b: np.ndarray) -> np.ndarray:
    """A relative motion (4,4) between two poses of frame b -> the same motion seen by frame a, rigidly attached to
    b (T_a_b maps b into a): T_a_b M_b T_a_b^-1, e.g. a lidar registration's T_dst_src as the cameras' motion."""
    return T_a_b @ M_b @ inv(T_a_b)


def inv_batch(T: np.ndarray) -> np.ndarray:
    """(N,4,4) rigid transforms -> (N,4,4) inverses."""
    T = np.asarray(T, float)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[:, :3, :3], 1, 2)
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def compose(*Ts: np.ndarray) -> np.ndarray:
    """T_a_b, T_b_c, ... -> T_a_z."""
    out = np.eye(4)
    for T in Ts:
        out = out @ T
    return out


def transform_points(T_a_b: np.ndarray, pts_b: np.ndarray) -> np.ndarray:
    """(N,3) points in frame b -> (N,3) in frame a."""
    pts_b = np.asarray(pts_b, dtype=float)
    return pts_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def from_rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def adjoint(T: np.ndarray) -> np.ndarray:
    """(6,6) adjoint for tangents ordered (rho, phi): exp(Ad(T) xi) = T exp(xi) T^-1."""
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[:3, 3:] = hat(t) @ R
    A[3:, 3:] = R
    return A


def to_gtsam_tangent(xi: np.ndarray) -> np.ndarray:
    """(rho, phi) -> gtsam's Pose3 order (phi, rho)."""
    return np.concatenate([xi[3:], xi[:3]])


def rotation_angle(T: np.ndarray) -> float:
    """Rotation angle of a pose or rotation matrix, radians."""
    R = np.asarray(T)[:3, :3]
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(np.arctan2(s, (np.trace(R) - 1.0) / 2.0))


def orthonormalize_batch(T: np.ndarray) -> np.ndarray:
    """(N,4,4) transforms -> the same with each rotation block projected onto SO(3) (nearest in Frobenius norm)."""
    T = np.asarray(T, float)
    U, _, Vt = np.linalg.svd(T[:, :3, :3])
    flip = np.linalg.det(U @ Vt) < 0
    U[flip, :, -1] *= -1
    out = T.copy()
    out[:, :3, :3] = U @ Vt
    return out


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """Project the rotation block back onto SO(3) (poses read from text drift off it)."""
    return orthonormalize_batch(np.asarray(T, float)[None])[0]
