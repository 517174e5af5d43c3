"""Camera pose from 3D-2D point and line correspondences: PnP + PnL in LO-RANSAC (poselib), refined on inliers.

poselib works with the world -> camera pose (R, t) = T_cam_world; everything here returns T_world_cam.
poselib 2.0.5 takes both RANSAC thresholds in pixels (`max_reproj_error` for points, `max_epipolar_error` for
the endpoint-to-line distance of lines) and scales them by the focal length itself. Its 3D lines are two points
on the line; its 2D lines are the observed segment's endpoints, whose distances to the projected line are the
residuals (the paper's line reprojection error, II-E).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import poselib

from plvo.config import TrackingConfig
from plvo.geometry import se3

log = logging.getLogger(__name__)

# Fewer usable correspondences than this and no pose is attempted (a minimal sample is 3).
MIN_CORRESPONDENCES = 4
# The refined prediction is kept over RANSAC's pose unless RANSAC explains more than 1 / 0.9 as many matches.
PREDICTION_MARGIN = 0.9
# poselib 2.0.5's PnPL RANSAC (points with lines; points alone are exact) returns poses that differ in the last bits
# between calls with the same input and seed: 30 calls on one town frame gave 30 poses, up to 2e-9 apart. Amplified
# by the rest of the pipeline, a sequence's trajectory depended on what the process had run before it (the second
# of two runs of town 21 in one process ended 1.6 cm from the first; `plvo eval run` reuses its worker processes).
# Refined on its inliers the pose differs by ~1e-13 between calls; it is snapped to this grid (tangent space, m and
# rad), far below any noise and far above those differences, so that runs repeat exactly.
_SNAP = 1e-6


@dataclass(frozen=True)
class PnPLResult:
    """Pose of one frame from 3D-2D matches.

    T_world_cam: (4,4) (the initial guess, or identity, when success is False). point_inliers (N,) and
    line_inliers (M,) bool after the final reprojection check. point_residuals (N,) px reprojection distance,
    line_residuals (M,) px larger endpoint-to-line distance (inf where not computable). n_iterations: RANSAC
    iterations. used_initial: the initial guess beat RANSAC's hypotheses.
    """

    T_world_cam: np.ndarray
    point_inliers: np.ndarray
    line_inliers: np.ndarray
    n_iterations: int
    success: bool
    message: str
    point_residuals: np.ndarray
    line_residuals: np.ndarray
    used_initial: bool = False

    @property
    def n_inliers(self) -> int:
        return int(self.point_inliers.sum() + self.line_inliers.sum())


def _camera_dict(K: np.ndarray) -> dict:
    # poselib only needs the intrinsics; width/height are unused by the PINHOLE model.
    return {"model": "PINHOLE", "width": 0, "height": 0, "params": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]}


def _to_poselib(T_world_cam: np.ndarray) -> poselib.CameraPose:
    T_cam_world = se3.inv(T_world_cam)
    pose = poselib.CameraPose()
    pose.R = T_cam_world[:3, :3]
    pose.t = T_cam_world[:3, 3]
    return pose


def _from_poselib(pose: poselib.CameraPose) -> np.ndarray:
    return se3.inv(se3.from_rt(np.asarray(pose.R), np.asarray(pose.t)))


def point_residuals(K: np.ndarray, T_world_cam: np.ndarray, pts_world: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N,3) world points, (N,2) pixels -> (N,) reprojection distance in px; inf behind the camera."""
    if len(pts_world) == 0:
        return np.zeros(0)
    pc = se3.transform_points(se3.inv(T_world_cam), pts_world)
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = pc[:, :2] / z[:, None] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
        err = np.linalg.norm(proj - uv, axis=1)
    err[~(z > 1e-6) | ~np.isfinite(err)] = np.inf
    return err


def line_residuals(K: np.ndarray, T_world_cam: np.ndarray, lines_world: np.ndarray,
                   segments: np.ndarray) -> np.ndarray:
    """(M,2,3) world endpoints, (M,4) segments -> (M,) larger endpoint-to-projected-line distance in px.

    The image line is the plane through the camera centre and the 3D line, so it stays valid when one endpoint
    has moved behind the camera; lines wholly behind it get inf.
    """
    if len(lines_world) == 0:
        return np.zeros(0)
    T_cam_world = se3.inv(T_world_cam)
    A = se3.transform_points(T_cam_world, lines_world[:, 0])
    B = se3.transform_points(T_cam_world, lines_world[:, 1])
    l_norm = np.cross(A, B)  # line in normalised image coordinates
    l_px = l_norm @ np.linalg.inv(K)  # l_px = K^-T l_norm, row-wise
    norm = np.linalg.norm(l_px[:, :2], axis=1)
    p1 = np.c_[segments[:, 0:2], np.ones(len(segments))]
    p2 = np.c_[segments[:, 2:4], np.ones(len(segments))]
    with np.errstate(divide="ignore", invalid="ignore"):
        d1 = np.abs(np.sum(l_px * p1, axis=1)) / norm
        d2 = np.abs(np.sum(l_px * p2, axis=1)) / norm
    err = np.maximum(d1, d2)
    in_front = (A[:, 2] > 1e-6) | (B[:, 2] > 1e-6)
    err[~in_front | ~np.isfinite(err)] = np.inf
    return err


