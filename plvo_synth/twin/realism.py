"""How far a twin's sensors fall short of ideal ones: every imperfection a setting, at the magnitude KITTI's rig has.

REALISTIC (the default) stands for KITTI's recording car; IDEAL writes the twins as they were before any of this
existed, file for file (`plvo synth --ideal`). The magnitudes and their sources are in docs/twins.md; those measured
on the real scans come from scripts/lidar_realism_stats.py.

Lidar (LidarRealism): range noise; each beam's elevation and range bias (the residual of the HDL-64E's intrinsic
calibration, one seeded draw per beam); KITTI's global vertical-angle error (every return sits elevation_offset_deg
too low, which readers take out as they do for real KITTI scans); returns missed on dark surfaces and car windows;
returns scattered from inside tree crowns; a compensated scan moved with the motion over whole GPS/INS record
periods instead of the sweep's (scripts/kitti_compensation_stats.py measured it on KITTI's scans). Rig (RigRealism):
the sequence's own calibration, the camera-lidar extrinsic error (the calibration written for the twin is the true
one turned and shifted by a seeded draw; the sensors are rendered with the true one) and the lidar's time offset
(its reference instant this long after the camera's, which the files do not state). Sweep: what a scan holds,
"as_data" (a twin of the odometry benchmark: motion-compensated to the lidar's reference instant; a twin of a raw
drive: each return in the sensor frame at its own time), "raw" or "compensated". The camera's settings are
CameraRealism of twin.camera_effects.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from plvo.errors import SynthError
from plvo_synth.twin.camera_effects import IDEAL_CAMERA, CameraRealism
from plvo_synth.twin.scenery_realism import IDEAL_SCENERY, REALISTIC_SCENERY, SceneryRealism

SWEEPS = ("as_data", "raw", "compensated")
CALIBRATIONS = ("own", "00-02")


@dataclass(frozen=True)
class LidarRealism:
    """range_noise_m: 1 sigma (None: the lidar model's own, 2 cm for the HDL-64E); beam_elevation_sigma_deg,
    beam_range_sigma_m: spread of the per-beam biases (each beam's draw is fixed for the twin); elevation_offset_deg:
    every return reported this much too low (KITTI's HDL-64E: 0.205); dropout_floor: chance of no return on any
    surface; dropout_dark, dropout_dark_reflectance: extra chance of no return on a surface of reflectance r,
    dropout_dark * exp(-r / dropout_dark_reflectance); dropout_glass: chance of no return from a car window;
    foliage_scatter, foliage_depth_m: the share of returns from closed crowns and hedges (foliage blobs, the
    scenery's at leaf density 0) that come from inside, and their mean depth behind the surface (exponential); a
    leafy crown scatters the rays by its own geometry; ego_occlusion: the recording car's body blocks the lower
    beams where it does on KITTI's car (twin.lidars.EGO_RETURN_NINTHS); compensation_records_a_sweep: a
    compensated scan is moved with the GPS/INS's motion between its records nearest the sweep's start and end, a
    whole number of record periods, while the sweep lasts this many (KITTI: records every 0.01 s, a sweep of
    0.1041 s, so 10 or 11 periods: 4 % too little or 6 % too much of the sweep's motion removed, by the beat of the
    two clocks; twin.lidars.LidarEffects.compensation_gain); 0: the sweep's exact motion."""

    range_noise_m: float | None = 0.010
    beam_elevation_sigma_deg: float = 0.07
    beam_range_sigma_m: float = 0.01
    elevation_offset_deg: float = 0.205
    dropout_floor: float = 0.0016
    dropout_dark: float = 0.143
    dropout_dark_reflectance: float = 0.052
    dropout_glass: float = 0.3
    foliage_scatter: float = 0.5
    foliage_depth_m: float = 0.4
    ego_occlusion: bool = True
    compensation_records_a_sweep: float = 10.41

    @property
    def is_ideal(self) -> bool:
        return self == IDEAL_LIDAR

    def check(self) -> None:
        for name in ("beam_elevation_sigma_deg", "beam_range_sigma_m", "foliage_depth_m"):
            _check_range(f"lidar.{name}", getattr(self, name), 0.0, 5.0)
        _check_range("lidar.dropout_dark_reflectance", self.dropout_dark_reflectance, 1e-3, 1.0)
        if self.range_noise_m is not None:
            _check_range("lidar.range_noise_m", self.range_noise_m, 0.0, 1.0)
        _check_range("lidar.elevation_offset_deg", self.elevation_offset_deg, -2.0, 2.0)
        for name in ("dropout_floor", "dropout_dark", "dropout_glass", "foliage_scatter"):
            _check_range(f"lidar.{name}", getattr(self, name), 0.0, 1.0)
        records = self.compensation_records_a_sweep
        _check_range("lidar.compensation_records_a_sweep", records, 0.0, 1000.0)
        if 0.0 < records < 1.0:
            raise SynthError(f"realism lidar.compensation_records_a_sweep = {records!r}: expected 0 (exact) or at "
                             "least 1 (a record period no longer than the sweep)")

    def beam_biases(self, n_beams: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """(B,) elevation biases (deg: the beam points this much above where the sensor reports it) and (B,) range
        biases (m: reported minus true), one seeded draw per beam."""
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 71]))
        elevation = rng.standard_normal(n_beams) * self.beam_elevation_sigma_deg
        range_m = rng.standard_normal(n_beams) * self.beam_range_sigma_m
        return elevation, range_m


@dataclass(frozen=True)
class RigRealism:
    """calibration: "own" (the sequence's own KITTI calibration and image size) or "00-02" (KITTI 00-02's for every
    twin, as the ideal twins have); extrinsic_rotation_deg, extrinsic_translation_m: 1 sigma per axis of the seeded
    error of the camera-lidar extrinsic the twin's calibration states; time_offset_s: the lidar's reference instant
    (facing forward) after the camera's exposure."""

    calibration: str = "own"
    extrinsic_rotation_deg: float = 0.1
    extrinsic_translation_m: float = 0.01
    # measured on the real clips (scripts/kitti_compensation_stats.py): lidar depth edges land on image edges best
    # with the scans taken 3 ms (04) and 2 ms (0009) before the camera's instant
    time_offset_s: float = -0.003

    def check(self) -> None:
        if self.calibration not in CALIBRATIONS:
            raise SynthError(f"rig.calibration {self.calibration!r}: choose from {', '.join(CALIBRATIONS)}")
        _check_range("rig.extrinsic_rotation_deg", self.extrinsic_rotation_deg, 0.0, 5.0)
        _check_range("rig.extrinsic_translation_m", self.extrinsic_translation_m, 0.0, 0.5)
        _check_range("rig.time_offset_s", self.time_offset_s, -0.05, 0.05)

    def extrinsic_error(self, seed: int) -> np.ndarray:
        """(4,4) E, seeded: the calibration written states E @ T_cam_velo (cam0 frame) for the true T_cam_velo."""
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 72]))
        rotvec = np.radians(rng.standard_normal(3) * self.extrinsic_rotation_deg)
        E = np.eye(4)
        E[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
        E[:3, 3] = rng.standard_normal(3) * self.extrinsic_translation_m
        return E


IDEAL_LIDAR = LidarRealism(range_noise_m=None, beam_elevation_sigma_deg=0.0, beam_range_sigma_m=0.0,
                           elevation_offset_deg=0.0, dropout_floor=0.0, dropout_dark=0.0, dropout_glass=0.0,
                           foliage_scatter=0.0, ego_occlusion=False, compensation_records_a_sweep=0.0)
IDEAL_RIG = RigRealism(calibration="00-02", extrinsic_rotation_deg=0.0, extrinsic_translation_m=0.0,
                       time_offset_s=0.0)


@dataclass(frozen=True)
class Realism:
    """Every imperfection of a twin: camera (twin.camera_effects.CameraRealism), lidar, rig, what a scan holds
    (sweep, one of SWEEPS) and how hard the scenery is (twin.scenery_realism.SceneryRealism)."""

    camera: CameraRealism = field(default_factory=CameraRealism)
    lidar: LidarRealism = field(default_factory=LidarRealism)
    rig: RigRealism = field(default_factory=RigRealism)
    sweep: str = "as_data"
    scenery: SceneryRealism = REALISTIC_SCENERY

    @property
    def is_ideal(self) -> bool:
        return self == IDEAL

    def check(self) -> None:
        if self.sweep not in SWEEPS:
            raise SynthError(f"sweep {self.sweep!r}: choose from {', '.join(SWEEPS)}")
        self.lidar.check()
        self.rig.check()
        self.camera.check()
        self.scenery.check()

    def compensated(self, raw_drive: bool) -> bool:
        """Whether scans are motion-compensated: a twin of the odometry benchmark's are, as KITTI's are; a raw
        drive's are not."""
        return self.sweep == "compensated" or (self.sweep == "as_data" and not raw_drive)

    def as_json(self) -> dict:
        return asdict(self)


def _check_range(name: str, value: object, lo: float, hi: float) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not lo <= float(value) <= hi:
        raise SynthError(f"realism {name} = {value!r}: expected a number in [{lo}, {hi}]")


REALISTIC = Realism()
IDEAL = Realism(camera=IDEAL_CAMERA, lidar=IDEAL_LIDAR, rig=IDEAL_RIG, sweep="raw", scenery=IDEAL_SCENERY)
