"""Voxel means as open3d's PointCloud.voxel_down_sample makes them, the voxels found by sorting their keys.

open3d keys each point by floor((p - (min - v/2)) / v), sums a voxel's points (and normals) in the order given and
divides by their count, in a hash map of voxels. Here one sort of the keys packed with the points' indices finds the
same voxels, and numpy's bincount sums each voxel's points in the order given: the same means, bit for bit
(tests/plvo/lidar/test_voxels.py compares them with open3d's). On the back end's local map (ten real KITTI 04
keyframes' scans, ~140k points at 0.5 m, with normals) the merged cloud takes 17 ms a keyframe against open3d's 22
(medians of 40 alternating pairs in one process, one thread). Only the voxels' order differs (by key here, by
open3d's hash map there), which the map's nearest-neighbour searches do not see; where a caller thins the result by
index (a scan's own downsampling, whose points become a registration's source), open3d's is kept.
"""

from __future__ import annotations

import numpy as np


def voxel_means(points: np.ndarray, voxel_m: float, normals: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray | None]:
    """(N,3) finite points (and their (N,3) normals) -> each occupied voxel's mean point (M,3) and the unit mean of
    its normals (M,3; a zero sum stays zero, as open3d's normalize_normals leaves it), voxels in the order of their
    (x, y, z) indices."""
    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    if n == 0:
        return np.zeros((0, 3)), None if normals is None else np.zeros((0, 3))
    # column by column: numpy reduces an (N,3) array along its rows ~20x slower
    low = np.array([pts[:, k].min() for k in range(3)]) - voxel_m * 0.5
    q = pts - low
    q /= voxel_m
    ijk = np.floor(q, out=q).astype(np.int64)
    spans = [int(ijk[:, k].max()) + 1 for k in range(3)]
    codes = _voxel_codes(ijk, spans)
    m = int(codes.max()) + 1
    count = np.bincount(codes, minlength=m).astype(np.float64)[:, None]
    means = np.stack([np.bincount(codes, pts[:, k], m) for k in range(3)], axis=1) / count
    if normals is None:
        return means, None
    nrm = np.asarray(normals, dtype=np.float64)
    summed = np.stack([np.bincount(codes, nrm[:, k], m) for k in range(3)], axis=1) / count
    norm = np.linalg.norm(summed, axis=1, keepdims=True)  # ((x^2 + y^2) + z^2), as Eigen's normalize
    return means, np.divide(summed, norm, out=summed.copy(), where=norm > 0)


def _voxel_codes(ijk: np.ndarray, spans: list[int]) -> np.ndarray:
    """(N,3) non-negative voxel indices -> (N,) each point's voxel numbered 0.. in the order of (i, j, k)."""
    n = len(ijk)
    if float(spans[0]) * float(spans[1]) * float(spans[2]) * n >= 2.0**62:  # far-flung points: keys too wide to pack
        return np.unique(ijk, axis=0, return_inverse=True)[1].ravel()
    key = (ijk[:, 0] * spans[1] + ijk[:, 1]) * spans[2] + ijk[:, 2]
    # (key, index) packed in one int64: the packed values are unique, so a plain sort orders them by key, and
    # sorting integers is faster than an argsort
    packed = np.sort(key * n + np.arange(n))
    cell = packed // n
    first = np.ones(n, dtype=bool)
    first[1:] = cell[1:] != cell[:-1]
    codes = np.empty(n, dtype=np.int64)
    codes[packed - cell * n] = np.cumsum(first) - 1
    return codes
