"""A raw camera (intrinsics, distortion, rectification) and the pinhole the pipeline sees after rectifying it.

The pipeline assumes an undistorted pinhole image. Sources that give a distorted camera (a ROS CameraInfo, a
calibration YAML) are rectified once a frame with OpenCV's remap; the resulting Calibration has the new camera
matrix and, when a rectification rotation R is given (stereo rigs), the lidar extrinsics of the rotated camera.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from plvo.errors import CalibrationError
from plvo.types import Calibration

# ROS distortion_model names -> OpenCV family
PINHOLE_MODELS = ("plumb_bob", "rational_polynomial", "radtan", "pinhole")
FISHEYE_MODELS = ("equidistant", "fisheye", "kannala_brandt")


@dataclass(frozen=True)
class CameraModel:
    """width, height (px); K (3,3); D (k,) distortion of `model`; R (3,3) rectification rotation (rectified camera
    <- raw camera); P (3,3) camera matrix of the rectified image, or None to choose one (alpha 0)."""

    width: int
    height: int
    K: np.ndarray
    D: np.ndarray = field(default_factory=lambda: np.zeros(0))
    model: str = "plumb_bob"
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    P: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.model not in PINHOLE_MODELS + FISHEYE_MODELS:
            raise CalibrationError(f"distortion model {self.model!r} not supported (one of "
                                   f"{', '.join(PINHOLE_MODELS + FISHEYE_MODELS)})")

    @property
    def distorted(self) -> bool:
        return bool(np.any(np.abs(self.D) > 0))

    @property
    def needs_rectification(self) -> bool:
        P_differs = self.P is not None and not np.allclose(self.P, self.K)
        return self.distorted or not np.allclose(self.R, np.eye(3)) or P_differs

    @property
    def fisheye(self) -> bool:
        return self.model in FISHEYE_MODELS

    def rectified_K(self) -> np.ndarray:
        """(3,3) camera matrix of the rectified image."""
        if self.P is not None:
            return np.asarray(self.P, dtype=np.float64).copy()
        if not self.distorted:
            return np.asarray(self.K, dtype=np.float64).copy()
        size = (self.width, self.height)
        if self.fisheye:
            return cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
                self.K, self._fisheye_D(), size, self.R, balance=0.0)
        K, _ = cv2.getOptimalNewCameraMatrix(self.K, self.D, size, 0.0, size)
        return K

    def _fisheye_D(self) -> np.ndarray:
        D = np.zeros(4)
        D[: min(4, len(self.D))] = self.D[:4]
        return D

    def calibration(self, T_cam_lidar: np.ndarray, elevation_offset_deg: float = 0.0) -> Calibration:
        """Calibration of the rectified image: new K, T_cam_velo of the rectified camera (R applied)."""
        T_rect_raw = np.eye(4)
        T_rect_raw[:3, :3] = self.R
        return Calibration(K=self.rectified_K(), T_cam_velo=T_rect_raw @ np.asarray(T_cam_lidar, dtype=np.float64),
                           width=int(self.width), height=int(self.height),
                           lidar_elevation_offset_deg=float(elevation_offset_deg))

    def rectifier(self) -> Rectifier | None:
        """The remap that rectifies this camera's images, or None when they are already rectified."""
        return Rectifier(self) if self.needs_rectification else None


class Rectifier:
    """Undistorts and rectifies images of one CameraModel (maps built once)."""

    def __init__(self, camera: CameraModel) -> None:
        size, new_K = (camera.width, camera.height), camera.rectified_K()
        if camera.fisheye:
            self._maps = cv2.fisheye.initUndistortRectifyMap(camera.K, camera._fisheye_D(), camera.R, new_K, size,
                                                             cv2.CV_16SC2)
        else:
            self._maps = cv2.initUndistortRectifyMap(camera.K, camera.D, camera.R, new_K, size, cv2.CV_16SC2)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(H,W) or (H,W,3) raw image -> the rectified image of the same size."""
        return cv2.remap(image, self._maps[0], self._maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
