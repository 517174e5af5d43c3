"""Point depth priors: foreground plane of the patch's lidar points, intersected with the feature's ray.

Batched over features: the patch points are gathered into padded (Q,P) arrays and every step (segmentation, the
weighted plane fits, the inlier refit, the ray-plane intersection, the checks) is one numpy pass over all patches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plvo.config import DepthConfig
from plvo.depth.projection import ProjectedScan, query_patches, to_padded
from plvo.depth.segmentation import depth_clusters, fit_planes_xyz, foreground_mask, grow_foreground_xyz
from plvo.types import (
    DEPTH_BAD_FIT,
    DEPTH_GRAZING_RAY,
    DEPTH_OK,
    DEPTH_OUT_OF_RANGE,
    DEPTH_TOO_FEW_POINTS,
)


@dataclass(frozen=True)
class PointDepthResult:
    """Per keypoint (N rows). depth (N,) z in metres, NaN where none; reason (N,) DEPTH_*; residual (N,) plane RMS
    (m); inliers (N,) int; plane (N,4) n.x + d = 0 camera frame, NaN where none; patch_index (N,P) indices into the
    ProjectedScan (-1 padding); foreground (N,P) bool, the segmented foreground; inlier_mask (N,P) bool."""

    depth: np.ndarray
    reason: np.ndarray
    residual: np.ndarray
    inliers: np.ndarray
    plane: np.ndarray
    patch_index: np.ndarray
    foreground: np.ndarray
    inlier_mask: np.ndarray


def point_depths(proj: ProjectedScan, keypoints: np.ndarray, K: np.ndarray, cfg: DepthConfig) -> PointDepthResult:
    """(N,2) pixel keypoints + projected scan -> PointDepthResult (camera frame of the scan's projection)."""
    kp = np.asarray(keypoints, dtype=float).reshape(-1, 2)
    N = len(kp)
    owner, idx = query_patches(proj, kp, float(cfg.point_patch_px))
    pidx, count = to_padded(owner, idx, N)
    if len(proj) == 0 or N == 0:
        return _no_depth(N, pidx.shape[1])
    X, Y, Z, U, V = proj.gather_columns(pidx)  # (N,P) each, zeros on padding
    depth = np.where(pidx >= 0, Z, np.nan)
    rays = np.stack([(kp[:, 0] - K[0, 2]) / K[0, 0], (kp[:, 1] - K[1, 2]) / K[1, 1], np.ones(N)], axis=1)
    unit = rays / np.linalg.norm(rays, axis=1, keepdims=True)

    labels = depth_clusters(depth, cfg.depth_jump_ratio, cfg.depth_jump_min_m)
    # Bridging tolerates slanter planes than a prior does, so that a slanted road is reported as grazing rather
    # than as a bad fit; a thin occluder joined with the wall behind it gives a far slanter plane still.
    k_sel = grow_foreground_xyz(X, Y, Z, labels, unit, cfg.plane_max_rms_m, 0.5 * cfg.min_ray_plane_cos)
    fg = foreground_mask(labels, k_sel)
    n, d, inl, rms, eig, c = _robust_plane(X, Y, Z, U - kp[:, 0, None], V - kp[:, 1, None], fg, cfg)
    # A strip of points barely wider than the range noise (a thin pole, a patch on an object's edge) leaves the
    # plane's tilt across the strip to the noise: take the plane facing the camera through the centroid.
    with np.errstate(invalid="ignore"):
        ill = np.sqrt(eig[:, 0]) > cfg.plane_max_flatness * np.sqrt(eig[:, 1])
    n = np.where(ill[:, None], -unit, n)
    d = np.where(ill, np.einsum("qi,qi->q", unit, c), d)

    denom = np.einsum("qi,qi->q", n, rays)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = -d / denom
        cos = np.abs(denom) / np.linalg.norm(rays, axis=1)
        # The inliers must span two directions: one scan ring alone leaves the plane's tilt unknown.
        eig_spread = np.sqrt(eig[:, 1]) >= 0.1 * np.sqrt(eig[:, 2])
        zmin = np.min(np.where(inl, depth, np.inf), axis=1)
        zmax = np.max(np.where(inl, depth, -np.inf), axis=1)
        tol = np.maximum(cfg.depth_jump_min_m, cfg.depth_jump_ratio * zmax)
    n_fg, n_inl = np.count_nonzero(fg, axis=1), np.count_nonzero(inl, axis=1)

    reason = np.full(N, DEPTH_OK, dtype=np.int64)
    out_of_range = ~((z > 0) & (z <= cfg.max_depth_m) & (z >= zmin - tol) & (z <= zmax + tol))
    reason[out_of_range] = DEPTH_OUT_OF_RANGE
    reason[~(cos >= cfg.min_ray_plane_cos)] = DEPTH_GRAZING_RAY
    bad_fit = ~(rms <= cfg.plane_max_rms_m) | ~eig_spread | (n_inl < cfg.min_inlier_fraction * n_fg)
    reason[bad_fit] = DEPTH_BAD_FIT
    reason[(count < cfg.min_points) | (n_fg < cfg.min_points) | (n_inl < cfg.min_points)] = DEPTH_TOO_FEW_POINTS
    ok = reason == DEPTH_OK
    plane = np.concatenate([n, d[:, None]], axis=1)
    plane[~ok] = np.nan
    return PointDepthResult(
        depth=np.where(ok, z, np.nan),
        reason=reason,
        residual=rms,
        inliers=n_inl.astype(np.int64),
        plane=plane,
        patch_index=pidx,
        foreground=fg,
        inlier_mask=inl,
    )


def _robust_plane(
    X: np.ndarray, Y: np.ndarray, Z: np.ndarray, du: np.ndarray, dv: np.ndarray, fg: np.ndarray, cfg: DepthConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reweighted fits on the foreground: inliers within plane_inlier_m, weighted towards the feature pixel.

    X, Y, Z: (Q,P) camera coordinates; du, dv: (Q,P) pixel offsets from the feature; fg: (Q,P) foreground.
    -> normals (Q,3), offsets (Q,), inlier mask (Q,P), inlier RMS distance (Q,), eigenvalues (Q,3) and
    centroids (Q,3) of the last fit.
    """
    sigma = max(float(cfg.point_patch_px), 1.0)
    # Points near the feature pixel count more, so at a concave fold the face under the feature wins.
    prox = np.exp((du * du + dv * dv) * (-0.5 / sigma**2))
    w = np.where(fg, prox, 0.0)
    for _ in range(2):
        n, d, eig, c = fit_planes_xyz(X, Y, Z, w)
        dist = np.abs(X * n[:, 0, None] + Y * n[:, 1, None] + Z * n[:, 2, None] + d[:, None])
        inl = fg & (dist <= cfg.plane_inlier_m)
        w = np.where(inl, prox, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(np.einsum("qp,qp->q", np.where(inl, dist, 0.0), np.where(inl, dist, 0.0))
                      / np.count_nonzero(inl, axis=1))
    return n, d, inl, rms, eig, c


def _no_depth(N: int, P: int) -> PointDepthResult:
    """Every feature without a prior (empty scan or no features)."""
    nan = np.full(N, np.nan)
    return PointDepthResult(
        depth=nan,
        reason=np.full(N, DEPTH_TOO_FEW_POINTS, dtype=np.int64),
        residual=nan.copy(),
        inliers=np.zeros(N, dtype=np.int64),
        plane=np.full((N, 4), np.nan),
        patch_index=np.full((N, P), -1, dtype=np.int64),
        foreground=np.zeros((N, P), dtype=bool),
        inlier_mask=np.zeros((N, P), dtype=bool),
    )
