"""Which landmark each feature of a frame is tracked to, and the search of landmarks near their projection."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class FrameAssociation:
    """Which landmark each feature of one frame is tracked to: point_landmark (N,) and line_landmark (M,) ids,
    -1 where none (one entry per keypoint / segment of the frame's FeatureSet)."""

    point_landmark: np.ndarray
    line_landmark: np.ndarray

    @staticmethod
    def empty(n_points: int, n_lines: int) -> FrameAssociation:
        return FrameAssociation(np.full(n_points, -1, np.int64), np.full(n_lines, -1, np.int64))

    @property
    def n_points(self) -> int:
        return int((self.point_landmark >= 0).sum())

    @property
    def n_lines(self) -> int:
        return int((self.line_landmark >= 0).sum())


SEARCH_NEIGHBOURS = 12  # keypoints considered around a projected landmark (more within the radius are rare)


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(k,32) uint8, (k,32) uint8 -> (k,) row-wise Hamming distances."""
    x = np.ascontiguousarray(a).view(np.uint64) ^ np.ascontiguousarray(b).view(np.uint64)
    return np.bitwise_count(x).sum(axis=1, dtype=np.int32)


def search_by_projection(uv_landmarks: np.ndarray, desc_landmarks: np.ndarray, keypoints: np.ndarray,
                         descriptors: np.ndarray, free: np.ndarray, radius_px: float, max_hamming: int
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Landmarks projected to (L,2) px with (L,32) descriptors, a frame's (N,2) keypoints, (N,32) descriptors and
    (N,) bool free (not yet associated) -> (k,) landmark rows and (k,) keypoint indices, one-to-one.

    Each landmark takes the free keypoint with the smallest Hamming distance (<= max_hamming) within radius_px
    of its projection; conflicts go to the smaller distance.
    """
    ok = np.flatnonzero(np.isfinite(uv_landmarks).all(axis=1))
    cand = np.flatnonzero(free)
    if len(ok) == 0 or len(cand) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    # The SEARCH_NEIGHBOURS nearest keypoints within the radius (fixed-shape arrays: no Python loop per landmark).
    k = min(SEARCH_NEIGHBOURS, len(cand))
    d, j = cKDTree(keypoints[cand]).query(uv_landmarks[ok], k=k, distance_upper_bound=radius_px)
    d, j = d.reshape(len(ok), k), j.reshape(len(ok), k)
    hit = np.isfinite(d)
    rows = np.repeat(ok, k).reshape(len(ok), k)[hit]
    kps = cand[j[hit]]
    if len(rows) == 0:
        return rows, kps
    dist = hamming(desc_landmarks[rows], descriptors[kps])
    keep = dist <= max_hamming
    rows, kps, dist = rows[keep], kps[keep], dist[keep]
    order = np.argsort(dist, kind="stable")
    rows, kps = rows[order], kps[order]
    _, first_row = np.unique(rows, return_index=True)  # best keypoint of each landmark
    rows, kps = rows[first_row], kps[first_row]
    dist_sorted = hamming(desc_landmarks[rows], descriptors[kps])
    order = np.argsort(dist_sorted, kind="stable")
    rows, kps = rows[order], kps[order]
    _, first_kp = np.unique(kps, return_index=True)  # and the best landmark of each keypoint
    return rows[first_kp], kps[first_kp]
