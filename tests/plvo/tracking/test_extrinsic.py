"""The camera-lidar extrinsic's rotation estimated from the data (plvo.tracking.extrinsic): recovered from motions
alone, an axis nothing excited kept at the stated extrinsic; on the looping synthetic town (exact calibration) told a
gross error, it is found, named, and the run starts again with it corrected."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from plvo.config import SystemConfig, config_from_dict
from plvo.data.registry import open_dataset
from plvo.errors import ConfigError
from plvo.runtime.run import run_dataset
from plvo.tracking.extrinsic import ExtrinsicEstimate, ExtrinsicEstimator, corrected
from plvo_eval.kitti_metric import absolute_trajectory_error


def _motions(n: int, turning: bool, rng: np.random.Generator) -> list[np.ndarray]:
    """Camera motions over 0.3 s at 12 m/s (camera frame: z ahead, y down): straight, or yawing by up to 9 deg."""
    out = []
    for i in range(n):
        yaw = np.radians(9.0 * np.sin(i / 4.0)) if turning else 0.0
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec([rng.normal(0, 2e-3), yaw, rng.normal(0, 2e-3)]).as_matrix()
        T[:3, 3] = [3.6 * np.sin(yaw / 2), rng.normal(0, 0.02), 3.6 * np.cos(yaw / 2)]
        out.append(T)
    return out


def _estimate(error_deg, turning: bool, n: int = 60) -> ExtrinsicEstimate | None:
    """The lidar's motions seen through an extrinsic turned by error_deg (D A D^-1), with its noise: 5 cm a step
    sideways, 1 cm vertically and along, 0.05 deg a rotation."""
    rng = np.random.default_rng(3)
    D = np.eye(4)
    D[:3, :3] = Rotation.from_rotvec(np.radians(error_deg)).as_matrix()
    est = ExtrinsicEstimator(prior_deg=1.0)
    for A in _motions(n, turning, rng):
        L = D @ A @ np.linalg.inv(D)
        L[:3, 3] += rng.normal(0, [0.05, 0.01, 0.01])
        L[:3, :3] = Rotation.from_rotvec(rng.normal(0, np.radians(0.05), 3)).as_matrix() @ L[:3, :3]
        est.interval(A, L)
    return est.estimate()


@pytest.mark.parametrize("error_deg", [(0.6, -0.4, 0.3), (0.0, 0.0, 0.0), (-1.5, 0.8, -0.5)])
def test_the_correction_undoes_the_error_on_a_winding_road(error_deg):
    found = _estimate(error_deg, turning=True)
    assert found is not None and found.n_intervals >= 50
    assert np.all(np.asarray(found.sigma_deg) < 0.15), found
    # the correction is the error's inverse: within 4 of its standard deviations and 0.1 deg a component
    miss = np.abs(np.asarray(found.correction_deg) + np.asarray(error_deg))
    assert np.all(miss < np.maximum(4 * np.asarray(found.sigma_deg), 0.1)), found
    assert found.departs(0.5, 3.0) == (max(np.abs(error_deg)) > 0.5 + 0.45)


def test_a_straight_road_tells_pitch_and_yaw_and_keeps_roll_at_the_stated():
    """Along a straight road only the direction of travel speaks: it fixes pitch (x) and yaw (y); roll (about the
    direction of travel, z) is told by the rotations' jitter alone (0.1 deg): its spread stays near the prior's
    1 deg, and it is pulled towards the stated extrinsic rather than past the truth."""
    found = _estimate((0.8, -0.6, 0.9), turning=False)
    assert found is not None
    c, s = np.asarray(found.correction_deg), np.asarray(found.sigma_deg)
    assert abs(c[0] + 0.8) < 0.1 and abs(c[1] - 0.6) < 0.15, found
    assert s[2] > 0.5 and s[2] > 5 * max(s[0], s[1]) and -0.9 < c[2] <= 0.0, found
    assert found.departs(0.5, 3.0)  # by pitch


def _straightish(seed: int, n: int) -> ExtrinsicEstimate | None:
    """n intervals of a nearly straight road (pitch, yaw and roll rates of 0.2 deg an interval, 1.9 m ahead) seen
    through the true extrinsic, with the lidar's noise: 1.5 / 1 / 2 cm and 0.03 deg a step."""
    rng = np.random.default_rng(seed)
    est = ExtrinsicEstimator(prior_deg=1.0)
    for _ in range(n):
        A = np.eye(4)
        A[:3, :3] = Rotation.from_rotvec(np.radians(rng.normal(0, 0.2, 3))).as_matrix()
        A[:3, 3] = [rng.normal(0, 0.02), rng.normal(0, 0.02), 1.9]
        L = A.copy()
        L[:3, 3] += rng.normal(0, [0.015, 0.01, 0.02])
        L[:3, :3] = Rotation.from_rotvec(rng.normal(0, np.radians(0.03), 3)).as_matrix() @ L[:3, :3]
        est.interval(A, L)
    return est.estimate()


@pytest.mark.parametrize("n", [10, 15])
def test_few_intervals_of_a_straight_road_name_no_error_the_rig_does_not_have(n):
    """A first estimate stands on a handful of intervals: their noise can fit a roll the road barely excites, and
    the posterior's spread, which trusts weights measured on those few, called it certain. The spread read from the
    grouped jackknife as well names nothing on 300 such starts (without it 3 of them at 10 intervals, 1 at 15)."""
    named = [s for s in range(300) if (e := _straightish(s, n)) is not None and e.departs(0.5, 3.0)]
    assert named == []


