"""The camera-lidar time offset estimated from the data (plvo.tracking.time_offset): recovered from rotations
alone on a turn, withheld where the motion cannot tell it; on a synthetic town whose scans are paired a frame
late (0.1 s) it is found, named, and the run starts again from its first frame with the scans moved by it: the
trajectory is then as good as without the offset."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest
from faults_table import fault
from scipy.spatial.transform import Rotation

from plvo.config import SystemConfig
from plvo.data.registry import open_dataset
from plvo.runtime.run import run_dataset
from plvo.tracking.time_offset import OffsetEstimate, TimeOffsetEstimator
from plvo_eval.kitti_metric import absolute_trajectory_error
from plvo_eval.kitti_variants import variant

DT = 0.1


def _yaw(t: np.ndarray, turning: bool) -> np.ndarray:
    """Heading (rad) at times t: a 90-degree turn between 3 and 6 s with smooth start and end, or a steady
    circle (a constant rate: no change of rate, nothing to tell an offset by)."""
    if not turning:
        return 0.05 * t
    s = np.clip((t - 3.0) / 3.0, 0.0, 1.0)
    return 0.5 * np.pi * (3 * s ** 2 - 2 * s ** 3)


def _estimator(offset: float, turning: bool, noise_deg: float = 0.05) -> TimeOffsetEstimator:
    rng = np.random.default_rng(1)
    est = TimeOffsetEstimator(max_s=0.2, sigma_bound_s=0.01)
    times = np.arange(0.0, 10.0, DT)
    for t in times:
        est.frame(t, Rotation.from_rotvec([0.0, _yaw(np.array([t]), turning)[0], 0.0]).as_matrix())
    for a, b in zip(times[:-3:3], times[3::3]):  # the lidar's rotation over scans taken `offset` after the images
        ya, yb = _yaw(np.array([a + offset, b + offset]), turning)
        noise = Rotation.from_rotvec(rng.normal(0, np.radians(noise_deg), 3))
        est.interval(a, b, (Rotation.from_rotvec([0.0, yb - ya, 0.0]) * noise).as_matrix())
    return est


@pytest.mark.parametrize("offset", [0.1, -0.05, 0.0, 0.013])
def test_offset_recovered_from_a_turn(offset):
    found = _estimator(offset, turning=True).estimate()
    assert found is not None and found.observable, found
    assert abs(found.offset_s - offset) < 0.005, found
    assert found.sigma_s < 0.005


def test_frames_not_the_cameras_own_are_left_out():
    """Over the turn's last 0.8 s the frames' orientations run 150 ms ahead (poses a lagging source gave, so marked):
    those frames, and the intervals reading them or a second after them, are left out and the offset (13 ms) is
    recovered from the rest of the turn (8 ms); taken as the camera's own, the same orientations pull it to -60 ms."""
    def estimate(marked: bool):
        rng = np.random.default_rng(1)
        est = TimeOffsetEstimator(max_s=0.2, sigma_bound_s=0.01)
        times = np.arange(0.0, 10.0, DT)
        for t in times:
            wrong = 5.0 <= t < 5.8
            yaw = _yaw(np.array([t + (0.15 if wrong else 0.0)]), True)[0]
            est.frame(t, Rotation.from_rotvec([0.0, yaw, 0.0]).as_matrix(), own=not (wrong and marked))
        for a, b in zip(times[:-3:3], times[3::3]):
            ya, yb = _yaw(np.array([a + 0.013, b + 0.013]), True)
            noise = Rotation.from_rotvec(rng.normal(0, np.radians(0.05), 3))
            est.interval(a, b, (Rotation.from_rotvec([0.0, yb - ya, 0.0]) * noise).as_matrix())
        return est.estimate()

    left_out, kept = estimate(True), estimate(False)
    assert left_out is not None and left_out.observable and abs(left_out.offset_s - 0.013) < 0.008, left_out
    assert kept is not None and abs(kept.offset_s - 0.013) > 0.05, kept
    assert left_out.n_intervals < kept.n_intervals


