"""KISS-ICP run exactly as plvo_eval.kiss runs it (the same scans, deskew, options and poses), with what each
registration saw and left, as statistics to set beside another run's (plvo_eval.stage_report).

Per frame after the first (the first aligns to an empty map):
- `kiss_scan_points`: the returns left after its range crop (and deskew), which go into its map;
- `kiss_source_points`: the returns it registers (downsampled at 1.5 voxels);
- `kiss_threshold_m`: its adaptive threshold sigma (the correspondence distance is 3 sigma, the kernel sigma);
- `kiss_residual_m`: the median distance of the registered source points to their nearest point of the local map
  as it stood for this registration (before the scan joined it): how well the scan fits what it was aligned to;
- `kiss_inlier_share`: the share of source points within the correspondence distance of a map point;
- `kiss_plane_residual_m`: the median distance of those points to the plane of their nearest map points (what a
  point-to-plane alignment such as plvo's e_bar measures; the nearest-point distance is mostly the map's sampling);
- `kiss_correction_m`, `kiss_correction_deg`: how far the registration moved the constant-velocity prediction (the
  model deviation its adaptive threshold learns from).
With ground truth, its heading and scale drift over consecutive frames (plvo_eval.stage_drift's "final" stage;
KISS-ICP has no other).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from plvo.data.dataset import Dataset
from plvo.errors import PlvoError
from plvo.geometry import se3
from plvo.results import StageSteps
from plvo_eval.kiss import (
    KissOptions,
    KissOutput,
    _scan_points,
    kitti_corrector,
    lidar_to_cam0,
    make_config,
    sweep_end_to_frame_time,
    timed_scan_reader,
)
from plvo_eval.stage_drift import stage_drift
from plvo_eval.stage_stats import describe, drift_stats

log = logging.getLogger(__name__)

KISS_FIELDS = ("scan_points", "source_points", "threshold_m", "residual_m", "inlier_share", "plane_residual_m",
               "correction_m", "correction_deg")
PLANE_NEIGHBOURS = 8  # map points a source point's local plane is fitted to (within ~1 m in KISS-ICP's map)


class _Probe:
    """Stands in for KissICP's registration: aligns as it does and keeps what the alignment was given (the local
    map's points before the scan joins them, the correspondence distance, the prediction) and its pose."""

    def __init__(self, inner: Any):
        self.inner = inner
        self.seen: tuple[np.ndarray, np.ndarray, float, np.ndarray] | None = None

    def align_points_to_map(self, points: np.ndarray, voxel_map: Any, initial_guess: np.ndarray,
                            max_correspondance_distance: float, kernel: float) -> np.ndarray:
        pose = self.inner.align_points_to_map(points=points, voxel_map=voxel_map, initial_guess=initial_guess,
                                              max_correspondance_distance=max_correspondance_distance, kernel=kernel)
        self.seen = (voxel_map.point_cloud(), np.asarray(pose, np.float64), float(max_correspondance_distance),
                     np.asarray(initial_guess, np.float64))
        return pose


def registration_fit(source: np.ndarray, T_world_lidar: np.ndarray, map_points: np.ndarray,
                     max_distance_m: float) -> tuple[float, float, float]:
    """Source points (N,3, lidar frame) registered at T_world_lidar (4,4), the map's points (M,3, world) and the
    correspondence distance -> (median nearest-map-point distance m, share within max_distance_m, median distance
    of those within it to the plane of their PLANE_NEIGHBOURS nearest map points, m); NaN without map or source.

    The nearest-point distance is mostly the map's sampling (a 0.5 m grid); the plane distance is what a
    point-to-plane registration (plvo's e_bar) measures, and shows the surfaces' noise."""
    nan = float("nan")
    if len(source) == 0 or len(map_points) < PLANE_NEIGHBOURS:
        return nan, nan, nan
    points = se3.transform_points(T_world_lidar, source)
    d, idx = cKDTree(map_points).query(points, k=PLANE_NEIGHBOURS)
    near = d[:, 0] < max_distance_m
    plane = nan
    if near.any():
        nb = map_points[idx[near]]  # (n,k,3)
        centred = nb - nb.mean(axis=1, keepdims=True)
        normal = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))[1][:, :, 0]
        plane = float(np.median(np.abs(np.einsum("ni,ni->n", points[near] - nb.mean(axis=1), normal))))
    return float(np.median(d[:, 0])), float(np.mean(near)), plane


