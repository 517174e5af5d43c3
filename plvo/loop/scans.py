"""The loop closer's stored scans: thinned to a voxel, kept as int16 centimetres, read back as float32 metres.

Below both the closer, which compacts each keyframe's scan for its database, and the verification, which reads
two of them back to register them.
"""

from __future__ import annotations

import numpy as np

from plvo.config import RegistrationConfig

SCAN_VOXEL_M = 0.2  # thin_scan's default voxel
SCAN_UNIT_M = 0.01  # stored scans: int16 centimetres (a 60 m crop fits; 6 bytes a point instead of 16)


def thin_scan(scan: np.ndarray, voxel_m: float = SCAN_VOXEL_M) -> np.ndarray:
    """(N,3|4) lidar points -> the first point of every occupied voxel, (M,3|4) float32.

    Column by column and with one plain sort: ~15x faster than np.unique's stable argsort over (N,3) keys, the same
    points (tests/plvo/loop/test_closer.py compares it with that)."""
    scan = np.asarray(scan, dtype=np.float32)
    if not np.isfinite(scan[:, :3]).all():
        scan = scan[np.all(np.isfinite(scan[:, :3]), axis=1)]
    n = len(scan)
    if n == 0:
        return scan
    keys = [np.floor(scan[:, c] / voxel_m).astype(np.int64) for c in range(3)]
    lows = [int(k.min()) for k in keys]
    spans = [int(k.max()) - lo + 1 for k, lo in zip(keys, lows)]
    if spans[0] * spans[1] * spans[2] * n >= 2**62:  # far-flung points: the packed keys below would overflow
        _, first = np.unique(np.stack(keys, axis=1), axis=0, return_index=True)
        return scan[np.sort(first)]
    flat = np.zeros(n, np.int64)  # row-major voxel id
    for key, lo, span in zip(keys, lows, spans):
        flat *= span
        flat += key - lo
    # a point in the voxel of the point before it is not its voxel's first: a spinning lidar's neighbouring returns
    # share voxels, so dropping them leaves a fraction of the scan to sort (half the time on KITTI scans)
    cand = np.flatnonzero(np.concatenate(([True], flat[1:] != flat[:-1])))
    # (voxel, index) packed in one int64: the keys are unique, so any sort orders them alike; the first of each
    # voxel's run is its first point
    packed = np.sort(flat[cand] * n + cand)
    cell = packed // n
    first = np.ones(len(packed), bool)
    first[1:] = cell[1:] != cell[:-1]
    return scan[np.sort(packed[first] - cell[first] * n)]


def compact_scan(scan: np.ndarray, reg_cfg: RegistrationConfig | None) -> np.ndarray:
    """(N,3|4) lidar points -> what the database keeps for a later verification: the returns registration uses
    (within min_range_m..max_range_m), thinned to its fine voxel (voxel_m / 2), as (M,3) int16 centimetres."""
    cfg = reg_cfg or RegistrationConfig()
    pts = np.asarray(scan, dtype=np.float32)[:, :3]
    r2 = np.einsum("ni,ni->n", pts, pts)
    pts = pts[(r2 >= cfg.min_range_m ** 2) & (r2 <= min(cfg.max_range_m, 300.0) ** 2)]
    pts = thin_scan(pts, cfg.voxel_m / 2 if cfg.voxel_m > 0 else SCAN_VOXEL_M)
    return np.round(pts / SCAN_UNIT_M).astype(np.int16)


def scan_points(scan: np.ndarray) -> np.ndarray:
    """A scan as registration takes it: (M,3) float32 metres from compact_scan's int16, or unchanged."""
    scan = np.asarray(scan)
    return scan.astype(np.float32) * SCAN_UNIT_M if scan.dtype == np.int16 else scan
