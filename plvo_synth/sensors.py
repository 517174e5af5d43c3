"""KITTI's sensor models: cam0 of odometry sequence 00 and the Velodyne HDL-64E, with KITTI's real calibration.

Ray directions are precomputed once: the camera's with z = 1 (so the ray caster's hit distance is the z-depth),
the lidar's as unit vectors (so the hit distance is the range).
"""

from __future__ import annotations

import numpy as np

# calib.txt of KITTI odometry sequences 00-02 (recorded 2011-10-03), copied verbatim.
KITTI_CALIB_00_TEXT = (
    "P0: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 0.000000000000e+00 0.000000000000e+00 "
    "7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 "
    "1.000000000000e+00 0.000000000000e+00\n"
    "P1: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.861448000000e+02 0.000000000000e+00 "
    "7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 "
    "1.000000000000e+00 0.000000000000e+00\n"
    "P2: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 4.538225000000e+01 0.000000000000e+00 "
    "7.188560000000e+02 1.852157000000e+02 -1.130887000000e-01 0.000000000000e+00 0.000000000000e+00 "
    "1.000000000000e+00 3.779761000000e-03\n"
    "P3: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.372877000000e+02 0.000000000000e+00 "
    "7.188560000000e+02 1.852157000000e+02 2.369057000000e+00 0.000000000000e+00 0.000000000000e+00 "
    "1.000000000000e+00 4.915215000000e-03\n"
    "Tr: 4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 -7.210626507497e-03 "
    "8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 9.999738645903e-01 4.859485810390e-04 "
    "-7.206933692422e-03 -2.921968648686e-01\n"
)

IMAGE_WIDTH = 1241  # KITTI odometry sequences 00-02
IMAGE_HEIGHT = 376
FRAME_DT = 0.1  # 10 Hz, camera and lidar triggered together
CAMERA_HEIGHT_M = 1.65  # KITTI's cam0 above the road


def _calib_matrix(key: str) -> np.ndarray:
    for line in KITTI_CALIB_00_TEXT.splitlines():
        name, values = line.split(":", 1)
        if name == key:
            return np.array([float(x) for x in values.split()]).reshape(3, 4)
    raise KeyError(key)


P0 = _calib_matrix("P0")
K_CAM0 = P0[:, :3].copy()
T_CAM_VELO = np.vstack([_calib_matrix("Tr"), [0.0, 0.0, 0.0, 1.0]])

# HDL-64E: an upper block of 32 lasers from +2 to -8.33 deg (1/3 deg apart) and a lower block of 32 lasers
# from -8.83 to -24.8 deg (about 1/2 deg apart); KITTI's scans span these elevations.
LIDAR_ELEVATIONS_DEG = np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.8, 32)])
LIDAR_AZIMUTH_STEPS = 2000
LIDAR_MAX_RANGE_M = 80.0  # KITTI's scans reach about 80 m on urban surfaces
LIDAR_MIN_RANGE_M = 2.5  # returns from the ego car are cut off in KITTI too
LIDAR_RANGE_NOISE_M = 0.02  # HDL-64E spec: < 2 cm (1 sigma)


def camera_rays(K: np.ndarray = K_CAM0, width: int = IMAGE_WIDTH, height: int = IMAGE_HEIGHT) -> np.ndarray:
    """(H*W,3) float32 ray directions in the camera frame with z = 1, row-major over pixel centres."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    return np.stack([x, y, np.ones_like(x)], axis=-1).reshape(-1, 3).astype(np.float32)


def lidar_rays(steps: int = LIDAR_AZIMUTH_STEPS) -> np.ndarray:
    """(64*steps,3) float32 unit ray directions in the Velodyne frame (x forward, y left, z up), beam-major."""
    el = np.radians(LIDAR_ELEVATIONS_DEG)[:, None]
    az = np.linspace(0.0, 2.0 * np.pi, steps, endpoint=False)[None, :]
    return spherical_directions(el, az).reshape(-1, 3).astype(np.float32)


def spherical_directions(elevation: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    """Elevations and azimuths (rad, broadcasting against each other) -> (..., 3) unit vectors in the Velodyne
    frame (x forward, y left, z up)."""
    return np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                     np.sin(elevation) * np.ones_like(azimuth)], axis=-1)