def run_kiss_stats(dataset: Dataset, options: KissOptions | None = None) -> tuple[KissOutput, dict[str, np.ndarray]]:
    """Dataset's scans -> (KISS-ICP's output, as plvo_eval.kiss.run_kiss gives it; per frame each of KISS_FIELDS,
    (N,), NaN at the first frame where it has no meaning)."""
    from kiss_icp.kiss_icp import KissICP

    options = options or KissOptions()
    if len(dataset) == 0:
        raise PlvoError(f"sequence {dataset.sequence}: no frames for KISS-ICP")
    odometry = KissICP(config=make_config(options))
    probe = _Probe(odometry.registration)
    odometry.registration = probe
    n = len(dataset)
    lidar_poses, seconds = np.zeros((n, 4, 4)), np.zeros(n)
    per_frame = {k: np.full(n, np.nan) for k in KISS_FIELDS}
    back = np.tile(np.eye(4), (n, 1, 1))
    read, no_times = timed_scan_reader(dataset), np.zeros(0)
    correct = kitti_corrector() if options.kitti_correction else None
    started_at = time.perf_counter()
    for i in range(n):
        scan, times = read(i)
        points = _scan_points(dataset, scan, i, correct)
        stamps = times if options.deskew and times is not None else no_times
        back[i] = sweep_end_to_frame_time(stamps, odometry.last_delta)
        t0 = time.perf_counter()
        frame, source = odometry.register_frame(points, stamps)
        seconds[i] = time.perf_counter() - t0
        lidar_poses[i] = odometry.last_pose
        if i == 0 or probe.seen is None:
            continue
        map_points, pose, max_distance, guess = probe.seen
        residual, share, plane = registration_fit(np.asarray(source), pose, map_points, max_distance)
        deviation = se3.inv(guess) @ pose
        values = (len(frame), len(source), max_distance / 3.0, residual, share, plane,
                  float(np.linalg.norm(deviation[:3, 3])), float(np.degrees(se3.rotation_angle(deviation))))
        for key, value in zip(KISS_FIELDS, values):
            per_frame[key][i] = value
    finished_at = time.perf_counter()
    lidar_poses = lidar_poses @ back
    calib = dataset.calib
    T_cam0_velo = np.asarray(calib.T_cam0_cam) @ np.asarray(calib.T_cam_velo)
    poses = lidar_to_cam0(lidar_poses, T_cam0_velo)
    poses = np.linalg.inv(poses[0]) @ poses
    return KissOutput(poses, lidar_poses, seconds, started_at, finished_at), per_frame


def kiss_summary(per_frame: dict[str, np.ndarray], frame_indices: Any = None, gt_cam0: np.ndarray | None = None,
                 est_cam0: np.ndarray | None = None) -> dict[str, dict[str, Any]]:
    """Per-frame figures of run_kiss_stats -> statistic name -> plvo_eval.stage_stats.describe entry; with the
    frames' numbers and ground-truth and estimated cam0 poses (N,4,4) also its drift over consecutive frames."""
    units = {"scan_points": "returns a frame", "source_points": "returns a frame", "threshold_m": "m a frame",
             "residual_m": "m a frame (median over its points)", "inlier_share": "share a frame",
             "plane_residual_m": "m a frame (median over its points)",
             "correction_m": "m a frame", "correction_deg": "deg a frame"}
    out = {f"kiss_{k}": describe(per_frame[k], "KISS-ICP registration", units[k]) for k in KISS_FIELDS}
    if gt_cam0 is not None and est_cam0 is not None and frame_indices is not None:
        frames = [int(f) for f in frame_indices]
        steps = [StageSteps((a, b), {}) for a, b in zip(frames[:-1], frames[1:])]
        out.update(drift_stats({"final": stage_drift(steps, frames, gt_cam0, est_cam0)["final"]}))
    return out
