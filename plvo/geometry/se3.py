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


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """(3,) rotation vector -> (3,3) rotation matrix (Rodrigues)."""
    phi = np.asarray(phi, dtype=float)
    theta = float(np.linalg.norm(phi))
    W = hat(phi)
    if theta < 1e-8:
        return np.eye(3) + W + 0.5 * W @ W
    return np.eye(3) + np.sin(theta) / theta * W + (1 - np.cos(theta)) / theta**2 * W @ W


def so3_log(R: np.ndarray) -> np.ndarray:
    """(3,3) rotation matrix -> (3,) rotation vector with norm in [0, pi]."""
    R = np.asarray(R, dtype=float)
    cos_t = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = float(np.arccos(cos_t))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-6:
        return 0.5 * v
    if np.pi - theta < 1e-4:
        # Near pi the antisymmetric part vanishes; read the axis off the symmetric part instead.
        B = (R + np.eye(3)) / 2.0
        axis = np.sqrt(np.clip(np.diag(B), 0.0, None))
        k = int(np.argmax(axis))
        axis = B[k] / max(axis[k], _EPS)
        axis /= np.linalg.norm(axis)
        if np.dot(axis, v) < 0:
            axis = -axis
        return theta * axis
    return theta / (2.0 * np.sin(theta)) * v


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(phi))
    W = hat(phi)
    if theta < 1e-6:
        return np.eye(3) + 0.5 * W + W @ W / 6.0
    return (
        np.eye(3)
        + (1 - np.cos(theta)) / theta**2 * W
        + (theta - np.sin(theta)) / theta**3 * W @ W
    )


def _left_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(phi))
    W = hat(phi)
    if theta < 1e-6:
        return np.eye(3) - 0.5 * W + W @ W / 12.0
    half = theta / 2.0
    coef = (1.0 - half * np.cos(half) / np.sin(half)) / theta**2
    return np.eye(3) - 0.5 * W + coef * W @ W


def exp(xi: np.ndarray) -> np.ndarray:
    """(6,) tangent (rho, phi) -> (4,4) pose."""
    xi = np.asarray(xi, dtype=float)
    T = np.eye(4)
    T[:3, :3] = so3_exp(xi[3:])
    T[:3, 3] = _left_jacobian(xi[3:]) @ xi[:3]
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
    R = T[:3, :3]
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """Project the rotation block back onto SO(3) (poses read from text drift off it)."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    out = T.copy()
    out[:3, :3] = R
    return out
