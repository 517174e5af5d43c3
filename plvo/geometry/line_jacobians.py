"""Analytic Jacobians of the line reprojection residual (gamma) and of the point-to-line distance.

Parameterisation (as in Zuo et al. 2017): a world line in orthonormal form (U, W) is perturbed by
`lines.orth_update(U, W, delta)`, delta in R^4; a camera pose T_cam_world is perturbed on the left,
T_cam_world <- se3.exp(xi) @ T_cam_world with xi = (rho, phi). With L = [w1 u1, w2 u2] the line's derivative is

    dm/d delta = [0, -w1 u3, w1 u2, -w2 u1],   dd/d delta = [w2 u3, 0, -w2 u1, w1 u2]   (columns),

and for a left pose perturbation m_c changes by rho x d_c + phi x m_c. Everything is vectorised over N
observations with numpy only.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from plvo.errors import PlvoError
from plvo.geometry.lines import cross3, hat_batch, line_projection_matrix, orth_to_plucker


def orth_plucker_jacobian(U: np.ndarray, W: np.ndarray) -> np.ndarray:
    """(N,3,3),(N,2,2) -> (N,6,4): d[m, d]/d delta of orth_to_plucker(orth_update(U, W, delta)) at delta = 0."""
    U = np.asarray(U, dtype=float)
    W = np.asarray(W, dtype=float)
    u1, u2, u3 = U[..., :, 0], U[..., :, 1], U[..., :, 2]
    w1, w2 = W[..., 0, 0, None], W[..., 1, 0, None]
    zero = np.zeros_like(u1)
    dm = np.stack([zero, -w1 * u3, w1 * u2, -w2 * u1], axis=-1)
    dd = np.stack([w2 * u3, zero, -w2 * u1, w1 * u2], axis=-1)
    return np.concatenate([dm, dd], axis=-2)


def line_residuals_and_jacobians_batch(
    K: np.ndarray, T_cam_world: np.ndarray, U: np.ndarray, W: np.ndarray, segments: np.ndarray,
    jacobians: bool = True,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(3,3), (N,4,4) or (4,4), (N,3,3) world, (N,2,2), (N,4) px -> r (N,2) px, J_pose (N,2,6), J_line (N,2,4).

    r is the paper's gamma (signed distances of the segment ends to the projected line); J_pose is w.r.t. xi in
    T_cam_world <- exp(xi) T_cam_world, J_line w.r.t. the orth_update delta of the world line. With
    jacobians=False the Jacobians are None and r is the same array, computed by the same operations.
    """
    r, later, _ = line_residuals_batch(K, T_cam_world, U, W, segments)
    return (r, *later()) if jacobians else (r, None, None)


def line_residuals_batch(
    K: np.ndarray, T_cam_world: np.ndarray, U: np.ndarray, W: np.ndarray, segments: np.ndarray,
) -> tuple[np.ndarray, Callable[[], tuple[np.ndarray, np.ndarray]], tuple[np.ndarray, np.ndarray]]:
    """line_residuals_and_jacobians_batch's r, a function that gives its (J_pose, J_line) from the quantities r was
    computed from (a trial step's cost needs r alone, and its Jacobians only once the step is accepted), and the
    lines in the camera frame, (d_c, m_c) (N,3) each."""
    U = np.asarray(U, dtype=float)
    W = np.asarray(W, dtype=float)
    seg = np.asarray(segments, dtype=float)
    n_obs = seg.shape[0]
    if seg.shape != (n_obs, 4) or U.shape != (n_obs, 3, 3) or W.shape != (n_obs, 2, 2):
        raise PlvoError(
            f"line_residuals_and_jacobians_batch: expected U (N,3,3), W (N,2,2), segments (N,4), "
            f"got {U.shape}, {W.shape}, {seg.shape}"
        )
    T = np.broadcast_to(np.asarray(T_cam_world, dtype=float), (n_obs, 4, 4))
    R, t = T[:, :3, :3], T[:, :3, 3]
    K_L = line_projection_matrix(K)

    L_w = orth_to_plucker(U, W)
    d_c = np.einsum("nij,nj->ni", R, L_w[:, 3:])
    m_c = np.einsum("nij,nj->ni", R, L_w[:, :3]) + cross3(t, d_c)
    l = m_c @ K_L.T

    ends = np.stack([seg[:, 0:2], seg[:, 2:4]], axis=1)  # (N,2,2)
    x = np.concatenate([ends, np.ones((n_obs, 2, 1))], axis=2)  # homogeneous endpoints (N,2,3)
    norm = np.hypot(l[:, 0], l[:, 1])
    r = np.einsum("nki,ni->nk", x, l) / norm[:, None]

    def jacobians() -> tuple[np.ndarray, np.ndarray]:
        grad_n = np.zeros_like(l)
        grad_n[:, :2] = l[:, :2] / norm[:, None]  # d|l_12|/dl
        dr_dl = (x - r[:, :, None] * grad_n[:, None, :]) / norm[:, None, None]
        dr_dm = dr_dl @ K_L  # (N,2,3)

        # m_c(xi) = m_c + rho x d_c + phi x m_c to first order.
        dm_dxi = np.concatenate([-hat_batch(d_c), -hat_batch(m_c)], axis=2)  # (N,3,6)
        J_pose = dr_dm @ dm_dxi

        dL = orth_plucker_jacobian(U, W)  # (N,6,4)
        dmc_dline = R @ dL[:, :3, :] + hat_batch(t) @ R @ dL[:, 3:, :]
        J_line = dr_dm @ dmc_dline
        return J_pose, J_line

    return r, jacobians, (d_c, m_c)


def line_residual_jacobians(
    K: np.ndarray, T_cam_world: np.ndarray, U: np.ndarray, W: np.ndarray, segment: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(3,3), (4,4), (3,3) world, (2,2), (4,) px -> r (2,) px, J_pose (2,6), J_line (2,4); see the batch form."""
    r, jp, jl = line_residuals_and_jacobians_batch(
        K,
        np.asarray(T_cam_world, dtype=float)[None],
        np.asarray(U, dtype=float)[None],
        np.asarray(W, dtype=float)[None],
        np.asarray(segment, dtype=float).reshape(1, 4),
    )
    assert jp is not None and jl is not None  # asked for (want_jacobians defaults to True)
    return r[0], jp[0], jl[0]


def point_line_distance_and_jacobian(
    points: np.ndarray, U: np.ndarray, W: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(N,3) points, (3,3),(2,2) line, same frame -> dist (N,) metres, J (N,4) w.r.t. the orth_update delta.

    At a point exactly on the line the distance is not differentiable; its Jacobian row is returned as zeros.
    """
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    L = orth_to_plucker(np.asarray(U, dtype=float), np.asarray(W, dtype=float))
    m, d = L[:3], L[3:]
    dL = orth_plucker_jacobian(U, W)
    dm, dd = dL[:3], dL[3:]
    nd = np.linalg.norm(d)
    e = cross3(pts, np.broadcast_to(d, pts.shape)) - m  # (N,3)
    ne = np.linalg.norm(e, axis=1)
    dist = ne / nd
    de = hat_batch(pts) @ dd - dm  # (N,3,4)
    safe = np.where(ne > 0, ne, 1.0)
    J = np.einsum("ni,nij->nj", e, de) / (safe * nd)[:, None] - (dist / nd**2)[:, None] * (d @ dd)[None, :]
    J[ne == 0] = 0.0
    return dist, J
