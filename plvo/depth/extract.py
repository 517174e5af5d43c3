"""Depth priors of one keyframe (paper, II-B): scan projection, point depths, line depths, and what a viewer shows.

`extract_depth_priors` is the pipeline's entry; `extract_depth` also returns a `DepthDebug` with the projected
scan, the searched patches, the fitted plane patches and per-stage timings, for the recorders (world/camera/image/
lidar, .../patches, world/depth/planes, world/depth/lines). Both work in the camera frame of `calib`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from plvo.config import DepthConfig
from plvo.depth.density import adapt_patches
from plvo.depth.lines import LineDepthResult, line_depths
from plvo.depth.points import PointDepthResult, point_depths
from plvo.depth.projection import ProjectedScan, project_scan
from plvo.errors import PlvoError
from plvo.types import Calibration, DepthPriors, FeatureSet

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DepthDebug:
    """What the viewer shows of a keyframe's depth extraction (camera frame, pixels).

    scan_uv (P,2) / scan_depth (P,): projected scan after the z-buffer; point_boxes (N,4) u0,v0,u1,v1 patch of each
    keypoint; line_bands (M,4,2) corner pixels of each segment's band; plane_quads (N,4,3) the fitted plane
    clipped to the patch's corner rays, NaN where no prior; point_foreground (N,) and line_inliers (M,) numbers of
    lidar points used; line_reproj_px (M,); timings_ms: stage -> milliseconds.
    """

    scan_uv: np.ndarray
    scan_depth: np.ndarray
    point_boxes: np.ndarray
    line_bands: np.ndarray
    plane_quads: np.ndarray
    point_foreground: np.ndarray
    line_inliers: np.ndarray
    line_reproj_px: np.ndarray
    timings_ms: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class DepthResult:
    priors: DepthPriors
    debug: DepthDebug


def extract_depth_priors(
    scan: np.ndarray, features: FeatureSet, calib: Calibration, cfg: DepthConfig
) -> DepthPriors:
    """(N,4) lidar-frame scan + FeatureSet -> DepthPriors in the camera frame of calib."""
    return extract_depth(scan, features, calib, cfg).priors


def extract_depth(scan: np.ndarray, features: FeatureSet, calib: Calibration, cfg: DepthConfig) -> DepthResult:
    """(N,4) lidar-frame scan + FeatureSet -> DepthResult (priors + viewer debug), camera frame of calib."""
    return extract_depth_arrays(scan, features.keypoints, features.segments, calib, cfg)


def extract_depth_arrays(
    scan: np.ndarray, keypoints: np.ndarray, segments: np.ndarray, calib: Calibration, cfg: DepthConfig
) -> DepthResult:
    """(N,4) lidar scan, (N,2) keypoints px, (M,4) segments px -> DepthResult, camera frame of calib."""
    kp = _as_array(keypoints, 2, "keypoints")
    seg = _as_array(segments, 4, "segments")
    t0 = time.perf_counter()
    proj = project_scan(scan, calib, cfg.min_depth_m, cfg.max_depth_m, cfg.grid_cell_px, cfg.zbuffer_px)
    cfg, scale = adapt_patches(cfg, proj)
    if scale != 1.0:
        log.debug("sparse scan: depth patches scaled %.2fx (point %d px, line %d px)", scale, cfg.point_patch_px,
                  cfg.line_patch_px)
    t1 = time.perf_counter()
    pr = point_depths(proj, kp, calib.K, cfg)
    t2 = time.perf_counter()
    lr = line_depths(proj, seg, calib.K, cfg)
    t3 = time.perf_counter()
    priors = DepthPriors(
        point_depth=pr.depth,
        point_reason=pr.reason,
        point_residual=pr.residual,
        point_inliers=pr.inliers,
        point_plane=pr.plane,
        line_endpoints=lr.endpoints,
        line_reason=lr.reason,
        line_residual=lr.residual,
        line_inliers=lr.inliers,
    )
    timings = {"projection": 1e3 * (t1 - t0), "points": 1e3 * (t2 - t1), "lines": 1e3 * (t3 - t2)}
    log.debug(
        "depth priors: %d/%d points, %d/%d lines, %.1f ms",
        int(priors.point_valid.sum()), len(kp), int(priors.line_valid.sum()), len(seg), sum(timings.values()),
    )
    return DepthResult(priors=priors, debug=_debug(proj, kp, seg, pr, lr, calib, cfg, timings))


def _as_array(a: np.ndarray, width: int, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=float)
    if arr.size == 0:
        return np.zeros((0, width))
    if arr.ndim != 2 or arr.shape[1] != width:
        raise PlvoError(f"extract_depth: field '{name}' must be (N,{width}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise PlvoError(f"extract_depth: field '{name}' contains NaN or inf")
    return arr


def _debug(
    proj: ProjectedScan,
    kp: np.ndarray,
    seg: np.ndarray,
    pr: PointDepthResult,
    lr: LineDepthResult,
    calib: Calibration,
    cfg: DepthConfig,
    timings: dict[str, float],
) -> DepthDebug:
    h = float(cfg.point_patch_px)
    boxes = np.concatenate([kp - h, kp + h], axis=1)
    return DepthDebug(
        scan_uv=proj.uv,
        scan_depth=proj.depth,
        point_boxes=boxes,
        line_bands=_band_corners(seg, float(cfg.line_patch_px)),
        plane_quads=_plane_quads(boxes, pr.plane, calib.K),
        point_foreground=pr.foreground.sum(axis=1),
        line_inliers=lr.inliers,
        line_reproj_px=lr.reproj_px,
        timings_ms=timings,
    )


def _band_corners(seg: np.ndarray, half: float) -> np.ndarray:
    """(M,4) segments -> (M,4,2) corners of the band of half-width `half` around each."""
    a, b = seg[:, :2], seg[:, 2:]
    d = b - a
    n = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    off = half * n
    return np.stack([a + off, b + off, b - off, a - off], axis=1)


def _plane_quads(boxes: np.ndarray, plane: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N,4) patch boxes, (N,4) planes -> (N,4,3) the plane cut by the rays of the box corners (NaN if none)."""
    corners = np.stack(
        [boxes[:, [0, 1]], boxes[:, [2, 1]], boxes[:, [2, 3]], boxes[:, [0, 3]]], axis=1
    )  # (N,4,2)
    rays = np.stack(
        [(corners[..., 0] - K[0, 2]) / K[0, 0], (corners[..., 1] - K[1, 2]) / K[1, 1], np.ones(corners.shape[:2])],
        axis=-1,
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        z = -plane[:, None, 3] / np.einsum("nki,ni->nk", rays, plane[:, :3])
    z = np.where(z > 0, z, np.nan)
    return rays * z[..., None]
