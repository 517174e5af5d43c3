"""Spinning lidar models of the twins and the time of each return within the 0.1 s sweep.

Like KITTI's HDL-64E, every model turns clockwise seen from above (azimuth decreasing in the Velodyne frame: x
forward, y left, z up) once a frame; the camera is triggered when the lidar faces forward (azimuth 0), so a return
at azimuth a was taken SWEEP_S * (-a / 2 pi) after the frame's time, from -0.05 s (behind, start of the sweep)
to +0.05 s (behind, end). A raw sweep holds each return in the sensor frame at its own time; a motion-compensated
scan (KITTI's odometry benchmark) holds every return in the sensor frame at the sweep's reference instant.

LidarEffects: what a real HDL-64E does to a sweep (twin.realism.LidarRealism): the beams point elsewhere than the
sensor reports (per-beam elevation biases and the global vertical-angle error), ranges carry per-beam biases and
noise, dark surfaces and car windows miss returns, tree crowns return from inside; and what KITTI's compensation
leaves of the sweep's motion (compensation_gain).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plvo.errors import SynthError
from plvo_synth import sensors
from plvo_synth.textures import MATERIAL_ID
from plvo_synth.twin.realism import LidarRealism

SWEEP_S = sensors.FRAME_DT


@dataclass(frozen=True)
class LidarModel:
    name: str
    elevations_deg: tuple[float, ...]
    azimuth_steps: int
    max_range_m: float
    min_range_m: float = sensors.LIDAR_MIN_RANGE_M
    range_noise_m: float = sensors.LIDAR_RANGE_NOISE_M

    def rays(self, elevations_deg: np.ndarray | None = None) -> np.ndarray:
        """(B*S,3) float32 unit directions, azimuth-major (column by column), each column from the top beam (at
        `elevations_deg` (B,) instead of the model's, when given)."""
        el = np.radians(np.asarray(self.elevations_deg if elevations_deg is None else elevations_deg))[None, :]
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


# The recording car's own body in the HDL-64E's lower beams: the share of firings that return, per ring (42-63,
# top first) and 10 deg of azimuth (from -180 deg, atan2(y, x) in the Velodyne frame), in ninths; the higher of
# KITTI raw drive 0009's 51 sweeps and odometry 04's 51 scans (the car's roof, rack and mast block the same rays in
# both; what one drive's scenery hides is not in the other), 9 where both return 85 % or more
# (scripts/lidar_realism_stats.py --ego-table RAW_0009_VELODYNE ODOMETRY_04_VELODYNE). Rings 0-41 are never blocked.
EGO_FIRST_RING = 42
EGO_RETURN_NINTHS = (
    "992999999999999999999999999999999949",
    "955999999999999999999999999999999669",
    "972999999999999999999999999999999749",
    "955999999999999999999999999999999669",
    "994999999999999999999999999999999959",
    "977999999994999999999999999999999799",
    "995999999991699999999999999999999949",
    "967999999921999999999999999999999969",
    "986999999950599999999999999999999959",
    "969999999901999999999999999999999969",
    "047999999940699999999999999999999950",
    "009999999901999999999999999999999900",
    "005999999950499999999999999999999920",
    "007997999910999999999999999999999900",
    "004995999950599999999999999999949900",
    "005995999912999990099999999999969600",
    "002993999950699960049999999999939700",
    "004994999914999940049999999999969500",
    "000993999961996540029799999999939700",
    "001965999939993720015699999999929300",
    "000754999976995520007299999999934500",
    "000315999859991700005499999999902000",
)


def ego_return_share(model: LidarModel) -> np.ndarray:
    """(B*S,) float32, 1 where a ray of model.rays() clears the recording car and 0 where its body blocks it: the
    measured share interpolated between the 10 deg bins' centres, blocked below one half (the body is one
    contiguous shape, so its shadow has edges, not a scatter of lost firings). A 64-beam model takes KITTI's
    table, any other clears everywhere."""
    n_beams = len(model.elevations_deg)
    share = np.ones((model.azimuth_steps, n_beams), np.float32)
    if n_beams != 64:
        return share.ravel()
    table = np.array([[int(c) / 9.0 for c in row] for row in EGO_RETURN_NINTHS])
    centres = np.arange(36) * 10.0 - 175.0
    az = np.degrees(model.azimuths())
    for k, row in enumerate(table):
        s = np.interp(az, centres, row, period=360.0)
        share[:, EGO_FIRST_RING + k] = (s >= 0.5).astype(np.float32)
    return share.ravel()


class LidarEffects:
    """One twin's lidar imperfections: the beams' seeded biases and how a sweep's returns are degraded."""

    def __init__(self, model: LidarModel, realism: LidarRealism, seed: int) -> None:
        self.realism = realism
        n_beams = len(model.elevations_deg)
        self.elevation_bias_deg, self.range_bias_m = realism.beam_biases(n_beams, seed)
        # The lasers point this much above the elevations the sensor reports (its calibration table, the model's).
        true = np.asarray(model.elevations_deg) + self.elevation_bias_deg + realism.elevation_offset_deg
        self.cast_dirs = model.rays(true)
        self.ray_range_bias = np.tile(self.range_bias_m, model.azimuth_steps).astype(np.float32)
        self.range_noise_m = model.range_noise_m if realism.range_noise_m is None else realism.range_noise_m
        self.ray_clear = ego_return_share(model) if realism.ego_occlusion else None
        # where the GPS/INS's record clock stands against the twin's clock at time 0, in record periods
        self.record_phase = float(np.random.default_rng(np.random.SeedSequence([int(seed), 73])).random())

    def compensation_gain(self, reference_time: float) -> float:
        """The share of the sweep's motion that the compensation of the sweep facing forward at reference_time (s,
        the twin's clock) removes: it reads the motion between the GPS/INS records nearest the sweep's start and
        end (KITTI's scans, scripts/kitti_compensation_stats.py), whole record periods against the sweep's
        realism.compensation_records_a_sweep. The record clock beats against the sweep's, so the gain changes from
        sweep to sweep (KITTI: 10 / 10.41 or 11 / 10.41) and averages 1. Exact (1) for 0."""
        n = self.realism.compensation_records_a_sweep
        if n == 0.0:
            return 1.0
        start = (reference_time / SWEEP_S - 0.5) * n + self.record_phase  # the sweep's start, in record periods
        return float((np.floor(start + n + 0.5) - np.floor(start + 0.5)) / n)

    def missed(self, rays: np.ndarray, darkness: np.ndarray, material: np.ndarray,
               rng: np.random.Generator) -> np.ndarray:
        """(K,) bool: which returns of rays (K,) (indices into model.rays()) are lost, from each surface's
        reflectance times its tint (`darkness`, dark paint and tyres near 0), its material (car windows) and the
        recording car's body."""
        r = self.realism
        p = r.dropout_floor + r.dropout_dark * np.exp(-np.maximum(darkness, 0.0) / r.dropout_dark_reflectance)
        p = np.where(material == MATERIAL_ID["car_glass"], np.maximum(p, r.dropout_glass), p)
        if self.ray_clear is not None:
            p = 1.0 - (1.0 - p) * self.ray_clear[rays]
        return rng.random(len(p)) < p

    def crown_depth(self, material: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(K,) metres added to each return's range: inside the crown for a share of the returns from foliage."""
        r = self.realism
        inside = (material == MATERIAL_ID["foliage"]) & (rng.random(len(material)) < r.foliage_scatter)
        return np.where(inside, rng.exponential(r.foliage_depth_m, len(material)), 0.0).astype(np.float32)

    def as_json(self) -> dict:
        return {"beam_elevation_bias_deg": [round(float(x), 6) + 0.0 for x in self.elevation_bias_deg],
                "beam_range_bias_m": [round(float(x), 6) + 0.0 for x in self.range_bias_m],
                "range_noise_m": self.range_noise_m,
                "elevation_offset_deg": self.realism.elevation_offset_deg,
                "compensation_records_a_sweep": self.realism.compensation_records_a_sweep,
                "compensation_record_phase": round(self.record_phase, 6) + 0.0}


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