def test_broken_rotations_are_left_out_not_raised():
    """A frame's pose or a lidar interval that is no rotation (NaN, a reflection, a scaled matrix: a fault upstream)
    is left out, with the intervals reading near that frame, and the estimate still recovers the offset; scipy
    would fail on it (an SVD that does not converge, a non-positive determinant) and end the run at its summary."""
    clean = _estimator(0.1, turning=True)
    est = TimeOffsetEstimator(max_s=0.2, sigma_bound_s=0.01)
    rng = np.random.default_rng(1)
    times = np.arange(0.0, 10.0, DT)
    for i, t in enumerate(times):
        R = Rotation.from_rotvec([0.0, _yaw(np.array([t]), True)[0], 0.0]).as_matrix()
        est.frame(t, {20: np.full((3, 3), np.nan), 70: -R, 85: 2.0 * R}.get(i, R))
    for a, b in zip(times[:-3:3], times[3::3]):
        ya, yb = _yaw(np.array([a + 0.1, b + 0.1]), True)
        noise = Rotation.from_rotvec(rng.normal(0, np.radians(0.05), 3))
        est.interval(a, b, (Rotation.from_rotvec([0.0, yb - ya, 0.0]) * noise).as_matrix())
        est.interval(a, b, np.full((3, 3), np.nan))
    found = est.estimate()
    assert found is not None and found.observable and abs(found.offset_s - 0.1) < 0.005, found
    assert found.n_intervals < clean.estimate().n_intervals  # those reading near the broken frames left out


def test_offset_withheld_where_the_motion_cannot_tell_it():
    found = _estimator(0.1, turning=False).estimate()
    assert found is not None and not found.observable, found


@pytest.fixture(scope="module")
def late_scans(synth_sequence_factory, tmp_path_factory):
    """The looping synthetic town (15 m/s, turns) with every frame's scan taken from the next frame: the scans
    0.1 s after the images."""
    root = synth_sequence_factory(150, seed=177, speed_mps=15.0, loop=True)
    return root, variant(root, "00", tmp_path_factory.mktemp("late") / "late", 60, scan_of=lambda i: i + 1)


def test_a_variant_of_a_generated_sequence_reads_as_the_sequence(late_scans):
    """A fault variant keeps the generated sequence's scene description: read without it, the town was taken for
    real KITTI (KITTI's lidar elevation offset instead of the town's), which alone tripled the stated offset's
    largest error on the looping town (0.166 against 0.050 m paired right; read right 0.105 m;
    docs/results/crosscheck/)."""
    source, late = (open_dataset(root, "00") for root in late_scans)
    assert late.calib.lidar_elevation_offset_deg == source.calib.lidar_elevation_offset_deg
    assert late.scans_compensated == source.scans_compensated


def _max_error(ds, poses) -> float:
    gt = np.asarray(ds.gt_T_world_cam, float)
    gt = np.linalg.inv(gt[0]) @ gt
    return float(np.linalg.norm(gt[:, :3, 3] - np.asarray(poses)[:, :3, 3], axis=1).max())


def _config(**crosscheck) -> SystemConfig:
    cfg = SystemConfig()
    return dataclasses.replace(cfg, crosscheck=dataclasses.replace(cfg.crosscheck, **crosscheck))