def test_the_intervals_that_named_a_false_roll_on_a_twin_name_nothing():
    """The 10 intervals (9 kept) after which a run of the realistic twin of KITTI 03 with a keyframe every 2 frames
    named a roll of +4.13 +- 0.67 deg (the twin's extrinsic error is 0.22 deg in all, 0.05 of it in roll) and
    started again on it (devkit error 0.21 -> 2.63 %): the estimate stays, its spread is now what leaving out a tenth
    of the intervals does to it."""
    d = np.load(Path(__file__).parents[2] / "data" / "extrinsic_twin03_kf2_intervals.npz")
    est = ExtrinsicEstimator(prior_deg=1.0)
    for A, L in zip(d["camera"], d["lidar"]):
        est.interval(A, L)
    found = est.estimate()
    assert found is not None and found.n_intervals == 9
    assert found.correction_deg[2] == pytest.approx(4.13, abs=0.01)
    assert found.sigma_deg[2] > 2.0 and not found.departs(0.5, 3.0), found


def test_too_few_or_too_short_intervals_give_no_estimate():
    est = ExtrinsicEstimator(prior_deg=1.0)
    for A in _motions(7, True, np.random.default_rng(0)):
        est.interval(A, A)
    assert est.estimate() is None
    still = np.eye(4)
    still[2, 3] = 0.2  # a car creeping: its steps' directions are the registration's noise
    for _ in range(20):
        est.interval(still, still)
    assert est.estimate() is None


def test_a_correction_turns_the_extrinsic_in_the_cameras_frame():
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix()  # KITTI's lidar axes
    T[:3, 3] = [0.02, -0.08, -0.27]
    C = corrected(T, (0.0, 2.0, 0.0))
    assert np.allclose(C[:3, 3], Rotation.from_rotvec([0, np.radians(2.0), 0]).apply(T[:3, 3]))
    assert np.allclose(C[:3, :3] @ T[:3, :3].T, Rotation.from_rotvec([0, np.radians(2.0), 0]).as_matrix())


def test_a_correction_must_be_three_angles():
    with pytest.raises(ConfigError, match="crosscheck.extrinsic_correction_deg"):
        config_from_dict({"crosscheck": {"extrinsic_correction_deg": [0.1, 0.2]}})
    with pytest.raises(ConfigError, match="crosscheck.extrinsic_correction_deg"):
        config_from_dict({"crosscheck": {"extrinsic_correction_deg": [0.1, 0.2, 9.0]}})


@pytest.fixture(scope="module")
def town(synth_sequence_factory):
    """The looping synthetic town (15 m/s, turns; as the late-scans test), its first 60 frames."""
    return open_dataset(synth_sequence_factory(150, seed=177, speed_mps=15.0, loop=True), "00", slice(0, 60))


def _config(**crosscheck) -> SystemConfig:
    cfg = SystemConfig()
    return dataclasses.replace(cfg, crosscheck=dataclasses.replace(cfg.crosscheck, **crosscheck))


def test_a_gross_extrinsic_error_is_found_and_the_run_starts_again_with_it_corrected(town, caplog):
    """Told an extrinsic turned by (1, -1, 0.5) deg, the run names it within its first 30 frames, starts again with
    the correction composed, and ends within 0.7 deg a component of the true extrinsic (the estimator reads an error
    0.5-1.6x its size: docs/crosscheck.md) and 0.6 of the injected error in all, and within 3x the ATE of the run
    told the true one (6x kept on the error). Measured (60 frames, the AMD EPYC machine): found at frame 16 as
    (-1.12, +0.66, -0.43) deg, what remains after it (-0.12, -0.34, +0.08); ATE 0.017 m told the truth, 0.026 m
    started again (and over 80 frames with restart_on_extrinsic off, 0.108 m kept on the error). With the jackknife's
    spread (fffdabe), on an AMD EPYC giving other last bits (2026-12-07): found at frame 16 as (-1.47, +1.10, -0.59),
    what remains (-0.47, +0.10, -0.08), ATE 0.019 and 0.026 m; on AVX2 kernels (scripts/test_other_bits.sh) not named
    at 9 intervals (x -1.36 +- 0.37) but at 13, frame 25, as (-1.43, +1.66, -0.54), what remains (-0.43, +0.66,
    -0.04), ATE 0.020 and 0.050 m."""
    injected = (1.0, -1.0, 0.5)
    with caplog.at_level(logging.WARNING, logger="plvo"):
        out = run_dataset(town, _config(extrinsic_correction_deg=injected))
    (restart,) = out.trust["restarts"]
    assert restart["reason"] == "camera-lidar extrinsic" and restart["at_frame"] <= 30, restart
    assert sum("starting again from the first frame with the extrinsic turned" in r.getMessage()
               for r in caplog.records) == 1
    left = Rotation.from_rotvec(restart["extrinsic_correction_deg"], degrees=True).as_rotvec(degrees=True)
    assert out.trust["extrinsic"]["correction_stated_deg"] == pytest.approx(restart["extrinsic_correction_deg"])
    assert np.all(np.abs(left) < 0.7), left
    assert np.linalg.norm(left) < 0.6 * np.linalg.norm(injected)
    assert out.trust["extrinsic"]["found"] is None  # once corrected, nothing gross is left to name
    truth = run_dataset(town, SystemConfig())
    gt = np.asarray(town.gt_T_world_cam, float)
    ate = {name: absolute_trajectory_error(gt, np.asarray(r.poses, float)).rmse_m
           for name, r in (("corrected", out), ("true", truth))}
    assert ate["corrected"] < 3.0 * ate["true"], ate
    est = truth.trust["extrinsic"]["estimate"]  # told the true extrinsic, it reads near zero and names nothing
    assert truth.trust["extrinsic"]["found"] is None and "restarts" not in truth.trust
    assert np.all(np.abs(est["correction_deg"]) < 0.2), est
