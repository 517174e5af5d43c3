"""The relative-pose (registration) factor of the bundle adjustment, vectorised over factors (paper II-E).

Poses are T_cam_world perturbed on the left, T_cw <- exp(xi) T_cw, xi = (rho, phi), as in bundle_adjustment.py.
The batch SE(3) helpers here follow plvo.geometry.se3 (same tangent order and formulas); rotations within 1e-2
rad of pi go through the scalar se3.log, which handles that case.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from plvo.geometry import se3
from plvo.geometry.lines import hat_batch


def log_batch(T: np.ndarray) -> np.ndarray:
    """(N,4,4) poses -> (N,6) tangents (rho, phi), as se3.log row by row."""
    R = T[:, :3, :3]
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    cos_t = (np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0
    theta = np.arctan2(0.5 * np.linalg.norm(v, axis=1), cos_t)
    small = theta < 1e-3
    t2 = theta * theta
    sinc = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, np.sin(theta) / np.where(small, 1.0, theta))
    phi = 0.5 / sinc[:, None] * v
    half = theta / 2.0
    safe = np.where(small, 1.0, theta)
    coef = np.where(small, 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0,
                    (1.0 - half * np.cos(half) / np.where(small, 1.0, np.sin(half))) / safe**2)
    W = hat_batch(phi)
    V_inv = np.eye(3) - 0.5 * W + coef[:, None, None] * (W @ W)
    out = np.concatenate([np.einsum("nij,nj->ni", V_inv, T[:, :3, 3]), phi], axis=1)
    for k in np.flatnonzero(np.pi - theta < 1e-2):  # the antisymmetric part vanishes near pi
        out[k] = se3.log(T[k])
    return out


def adjoint_batch(T: np.ndarray) -> np.ndarray:
    """(N,4,4) -> (N,6,6) adjoints for (rho, phi) tangents, as se3.adjoint."""
    R = T[:, :3, :3]
    A = np.zeros((len(T), 6, 6))
    A[:, :3, :3] = R
    A[:, 3:, 3:] = R
    A[:, :3, 3:] = hat_batch(T[:, :3, 3]) @ R
    return A


def _ad(xi: np.ndarray) -> np.ndarray:
    """(N,6) (rho, phi) -> (N,6,6) se(3) adjoint ad(xi) = [[phi^, rho^], [0, phi^]]."""
    A = np.zeros((len(xi), 6, 6))
    A[:, :3, :3] = A[:, 3:, 3:] = hat_batch(xi[:, 3:])
    A[:, :3, 3:] = hat_batch(xi[:, :3])
    return A


def relpose_block(
    T_cw_i: np.ndarray, T_cw_j: np.ndarray, T_ij_meas: np.ndarray, zeta: np.ndarray, weight: np.ndarray | None = None,
    jacobians: bool = True,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(N,4,4) x2, (N,4,4) measured T_cam_i_cam_j, (N,) zeta, (6,) weight -> r (N,6), J_i, J_j (N,6,6), whitened.

    r = Log(T_ij_meas^-1 T_i_j), T_i_j = T_cam_i_world T_world_cam_j (the paper's xi_ij up to the side of the
    inverse; same minimiser, gtsam's BetweenFactor convention), whitened by sqrt(zeta * weight): the information
    is zeta diag(weight) (weight in (rho, phi) order, default ones: the paper's zeta I).
    With T_cw <- exp(xi) T_cw: dr/dxi_i = Jr^-1(r) Ad(T_i_j^-1), dr/dxi_j = -Jr^-1(r), Jr^-1(r) ~ I + ad(r)/2.
    jacobians=False: (r, None, None).
    """
    r, later = relpose_residuals(T_cw_i, T_cw_j, T_ij_meas, zeta, weight)
    return (r, *later()) if jacobians else (r, None, None)


def relpose_residuals(
    T_cw_i: np.ndarray, T_cw_j: np.ndarray, T_ij_meas: np.ndarray, zeta: np.ndarray, weight: np.ndarray | None = None,
) -> tuple[np.ndarray, Callable[[], tuple[np.ndarray, np.ndarray]]]:
    """relpose_block's whitened r, and a function that gives its (J_i, J_j) from the quantities r was computed
    from (for the bundle adjustment's trial steps, which need the cost alone)."""
    T_ij = T_cw_i @ se3.inv_batch(T_cw_j)
    r = log_batch(se3.inv_batch(T_ij_meas) @ T_ij)
    w = np.ones(6) if weight is None else np.asarray(weight, dtype=float)
    s = np.sqrt(np.asarray(zeta, dtype=float)[:, None] * np.broadcast_to(w, (len(r), 6)))  # (N,6) per-row whitening

    def jacobians() -> tuple[np.ndarray, np.ndarray]:
        Ji = adjoint_batch(se3.inv_batch(T_ij))
        Jr_inv = np.eye(6) + 0.5 * _ad(r)
        return (Jr_inv @ Ji) * s[:, :, None], -Jr_inv * s[:, :, None]

    return r * s, jacobians
