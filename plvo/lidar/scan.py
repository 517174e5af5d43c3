"""A scan as scan registration uses it: KITTI's lidar elevation error corrected (see plvo.lidar.registration).

numpy only, so that the keyframe (plvo.tracking.keyframes) can prepare it once for both workers that register
scans (the back end and the loop verification) without importing open3d.
"""

from __future__ import annotations

import numpy as np

from plvo.types import Frame


def registration_scan(frame: Frame) -> np.ndarray:
    """The frame's scan raised by its calibration's lidar_elevation_offset_deg (the scan itself when that is 0)."""
    return raise_elevation(frame.scan, frame.calib.lidar_elevation_offset_deg)


def raise_elevation(scan: np.ndarray, degrees: float) -> np.ndarray:
    """(N,3|4) lidar-frame points -> a copy with every point's elevation raised by `degrees`, range and azimuth
    unchanged (KISS-ICP's correct_kitti_scan, a rotation about p x z); the scan itself when degrees is 0."""
    if degrees == 0.0:
        return scan
    out = np.array(scan, copy=True)
    x, y, z = out[:, 0], out[:, 1], out[:, 2]
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    h = np.hypot(x, y)
    # the rotation written out: horizontal components scale by cos a - sin a z/h, z' = z cos a + h sin a; a point
    # straight up or down (h = 0) has no azimuth to keep and is left as it is
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(h > 0, c - s * z / h, 1.0)
    z_new = np.where(h > 0, z * c + h * s, z)
    x *= f
    y *= f
    out[:, 2] = z_new
    return out
