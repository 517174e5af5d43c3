"""Spinning lidar models of the twins and the time of each return within the 0.1 s sweep.

Like KITTI's HDL-64E, every model turns clockwise seen from above (azimuth decreasing in the Velodyne frame: x
forward, y left, z up) once a frame; the camera is triggered when the lidar faces forward (azimuth 0), so a return
at azimuth a was taken SWEEP_S * (-a / 2 pi) after the frame's time, from -0.05 s (behind, start of the sweep)
to +0.05 s (behind, end). KITTI's odometry scans are not motion-compensated: each return is in the sensor frame at
its own time, and so are the twins'.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plvo.data.synth import sensors
from plvo.errors import SynthError

SWEEP_S = sensors.FRAME_DT


@dataclass(frozen=True)
class LidarModel:
    name: str
    elevations_deg: tuple[float, ...]
    azimuth_steps: int
    max_range_m: float
    min_range_m: float = sensors.LIDAR_MIN_RANGE_M
    range_noise_m: float = sensors.LIDAR_RANGE_NOISE_M

    def rays(self) -> np.ndarray:
        """(B*S,3) float32 unit directions, azimuth-major (column by column), each column from the top beam."""
        el = np.radians(np.asarray(self.elevations_deg))[None, :]
        d = sensors.spherical_directions(el, self.azimuths()[:, None])
        return d.reshape(-1, 3).astype(np.float32)

    def azimuths(self) -> np.ndarray:
        """(S,) column azimuths in sweep order: from just below +pi down to -pi (clockwise from behind)."""
        return np.pi - 2.0 * np.pi * (np.arange(self.azimuth_steps) + 0.5) / self.azimuth_steps

    def ray_times(self) -> np.ndarray:
        """(B*S,) seconds after the frame's time at which each ray of rays() is taken."""
        t = sweep_time(self.azimuths())
        return np.repeat(t, len(self.elevations_deg))

    def as_json(self) -> dict:
        return {"name": self.name, "elevations_deg": list(self.elevations_deg), "azimuth_steps": self.azimuth_steps,
                "max_range_m": self.max_range_m, "min_range_m": self.min_range_m,
                "range_noise_m": self.range_noise_m, "sweep_s": SWEEP_S,
                "timing": "t = frame time + sweep_s * (-azimuth / 2 pi), azimuth = atan2(y, x) in (-pi, pi]; "
                          "points are not motion-compensated"}


def sweep_time(azimuth: np.ndarray) -> np.ndarray:
    """Azimuth(s) (rad, atan2(y, x) in the Velodyne frame) -> seconds after the frame's time."""
    a = np.angle(np.exp(1j * np.asarray(azimuth, np.float64)))  # wrap into (-pi, pi]
    return -a / (2.0 * np.pi) * SWEEP_S


def point_times(points: np.ndarray) -> np.ndarray:
    """(N,>=2) scan points (x, y, ...) -> (N,) seconds after the frame's time at which each was taken."""
    return sweep_time(np.arctan2(points[:, 1], points[:, 0]))


LIDAR_MODELS: dict[str, LidarModel] = {
    "hdl64": LidarModel("hdl64", tuple(sensors.LIDAR_ELEVATIONS_DEG.tolist()), sensors.LIDAR_AZIMUTH_STEPS,
                        sensors.LIDAR_MAX_RANGE_M),
    # HDL-32E: 32 beams 1.33 deg apart from +10.67 to -30.67 deg, 0.16 deg steps at 10 Hz
    "hdl32": LidarModel("hdl32", tuple(np.linspace(10.67, -30.67, 32).tolist()), 2170, 70.0),
    # VLP-16: 16 beams 2 deg apart over +-15 deg, 0.2 deg steps at 10 Hz
    "vlp16": LidarModel("vlp16", tuple(np.linspace(15.0, -15.0, 16).tolist()), 1800, 80.0, range_noise_m=0.03),
    # Ouster OS1-128: 128 beams evenly over +-22.5 deg, 2048 columns at 10 Hz
    "os128": LidarModel("os128", tuple(np.linspace(22.5, -22.5, 128).tolist()), 2048, 90.0, range_noise_m=0.03),
}


def lidar_model(name: str) -> LidarModel:
    if name not in LIDAR_MODELS:
        raise SynthError(f"--lidar {name!r}: unknown model (choose from {', '.join(LIDAR_MODELS)})")
    return LIDAR_MODELS[name]
