"""Typed data passed between stages: frames, calibration, features, depth priors.

Conventions (see README): `T_a_b` maps points in frame b into frame a; camera frames are OpenCV's (x right,
y down, z forward); metres and radians; pixels (N,2) float64; 2D segments (N,4) as x1,y1,x2,y2; 3D points (N,3).
Stage results are frozen dataclasses holding numpy arrays; treat the arrays as read-only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Calibration:
    """Pinhole camera and lidar extrinsics of one sequence.

    K: (3,3) intrinsics of the chosen camera. T_cam_velo: (4,4) lidar -> camera. width, height: image size (px).
    T_cam0_cam: (4,4) chosen camera -> cam0 (identity for cam0; poses are always reported for cam0).
    lidar_elevation_offset_deg: the lidar's vertical-angle error, by which scan registration raises every return
    (0.205 for KITTI's HDL-64E, see plvo.lidar.registration; 0 for the synthetic town).
    """

    K: np.ndarray
    T_cam_velo: np.ndarray
    width: int
    height: int
    T_cam0_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    lidar_elevation_offset_deg: float = 0.0

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])


@dataclass(frozen=True)
class Frame:
    """One synchronised camera image and lidar scan.

    image: (H,W) uint8 grayscale. scan: (N,4) float32 x,y,z,reflectance in the lidar frame.
    gt_T_world_cam: (4,4) ground-truth pose of the camera in the world (cam0 of frame 0), or None.
    color: (H,W,3) uint8 RGB of the same (rectified) image when the source is a colour camera, else None; only
    viewers use it, the pipeline works on `image`. scan_time: (N,) float64 seconds of each return relative to the
    frame's `time` when the source records it (ROS PointCloud2 `t`/`time` fields), else None. scan_compensated:
    False when each return is in the sensor frame at its own time within the sweep (a spinning lidar's raw scan:
    the twins', KITTI raw's, a bag's with per-point times), so that registration should deskew it first
    (plvo.lidar.deskew); True when the source delivers it motion-compensated or taken at one instant.
    features: the tracker's features of `image`, extracted ahead of tracking by `System.prepare` (while earlier
    frames are tracked), with features_s the seconds it took; None: the tracker extracts them itself.
    """

    index: int
    time: float
    image: np.ndarray
    scan: np.ndarray
    calib: Calibration
    gt_T_world_cam: np.ndarray | None = None
    color: np.ndarray | None = None
    scan_time: np.ndarray | None = None
    scan_compensated: bool = True
    features: FeatureSet | None = None
    features_s: float = 0.0


@dataclass(frozen=True)
class FeatureSet:
    """Point and line features of one image.

    keypoints: (N,2) pixel positions; kp_octave (N,) int; kp_angle (N,) degrees as OpenCV gives them;
    kp_response (N,); descriptors: (N,32) uint8 ORB.
    segments: (M,4) repaired LSD segments (chained and merged, >= min length); line_descriptors: (M,32) uint8 LBD.
    raw_segments: (R,4) LSD output before repair; segment_sources: for each repaired segment, the indices of the
    raw segments it came from.
    """

    keypoints: np.ndarray
    kp_octave: np.ndarray
    kp_angle: np.ndarray
    kp_response: np.ndarray
    descriptors: np.ndarray
    segments: np.ndarray
    line_descriptors: np.ndarray
    raw_segments: np.ndarray
    segment_sources: tuple[np.ndarray, ...]
    image_size: tuple[int, int]  # (width, height)

    @property
    def n_points(self) -> int:
        return int(len(self.keypoints))

    @property
    def n_lines(self) -> int:
        return int(len(self.segments))


@dataclass(frozen=True)
class Matches:
    """Index pairs between two feature sets. pairs: (K,2) int (index in prev, index in cur); distance: (K,)."""

    pairs: np.ndarray
    distance: np.ndarray

    def __len__(self) -> int:
        return int(len(self.pairs))


@dataclass(frozen=True)
class FeatureMatches:
    points: Matches
    lines: Matches


# Reasons a feature gets no depth prior (DepthPriors.*_reason); 0 means it has one.
DEPTH_OK = 0
DEPTH_TOO_FEW_POINTS = 1
DEPTH_BAD_FIT = 2
DEPTH_GRAZING_RAY = 3
DEPTH_OUT_OF_RANGE = 4
DEPTH_NOT_CONVERGED = 5
DEPTH_REASONS = {
    DEPTH_OK: "ok",
    DEPTH_TOO_FEW_POINTS: "too few lidar points in the patch",
    DEPTH_BAD_FIT: "plane or line fit too poor",
    DEPTH_GRAZING_RAY: "ray nearly parallel to the fitted plane",
    DEPTH_OUT_OF_RANGE: "depth out of range",
    DEPTH_NOT_CONVERGED: "line fit did not converge",
}


@dataclass(frozen=True)
class DepthPriors:
    """Depth priors of one keyframe's features, in the camera frame.

    point_depth: (N,) metres along z, NaN where none; point_reason: (N,) int (DEPTH_*); point_residual: (N,) plane
    RMS (m); point_inliers: (N,) int; point_plane: (N,4) plane n.x + d = 0 in the camera frame (NaN where none).
    line_endpoints: (M,2,3) trimmed 3D endpoints in the camera frame, NaN where none; line_reason (M,) int;
    line_residual: (M,) RMS point-to-line distance (m); line_inliers: (M,) int.
    """

    point_depth: np.ndarray
    point_reason: np.ndarray
    point_residual: np.ndarray
    point_inliers: np.ndarray
    point_plane: np.ndarray
    line_endpoints: np.ndarray
    line_reason: np.ndarray
    line_residual: np.ndarray
    line_inliers: np.ndarray

    @property
    def point_valid(self) -> np.ndarray:
        return self.point_reason == DEPTH_OK

    @property
    def line_valid(self) -> np.ndarray:
        return self.line_reason == DEPTH_OK
