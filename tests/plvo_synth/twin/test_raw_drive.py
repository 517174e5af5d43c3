"""The twin of a KITTI raw drive (plvo_synth.twin.raw_drive): written in KITTI's raw layout and read as the real
drive is, its oxts giving back the poses it was rendered at, its path the drive's oxts without their timing jitter,
its scans raw sweeps timed as the drive's."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pykitti.utils as kitti_utils
import pytest
from scipy.spatial.transform import Rotation

from plvo.data.kitti import KittiRaw
from plvo.data.trajectory import read_kitti_poses
from plvo.errors import SynthError
from plvo_app.cli import main
from plvo_synth import sensors
from plvo_synth.twin.follow import PoseInterpolator
from plvo_synth.twin.generate import TwinSettings
from plvo_synth.twin.lidars import point_times
from plvo_synth.twin.raw_drive import (
    T_velo_imu,
    generate_raw_twin,
    mercator,
    plan_raw_twin,
    read_drive,
    smooth_path,
)

DRIVE = "2011_09_26_drive_0009"


@pytest.fixture(scope="module")
def raw_root(kitti_root):
    root = kitti_root.parent / "kitti_raw"
    if not (root / "2011_09_26" / f"{DRIVE}_sync" / "oxts" / "timestamps.txt").is_file():
        pytest.skip(f"KITTI raw drive {DRIVE} not found under {root} (see ../shared/data/README.md)")
    return root


@pytest.fixture(scope="module")
def raw_twin(raw_root, tmp_path_factory):
    out = tmp_path_factory.mktemp("raw_twin")
    settings = TwinSettings(str(raw_root / "2011_09_26" / f"{DRIVE}_sync"), "10:14", traffic=0, write_depth=True)
    return generate_raw_twin(out, raw_root, DRIVE, settings)


def _folder(root):
    return root / "2011_09_26" / f"{DRIVE}_sync"


def test_raw_twin_reads_as_the_real_drive_and_gives_back_its_poses(raw_twin):
    ds = KittiRaw(raw_twin, DRIVE)
    assert len(ds) == 4 and (ds.calib.width, ds.calib.height) == (1242, 375)
    truth = read_kitti_poses(_folder(raw_twin) / "gt" / "poses.txt")
    gt = ds.gt_T_world_cam
    assert np.abs(gt[:, :3, 3] - truth[:, :3, 3]).max() < 1e-3
    angles = [np.degrees(np.linalg.norm(Rotation.from_matrix(a[:3, :3].T @ b[:3, :3]).as_rotvec()))
              for a, b in zip(gt, truth)]
    assert max(angles) < 1e-3
    scene = json.loads((_folder(raw_twin) / "gt" / "scene.json").read_text())
    period = scene["raw_drive"]["frame_period_s"]
    assert period == pytest.approx(0.10351, abs=2e-4)  # the HDL-64E's spin on this drive
    np.testing.assert_allclose(np.diff([ds[i].time for i in range(4)]), period, atol=2e-6)
    # the day's calibration with the rig's extrinsic error in calib_velo_to_cam.txt, the rest verbatim
    stated = np.array(scene["realism"]["calibration"]["T_cam_velo_stated"])
    np.testing.assert_allclose(ds.calib.T_cam_velo, stated, atol=1e-9)
    real = scene["raw_drive"]["source"]
    for name in ("calib_cam_to_cam.txt", "calib_imu_to_velo.txt"):
        assert (raw_twin / "2011_09_26" / name).read_text() == (Path(real).parent / name).read_text()


def test_raw_twin_scans_are_raw_sweeps_timed_as_the_drives(raw_twin):
    folder = _folder(raw_twin)
    scene = json.loads((folder / "gt" / "scene.json").read_text())
    lidar, real = scene["lidar"], scene["realism"]
    assert not lidar["motion_compensated"] and lidar["sweep_s"] == pytest.approx(0.10351, abs=2e-4)
    assert not KittiRaw(raw_twin, DRIVE).scans_compensated
    start, forward, end = ([float(line[17:]) for line in (folder / "velodyne_points" / f"timestamps{s}.txt")
                            .read_text().splitlines()] for s in ("_start", "", "_end"))
    np.testing.assert_allclose(np.subtract(end, start), lidar["sweep_s"], atol=1e-6)
    np.testing.assert_allclose(np.subtract(forward, start), lidar["sweep_s"] / 2, atol=1e-6)
    # each return in the sensor at its own time lands on the camera's depth; read as compensated it does not
    gt = read_kitti_poses(folder / "gt" / "poses.txt")
    T_true = np.array(real["calibration"]["T_cam_velo_true"])
    fx = real["lidar_effects"]
    K = KittiRaw(raw_twin, DRIVE).calib.K
    i = 2
    scan = np.fromfile(folder / "velodyne_points" / "data" / f"{i:010d}.bin", np.float32).reshape(-1, 4)
    depth = np.load(folder / "gt" / "depth" / f"{i:010d}.npy")
    # the twin's clock runs 0.1 s a frame: a return's time scales with the sweep
    offset = real["rig"]["time_offset_s"] * sensors.FRAME_DT / lidar["sweep_s"]
    medians: dict[bool, tuple[float, float]] = {}
    for raw in (True, False):
        dt = offset + (point_times(scan) if raw else 0.0)
        T = PoseInterpolator(gt)(i * sensors.FRAME_DT + np.broadcast_to(dt, len(scan))) @ T_true
        p = _unbiased(scan, fx, np.array(lidar["elevations_deg"]))
        X = np.einsum("kij,kj->ki", T[:, :3, :3], p) + T[:, :3, 3]
        Xc = (X - gt[i, :3, 3]) @ gt[i, :3, :3]
        z = Xc[:, 2]
        front = (z > 2) & (z < 30) & (np.abs(Xc[:, 0]) > 0.5 * z)  # to the sides, where the sweep's motion shows
        u = np.rint(K[0, 0] * Xc[front, 0] / z[front] + K[0, 2]).astype(int)
        v = np.rint(K[1, 1] * Xc[front, 1] / z[front] + K[1, 2]).astype(int)
        ok = (u >= 0) & (u < depth.shape[1]) & (v >= 0) & (v < depth.shape[0])
        res = np.abs(z[front][ok] - depth[v[ok], u[ok]])
        medians[raw] = (float(np.median(res)), float(np.mean(res > 0.05)))
    (median, tail), (_, tail_compensated) = medians[True], medians[False]
    assert median < 0.02 and tail < 0.08 and tail_compensated > 3 * tail, medians


def _unbiased(scan: np.ndarray, fx: dict, elevations: np.ndarray) -> np.ndarray:
    """Raw returns -> the points they measured in the sensor frame (the beams' elevation errors taken out)."""
    p = scan[:, :3].astype(np.float64)
    r = np.linalg.norm(p, axis=1)
    el = np.degrees(np.arcsin(p[:, 2] / r))
    beam = np.argmin(np.abs(el[:, None] - elevations[None]), axis=1)
    true_el = np.radians(el + np.asarray(fx["beam_elevation_bias_deg"])[beam] + fx["elevation_offset_deg"])
    r = r - np.asarray(fx["beam_range_bias_m"])[beam]
    az = np.arctan2(p[:, 1], p[:, 0])
    return np.column_stack([np.cos(true_el) * np.cos(az), np.cos(true_el) * np.sin(az), np.sin(true_el)]) * r[:, None]


def test_raw_twin_path_is_the_oxts_without_their_timing_jitter(raw_root):
    """The oxts records are the 100 Hz samples nearest each frame: against the frame clock their steps alternate
    by +-5 cm; the twin's path, smoothed through them at their own times, steps evenly and keeps to them."""
    plan = plan_raw_twin(raw_root, DRIVE, None)
    drive = read_drive(raw_root, DRIVE)
    real = np.array([o.T_w_imu[:3, 3] for o in kitti_utils.load_oxts_packets_and_poses(
        sorted((raw_root / "2011_09_26" / f"{DRIVE}_sync" / "oxts" / "data").glob("*.txt")))])
    real_step = np.linalg.norm(np.diff(real, axis=0), axis=1)
    imu = plan.T_w_cam @ plan.calib.T_cam_velo @ T_velo_imu(plan.calib)  # the twin's path of the oxts unit
    twin_step = np.linalg.norm(np.diff(imu[:, :3, 3], axis=0), axis=1)
    jitter = lambda s: float(np.std(np.diff(s, 2)[5:-5]))  # noqa: E731
    assert jitter(real_step) > 0.03 and jitter(twin_step) < 0.006, (jitter(real_step), jitter(twin_step))
    assert abs(twin_step.sum() - real_step.sum()) < 0.001 * real_step.sum()
    # at the records' own times the smoothed IMU path stays within the GPS/INS noise of them
    pose, scale = smooth_path(drive)
    xyz = mercator(drive.packets, scale)
    xyz -= xyz[0]
    err = np.linalg.norm(pose(drive.oxts_times)[:, :3, 3] - xyz, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.005 and err.max() < 0.02


def test_raw_twin_bad_input_is_one_line(raw_root, tmp_path, capsys):
    argv = ["synth", "--out", str(tmp_path / "out"), "--raw-drive", str(raw_root)]
    assert main(argv + ["--seq", "2011_09_26_drive_9"]) == 2
    assert "expected a name like 2011_09_26_drive_0009" in capsys.readouterr().err
    assert main(argv + ["--seq", "2011_09_26_drive_0001"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "2011_09_26_drive_0001_sync/oxts/data: no oxts records" in err
    assert main(argv + ["--seq", DRIVE, "--frames", "0:9999"]) == 2
    assert "has 447 poses" in capsys.readouterr().err
    assert not (tmp_path / "out" / "2011_09_26").exists()
    with pytest.raises(SynthError, match="over the real drive"):
        generate_raw_twin(raw_root, raw_root, DRIVE, TwinSettings(str(raw_root), "0:2"))