def test_late_scans_are_found_and_the_run_starts_again_with_them_moved(late_scans, caplog):
    row = fault("time-offset")
    paired_right, late = late_scans
    ds = open_dataset(late, "00")
    with caplog.at_level(logging.WARNING, logger="plvo"):
        out = run_dataset(ds, SystemConfig())
    warned = [r.getMessage() for r in caplog.records]
    named = [m for m in warned if row.message in m]
    assert len(named) == 1 and "starts again from its first frame" in named[0], warned
    (restart,) = out.trust["restarts"]
    assert abs(restart["time_offset_s"] - 0.1) < 0.02 and restart["frames_before"] == restart["at_frame"] + 1
    assert sum("starting again from the first frame" in m for m in warned) == 1, warned
    assert out.trust["time_offset"]["stated_s"] == pytest.approx(restart["time_offset_s"], abs=1e-4)
    assert out.trust["time_offset"]["found"] is None  # nothing more to name once it is used
    assert len(out.poses) == 60 and out.trust["frames_by_source"]["camera"] >= 55  # the frames of the run again
    # Without the restart: named with the flag that states it, and what the offset costs unstated
    kept_on = run_dataset(ds, _config(restart_on_offset=False))
    assert "restarts" not in kept_on.trust
    found = kept_on.trust["time_offset"]["found"]
    assert found is not None and abs(found["offset_s"] - restart["time_offset_s"]) < 0.005
    assert _max_error(ds, kept_on.poses) > 0.5
    # the measure: the trajectory within 2x of the run with the scans paired right (60 frames on the AMD
    # EPYC machine: ATE started again 0.021, paired right 0.017, unstated 0.214 m). The largest error (0.106,
    # 0.056, 0.95 m) is held within 3x: on this town's turns (107 deg/s) it hangs on the estimate's last
    # milliseconds (the offset found at frame 26 is 0.0976 s; stated 0.095 / 0.100 / 0.105 s: 0.174 / 0.053 /
    # 0.160 m), more than a bound can hold on two machines
    aligned = run_dataset(open_dataset(paired_right, "00", slice(0, 60)), SystemConfig())
    gt = np.asarray(ds.gt_T_world_cam, float)
    ate = {name: absolute_trajectory_error(gt, np.asarray(r.poses, float)).rmse_m
           for name, r in (("unstated", kept_on), ("started again", out), ("paired right", aligned))}
    assert ate["started again"] < 2 * ate["paired right"] < ate["unstated"], ate
    worst = {name: _max_error(ds, r.poses) for name, r in (("started again", out), ("paired right", aligned))}
    assert worst["started again"] < 3 * worst["paired right"], worst


def test_plvo_viz_says_it_started_again_and_keeps_both_recordings(late_scans, tmp_path, monkeypatch, capsys):
    """As a user meets it: exit 0, the last line says the offset and that the run started again, config.toml is
    the config the poses come from (the offset stated), and the recording of the frames before is kept beside."""
    from plvo.config import load_config
    from plvo_app.cli import main_viz
    from plvo_app.rrd_reader import read_rrd

    monkeypatch.chdir(tmp_path)
    assert main_viz(["--root", str(late_scans[1]), "--seq", "00", "--frames", "0:40", "--no-serve",
                     "--rrd", "run.rrd", "--out", "out"]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err[-1].startswith("camera-lidar time offset: the scans are taken 0.09") and "started again" in err[-1]
    assert err[-2].startswith("complete: 40 frames"), err[-3:]
    stated = load_config(tmp_path / "out" / "config.toml").crosscheck.time_offset_s
    assert abs(stated - 0.1) < 0.02
    assert len((tmp_path / "out" / "poses.txt").read_text().splitlines()) == 40
    data, before = read_rrd(tmp_path / "run.rrd"), read_rrd(tmp_path / "run-before-restart.rrd")
    assert data.frames("/world/camera") == list(range(40)) and data.properties["plvo_run:status"] == "complete"
    assert before.properties["plvo_run:status"] == "restarted"
    assert before.frames("/world/camera") == list(range(before.properties["plvo_run:frames_done"]))


@pytest.mark.parametrize("offset_ms, sigma_ms, named", [
    (-20.9, 6.2, False),  # the realistic twin of 02's first observable estimate (its rig: -3 ms): within 3 sigma of 20
    (-12.8, 3.7, False),  # the same a few seconds on: within offset_warn_s
    (97.6, 1.0, True),    # scans a frame late (the late-scans test's estimate)
    (-45.0, 5.0, True),   # 45 - 15 > 20
    (-45.0, 9.0, False),  # 45 - 27 < 20: not yet certain enough
])
def test_an_offset_is_named_only_when_it_departs_by_its_uncertainty_too(offset_ms, sigma_ms, named):
    cc = SystemConfig().crosscheck
    est = OffsetEstimate(offset_ms / 1000, sigma_ms / 1000, 20, observable=True, rate_spread_deg_s=8.0)
    assert est.departs_from(cc.time_offset_s, cc.offset_warn_s, cc.offset_confidence_sigmas) is named
    # the same offset stated: nothing to name; unobservable: never named
    assert not est.departs_from(offset_ms / 1000, cc.offset_warn_s, cc.offset_confidence_sigmas)
    assert not OffsetEstimate(offset_ms / 1000, sigma_ms / 1000, 20, observable=False).departs_from(
        cc.time_offset_s, cc.offset_warn_s, cc.offset_confidence_sigmas)