def _valid_inputs(pts_world: np.ndarray, uv: np.ndarray, lines_world: np.ndarray,
                  segments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pv = np.isfinite(pts_world).all(axis=1) & np.isfinite(uv).all(axis=1)
    lv = np.isfinite(lines_world).reshape(len(lines_world), 6).all(axis=1) & np.isfinite(segments).all(axis=1)
    if len(lines_world):
        # A 3D line needs two distinct points, a 2D line two distinct endpoints.
        lv &= np.linalg.norm(lines_world[:, 1] - lines_world[:, 0], axis=1) > 1e-6
        lv &= np.linalg.norm(segments[:, 2:] - segments[:, :2], axis=1) > 1e-3
    return pv, lv


def _check_shapes(pts_world: np.ndarray, uv: np.ndarray, lines_world: np.ndarray, segments: np.ndarray) -> None:
    if pts_world.shape != (len(uv), 3) or uv.shape != (len(pts_world), 2):
        raise ValueError(f"solve_pnpl: pts_world {pts_world.shape} and uv {uv.shape} must be (N,3) and (N,2)")
    if lines_world.shape != (len(segments), 2, 3) or segments.shape != (len(lines_world), 4):
        raise ValueError(
            f"solve_pnpl: lines_world {lines_world.shape} and segments {segments.shape} must be (M,2,3) and (M,4)"
        )


def _ransac(K: np.ndarray, P: np.ndarray, uv: np.ndarray, L: np.ndarray, S: np.ndarray, init: np.ndarray | None,
            cfg: TrackingConfig) -> tuple[np.ndarray, int]:
    """Run poselib's RANSAC on the valid subset; returns (T_world_cam, n_iterations)."""
    ransac_opt = {
        "max_reproj_error": float(cfg.ransac_reproj_px),
        "max_epipolar_error": float(cfg.ransac_line_px),
        "max_iterations": int(cfg.ransac_iterations),
        "min_iterations": min(50, int(cfg.ransac_iterations)),
        "success_prob": 0.9999,
        "seed": int(cfg.ransac_seed),
    }
    bundle_opt = {"loss_type": "CAUCHY", "loss_scale": 0.5 * float(cfg.ransac_reproj_px), "max_iterations": 50}
    initial = _to_poselib(init) if init is not None else None
    if len(L) == 0:
        pose, info = poselib.estimate_absolute_pose(uv, P, _camera_dict(K), ransac_opt, bundle_opt, initial)
    else:
        pose, info = poselib.estimate_absolute_pose_pnpl(
            uv.reshape(-1, 2), P.reshape(-1, 3), S[:, :2], S[:, 2:], L[:, 0], L[:, 1],
            _camera_dict(K), ransac_opt, bundle_opt, initial,
        )
    return _from_poselib(pose), int(info["iterations"])


def _refine(K: np.ndarray, T: np.ndarray, P: np.ndarray, uv: np.ndarray, L: np.ndarray, S: np.ndarray,
            cfg: TrackingConfig) -> np.ndarray:
    """Non-linear refinement of T_world_cam on the given (inlier) correspondences."""
    bundle_opt = {"loss_type": "HUBER", "loss_scale": float(cfg.outlier_reproj_px), "max_iterations": 50}
    pose, _ = poselib.refine_absolute_pose_pnpl(
        uv.reshape(-1, 2), P.reshape(-1, 3), S[:, :2].reshape(-1, 2), S[:, 2:].reshape(-1, 2),
        L[:, 0].reshape(-1, 3), L[:, 1].reshape(-1, 3), _to_poselib(T), _camera_dict(K), bundle_opt, {},
    )
    return _from_poselib(pose)


def snap_pose(T: np.ndarray) -> np.ndarray:
    """T_world_cam on the _SNAP grid of its tangent (see _SNAP)."""
    return se3.exp(np.round(se3.log(T) / _SNAP) * _SNAP)


def _failure(N: int, M: int, init: np.ndarray | None, message: str) -> PnPLResult:
    T = np.eye(4) if init is None else np.array(init, dtype=float)
    return PnPLResult(T, np.zeros(N, bool), np.zeros(M, bool), 0, False, message,
                      np.full(N, np.inf), np.full(M, np.inf))


def solve_pnpl(
    K: np.ndarray,
    pts_world: np.ndarray,
    uv: np.ndarray,
    lines_world: np.ndarray,
    segments: np.ndarray,
    T_world_cam_init: np.ndarray | None,
    cfg: TrackingConfig,
) -> PnPLResult:
    """World points (N,3) + pixels (N,2), world line endpoints (M,2,3) + segments (M,4) -> T_world_cam (4,4).

    RANSAC over points and lines (points only when M == 0 or cfg.points_only), then the pose is refined on the
    matches it explains, every match is reprojected (points > cfg.outlier_reproj_px, lines with an endpoint
    farther than that from the projected line are outliers), and refined once more on the survivors. The initial
    guess (the motion prediction) is refined the same way and kept unless RANSAC's pose explains clearly more
    matches (PREDICTION_MARGIN). success is False, without raising, when fewer than cfg.min_pnp_inliers matches
    survive or too few were given.
    """
    K = np.asarray(K, dtype=float)
    pts_world = np.asarray(pts_world, dtype=float).reshape(-1, 3)
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    lines_world = np.asarray(lines_world, dtype=float).reshape(-1, 2, 3)
    segments = np.asarray(segments, dtype=float).reshape(-1, 4)
    _check_shapes(pts_world, uv, lines_world, segments)
    N, M = len(pts_world), len(lines_world)
    pv, lv = _valid_inputs(pts_world, uv, lines_world, segments)
    if cfg.points_only:
        lv[:] = False
    if pv.sum() + lv.sum() < MIN_CORRESPONDENCES:
        return _failure(N, M, T_world_cam_init, f"too few correspondences ({pv.sum()} points, {lv.sum()} lines)")

    P, U, L, S = pts_world[pv], uv[pv], lines_world[lv], segments[lv]
    T, n_iter = _ransac(K, P, U, L, S, T_world_cam_init, cfg)
    T, n_best = _refine_on_inliers(K, T, P, U, L, S, cfg)
    T = snap_pose(T)
    used_initial = False
    if T_world_cam_init is not None:
        # RANSAC can settle on a wrong pose that explains a few more matches when they are few and far away
        # (a lateral shift looks like a yaw). The motion prediction is a strong prior at 10 Hz: refined on its own
        # inliers, it wins unless RANSAC explains clearly more matches.
        T_init, n_init = _refine_on_inliers(K, np.array(T_world_cam_init, dtype=float), P, U, L, S, cfg)
        if n_init >= PREDICTION_MARGIN * n_best:
            used_initial = not np.allclose(T_init, T, atol=1e-6)
            T = T_init

    thr = float(cfg.outlier_reproj_px)
    pres = np.full(N, np.inf)
    lres = np.full(M, np.inf)
    pres[pv] = point_residuals(K, T, P, U)
    lres[lv] = line_residuals(K, T, L, S)
    point_inliers = pv & (pres < thr)
    line_inliers = lv & (lres < thr)
    n_in = int(point_inliers.sum() + line_inliers.sum())
    if n_in < cfg.min_pnp_inliers:
        res = _failure(N, M, T_world_cam_init, f"only {n_in} inliers (need {cfg.min_pnp_inliers})")
        return PnPLResult(res.T_world_cam, point_inliers, line_inliers, n_iter, False, res.message, pres, lres,
                          used_initial)
    msg = f"{int(point_inliers.sum())}/{N} point and {int(line_inliers.sum())}/{M} line inliers"
    return PnPLResult(T, point_inliers, line_inliers, n_iter, True, msg, pres, lres, used_initial)


def refine_pose(K: np.ndarray, T_world_cam: np.ndarray, pts_world: np.ndarray, uv: np.ndarray,
                lines_world: np.ndarray, segments: np.ndarray, cfg: TrackingConfig
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refine a (4,4) T_world_cam on (N,3)/(N,2) points and (M,2,3)/(M,4) lines without RANSAC (the pose must be
    close already) -> (T_world_cam, point inliers (N,) bool, line inliers (M,) bool at cfg.outlier_reproj_px)."""
    P = np.asarray(pts_world, dtype=float).reshape(-1, 3)
    U = np.asarray(uv, dtype=float).reshape(-1, 2)
    L = np.asarray(lines_world, dtype=float).reshape(-1, 2, 3)
    S = np.asarray(segments, dtype=float).reshape(-1, 4)
    if cfg.points_only:
        L, S = L[:0], S[:0]
    T, _ = _refine_on_inliers(K, np.array(T_world_cam, dtype=float), P, U, L, S, cfg)
    thr = float(cfg.outlier_reproj_px)
    lin = np.zeros(len(lines_world), bool)
    lin[: len(L)] = line_residuals(K, T, L, S) < thr
    return T, point_residuals(K, T, P, U) < thr, lin


def _refine_on_inliers(K: np.ndarray, T: np.ndarray, P: np.ndarray, U: np.ndarray, L: np.ndarray, S: np.ndarray,
                       cfg: TrackingConfig) -> tuple[np.ndarray, int]:
    """Refine T on the matches within cfg.outlier_reproj_px, recheck them, once more; -> (T, inlier count)."""
    thr = float(cfg.outlier_reproj_px)
    n = 0
    for _ in range(2):
        pin = point_residuals(K, T, P, U) < thr
        lin = line_residuals(K, T, L, S) < thr
        n = int(pin.sum() + lin.sum())
        if n < MIN_CORRESPONDENCES:
            return T, n
        T = _refine(K, T, P[pin], U[pin], L[lin], S[lin], cfg)
    n = int((point_residuals(K, T, P, U) < thr).sum() + (line_residuals(K, T, L, S) < thr).sum())
    return T, n
