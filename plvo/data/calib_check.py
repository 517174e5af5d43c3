"""A calibration checked where it is read: a degenerate one (a zero focal length, as an uncalibrated ROS camera
publishes; a transform that is not a rigid motion) would otherwise end the run frames later as an unexpected error
far from its cause."""

from __future__ import annotations

import numpy as np

from plvo.errors import CalibrationError
from plvo.types import Calibration

RIGID_TOL = 1e-3  # largest |R^T R - I| entry of a rotation read from a file (KITTI's: ~1e-7)


def check_calibration(calib: Calibration, where: str) -> Calibration:
    """calib, if usable; else CalibrationError naming `where` (the file, or the bag and topic) and the field."""
    K = np.asarray(calib.K, float)
    bad = f"{where}: degenerate calibration:"
    if not (calib.width > 0 and calib.height > 0):
        raise CalibrationError(f"{bad} image size {calib.width}x{calib.height} is not positive")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise CalibrationError(f"{bad} focal length fx {K[0, 0]:g}, fy {K[1, 1]:g}: must be positive (an "
                               "uncalibrated camera's zeros?)")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
        raise CalibrationError(f"{bad} camera matrix {K.ravel().tolist()} is not a pinhole matrix "
                               "[fx s cx; 0 fy cy; 0 0 1]")
    for name, T in (("lidar-to-camera transform", calib.T_cam_velo), ("camera-to-cam0 transform", calib.T_cam0_cam)):
        _check_rigid(np.asarray(T, float), f"{where}: degenerate calibration: the {name}")
    return calib


def _check_rigid(T: np.ndarray, what: str) -> None:
    if T.shape != (4, 4) or not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise CalibrationError(f"{what} is not a 4x4 rigid transform (last row {T[3].tolist()})")
    check_rotation(T[:3, :3], what)


def check_rotation(R: np.ndarray, what: str) -> None:
    """CalibrationError unless R (3,3) is a rotation within RIGID_TOL; `what` names the file and matrix."""
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > RIGID_TOL or np.linalg.det(R) < 0:
        raise CalibrationError(f"{what} has a rotation block that is not a rotation (|R^T R - I| {err:.3g}, "
                               f"det {np.linalg.det(R):.3g}): singular, scaled or mirrored")
