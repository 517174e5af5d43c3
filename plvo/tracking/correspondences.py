"""A frame's 3D-2D correspondences: the landmarks the tracker ties to the frame's features, as the pose solvers
(plvo.tracking.pnpl) take them."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Correspondences:
    """Points: point_landmarks (P,) landmark ids, point_features (P,) the frame's keypoint indices, point_positions
    (P,3) world, point_pixels (P,2). Lines: line_landmarks (L,), line_features (L,) segment indices, line_endpoints
    (L,2,3) world, line_segments (L,4) pixels. Row i of each point (line) array is one correspondence."""

    point_landmarks: np.ndarray
    point_features: np.ndarray
    point_positions: np.ndarray
    point_pixels: np.ndarray
    line_landmarks: np.ndarray
    line_features: np.ndarray
    line_endpoints: np.ndarray
    line_segments: np.ndarray

    @property
    def n_points(self) -> int:
        return len(self.point_landmarks)

    @property
    def n_lines(self) -> int:
        return len(self.line_landmarks)

    def solver_inputs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(point positions, pixels, line endpoints, segments): what solve_pnpl and refine_pose take."""
        return self.point_positions, self.point_pixels, self.line_endpoints, self.line_segments

    def with_points(self, landmarks: np.ndarray, features: np.ndarray, positions: np.ndarray,
                    pixels: np.ndarray) -> Correspondences:
        """These point correspondences added after the ones held."""
        return dataclasses.replace(
            self, point_landmarks=np.r_[self.point_landmarks, landmarks],
            point_features=np.r_[self.point_features, features],
            point_positions=np.r_[self.point_positions, positions], point_pixels=np.r_[self.point_pixels, pixels])

    def with_lines(self, landmarks: np.ndarray, features: np.ndarray, endpoints: np.ndarray,
                   segments: np.ndarray) -> Correspondences:
        """These line correspondences added after the ones held."""
        return dataclasses.replace(
            self, line_landmarks=np.r_[self.line_landmarks, landmarks],
            line_features=np.r_[self.line_features, features],
            line_endpoints=np.r_[self.line_endpoints, endpoints], line_segments=np.r_[self.line_segments, segments])
