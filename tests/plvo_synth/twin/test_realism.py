"""The twins' sensor imperfections (plvo_synth.twin.realism), each measured on a twin against its setting.

In-process on one twin world (07, frames 60:64): range noise against the surfaces (the same rays without noise), a
biased beam's elevation measured back by casting candidate elevations into the world, dropouts, returns from
inside tree crowns, the recording car's shadow. On a generated 6-frame twin with exaggerated rig errors: the
compensated sweep lands on the camera's depth at the lidar's reference instant, the time offset and the extrinsic
error measured between what the lidar and the camera see. An ideal twin is described as twins were before."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from plvo.data.kitti import KittiOdometry
from plvo.errors import SynthError
from plvo_synth import sensors
from plvo_synth.kitti_calib import CALIB_00_02, CALIB_04_10, CALIB_2011_09_26, odometry_calibration
from plvo_synth.twin.camera_effects import IDEAL_CAMERA
from plvo_synth.twin.follow import PoseInterpolator
from plvo_synth.twin.generate import TwinSettings, build_twin, generate_twin
from plvo_synth.twin.lidars import EGO_FIRST_RING, LidarEffects, ego_return_share, sweep_time
from plvo_synth.twin.realism import IDEAL, IDEAL_LIDAR, LidarRealism, Realism, RigRealism
from plvo_synth.twin.scenery_realism import IDEAL_SCENERY

SEQ = "07"
QUIET = LidarRealism(range_noise_m=0.0, beam_elevation_sigma_deg=0.0, beam_range_sigma_m=0.0,
                     elevation_offset_deg=0.0, dropout_floor=0.0, dropout_dark=0.0, dropout_glass=0.0,
                     foliage_scatter=0.0, ego_occlusion=False)


def _replace(lidar: LidarRealism, **kw) -> LidarRealism:
    return LidarRealism(**{**lidar.__dict__, **kw})


@pytest.fixture(scope="module")
def world(kitti_root):
    """One twin of 07 (frames 60:64, no traffic, closed crowns), built once: its renderer scans with any lidar
    effects."""
    settings = TwinSettings(str(kitti_root / "poses" / f"{SEQ}.txt"), "60:64", traffic=0,
                            realism=Realism(scenery=IDEAL_SCENERY))
    return build_twin(settings, SEQ)


def _scan(world, lidar: LidarRealism | None, i: int = 2, seed: int = 3):
    """Frame i's raw sweep with `lidar`'s effects (None: none) -> (N,4) scan and (N,) ray ids into rays()."""
    r = world.renderer
    r.lidar_effects = None if lidar is None else LidarEffects(r.lidar, lidar, world.seed)
    poses = PoseInterpolator(world.path.T_town_cam)
    scan, _ = r.scan_twin(poses, i * sensors.FRAME_DT, world.T_cam_velo, np.random.default_rng(seed),
                          np.random.default_rng(seed + 1))
    return scan, _ray_ids(r.lidar, scan)


def _ray_ids(model, scan: np.ndarray) -> np.ndarray:
    """Each return's ray (column * beams + beam), from its reported direction: the beams' nominal elevations and the
    columns' azimuths."""
    el = np.degrees(np.arctan2(scan[:, 2], np.hypot(scan[:, 0], scan[:, 1])))
    beam = np.argmin(np.abs(el[:, None] - np.asarray(model.elevations_deg)[None]), axis=1)
    az = np.arctan2(scan[:, 1], scan[:, 0])
    col = np.rint((np.pi - az) / (2 * np.pi) * model.azimuth_steps - 0.5).astype(int) % model.azimuth_steps
    return col * len(model.elevations_deg) + beam


def _matched(a_ids, b_ids):
    common, ia, ib = np.intersect1d(a_ids, b_ids, return_indices=True)
    return ia, ib


def test_range_noise_against_the_surfaces(world):
    truth, t_ids = _scan(world, QUIET)
    noisy, n_ids = _scan(world, _replace(QUIET, range_noise_m=0.05))
    ia, ib = _matched(t_ids, n_ids)
    assert len(ia) > 0.95 * len(truth) > 50_000
    err = np.linalg.norm(noisy[ib, :3], axis=1) - np.linalg.norm(truth[ia, :3], axis=1)
    assert np.std(err) == pytest.approx(0.05, rel=0.03)
    assert abs(np.mean(err)) < 0.002
    # the realistic level, measured on KITTI's scans (scripts/lidar_realism_stats.py): 1 cm
    real, r_ids = _scan(world, _replace(QUIET, range_noise_m=LidarRealism().range_noise_m))
    ia, ib = _matched(t_ids, r_ids)
    err = np.linalg.norm(real[ib, :3], axis=1) - np.linalg.norm(truth[ia, :3], axis=1)
    assert np.std(err) == pytest.approx(0.010, rel=0.05)


def test_a_biased_beams_elevation_is_measured_back(world):
    """The sensor reports each beam at its nominal elevation; its laser points bias + the global offset higher.
    Casting rays at candidate elevations into the world, the one whose ranges match the reported ones is it."""
    lidar = _replace(QUIET, beam_elevation_sigma_deg=0.3, beam_range_sigma_m=0.0, elevation_offset_deg=0.205)
    scan, ids = _scan(world, lidar)
    r, model = world.renderer, world.renderer.lidar
    bias = r.lidar_effects.elevation_bias_deg
    B = len(model.elevations_deg)
    poses = PoseInterpolator(world.path.T_town_cam)
    checked = 0
    for beam in (36, 44, int(np.argmax(np.abs(bias[32:]))) + 32):
        k = np.flatnonzero(ids % B == beam)
        cols = ids[k] // B
        T = poses(2 * sensors.FRAME_DT + sweep_time(model.azimuths()[cols])) @ world.T_cam_velo
        reported = np.linalg.norm(scan[k, :3], axis=1)
        nominal = model.elevations_deg[beam]
        candidates = nominal + np.arange(-0.8, 0.8, 0.005)
        cost = []
        for e in candidates:
            d = np.stack([np.cos(np.radians(e)) * np.cos(model.azimuths()[cols]),
                          np.cos(np.radians(e)) * np.sin(model.azimuths()[cols]),
                          np.full(len(cols), np.sin(np.radians(e)))], axis=1)
            rays = np.concatenate([T[:, :3, 3], np.einsum("kij,kj->ki", T[:, :3, :3], d)], axis=1)
            t = r.scene.cast_rays(o3d.core.Tensor.from_numpy(rays.astype(np.float32)))["t_hit"].numpy()
            cost.append(np.median(np.abs(t - reported)))
        measured = candidates[int(np.argmin(cost))] - nominal
        assert measured == pytest.approx(bias[beam] + 0.205, abs=0.012), (beam, measured, bias[beam])
        checked += 1
    assert checked == 3 and np.abs(bias).max() > 0.2


def test_dropouts_against_their_setting(world):
    full, f_ids = _scan(world, QUIET)
    floor, d_ids = _scan(world, _replace(QUIET, dropout_floor=0.2))
    assert len(floor) / len(full) == pytest.approx(0.8, abs=0.01)
    # dark surfaces lose more: the lost returns are darker than those kept
    dark, k_ids = _scan(world, _replace(QUIET, dropout_dark=0.9, dropout_dark_reflectance=0.1))
    lost = ~np.isin(f_ids, k_ids)
    assert 0.05 < lost.mean() < 0.9
    assert full[lost, 3].mean() < full[~lost, 3].mean() - 0.03
    # a surface of reflectance r keeps 1 - 0.9 exp(-r / 0.1) of its returns: compare where the tint is 1 (the
    # ground's reflectance is its darkness)
    ground = (np.abs(full[:, 2] + 1.73) < 0.3) & (np.hypot(full[:, 0], full[:, 1]) < 20)
    p = 0.9 * np.exp(-full[ground, 3] / 0.1)
    assert lost[ground].mean() == pytest.approx(p.mean(), abs=0.03)


def test_returns_from_inside_tree_crowns(world):
    truth, t_ids = _scan(world, QUIET)
    scattered, s_ids = _scan(world, _replace(QUIET, foliage_scatter=0.5, foliage_depth_m=0.4))
    ia, ib = _matched(t_ids, s_ids)
    extra = np.linalg.norm(scattered[ib, :3], axis=1) - np.linalg.norm(truth[ia, :3], axis=1)
    inside = extra > 1e-3
    assert (extra > -1e-3).all()  # only ever deeper than the crown's surface
    assert inside.sum() > 200
    assert np.mean(extra[inside]) == pytest.approx(0.4, rel=0.15)


def test_the_recording_cars_shadow(world):
    full, f_ids = _scan(world, QUIET)
    shadowed, s_ids = _scan(world, _replace(QUIET, ego_occlusion=True))
    B = len(world.renderer.lidar.elevations_deg)
    clear = ego_return_share(world.renderer.lidar)
    assert set(np.unique(clear)) == {0.0, 1.0}
    assert (clear[s_ids] == 1.0).all()  # no return where the car's body is
    upper = f_ids % B < EGO_FIRST_RING
    assert np.isin(f_ids[upper], s_ids).all()  # the upper beams see past it
    lowest = f_ids % B == B - 1
    kept = np.isin(f_ids[lowest], s_ids).mean()
    assert 0.35 < kept < 0.75  # KITTI's lowest beam returns 54-56 % of its firings (drives 04 and 0009)


def test_odometry_sequences_have_their_own_calibration():
    assert odometry_calibration("00") is CALIB_00_02 and odometry_calibration("02") is CALIB_00_02
    assert odometry_calibration("03") is CALIB_2011_09_26 and odometry_calibration("07") is CALIB_04_10
    assert (CALIB_04_10.width, CALIB_04_10.height) == (1226, 370)
    assert (CALIB_2011_09_26.width, CALIB_2011_09_26.height) == (1242, 375)
    # 03's Tr is R_rect_00 @ [R|T] of the day's calib_velo_to_cam.txt, as KITTI's own 03 calib.txt has it
    np.testing.assert_allclose(CALIB_2011_09_26.T_cam_velo[:3, 3], [-2.796816941295e-03, -7.510879138296e-02,
                                                                    -2.721327964059e-01], atol=1e-12)
    stated = CALIB_04_10.odometry_text_with(CALIB_04_10.T_cam_velo)
    assert stated == CALIB_04_10.odometry_text


def test_realism_settings_are_checked():
    with pytest.raises(SynthError, match="lidar.dropout_floor"):
        Realism(lidar=_replace(QUIET, dropout_floor=1.5)).check()
    with pytest.raises(SynthError, match="sweep 'sideways'"):
        Realism(sweep="sideways").check()
    with pytest.raises(SynthError, match="rig.calibration"):
        Realism(rig=RigRealism(calibration="mine")).check()


# ---------------------------------------------------------------- a generated twin with exaggerated rig errors

RIG = RigRealism(calibration="own", extrinsic_rotation_deg=0.5, extrinsic_translation_m=0.05, time_offset_s=0.03)


@pytest.fixture(scope="module")
def rig_twin(kitti_root, tmp_path_factory):
    realism = Realism(camera=IDEAL_CAMERA, lidar=_replace(QUIET, range_noise_m=0.01), rig=RIG, scenery=IDEAL_SCENERY)
    root = tmp_path_factory.mktemp("rig_twin")
    settings = TwinSettings(str(kitti_root / "poses" / f"{SEQ}.txt"), "60:66", traffic=0, write_depth=True,
                            realism=realism)
    return generate_twin(root, SEQ, settings)


def _lidar_in_world(root, i: int, T_cam_velo: np.ndarray, offset: float) -> np.ndarray:
    """Frame i's compensated scan taken to the world as the lidar at the frame's time + offset."""
    ds = KittiOdometry(root, SEQ)
    gt = ds.gt_T_world_cam
    scan = np.fromfile(root / "sequences" / SEQ / "velodyne" / f"{i:06d}.bin", np.float32).reshape(-1, 4)
    T = PoseInterpolator(gt)(np.array([i * sensors.FRAME_DT + offset]))[0] @ T_cam_velo
    return scan[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]


def _depth_residual(root, i: int, X: np.ndarray) -> np.ndarray:
    """|z - depth| (m) of world points X seen by cam0 at frame i, where the depth is smooth around them."""
    ds = KittiOdometry(root, SEQ)
    gt, K = ds.gt_T_world_cam, ds.calib.K
    depth = np.load(root / "sequences" / SEQ / "gt" / "depth" / f"{i:06d}.npy")
    Xc = (X - gt[i, :3, 3]) @ gt[i, :3, :3]
    z = Xc[:, 2]
    front = (z > 2.0) & (z < 30.0)
    u = K[0, 0] * Xc[front, 0] / z[front] + K[0, 2]
    v = K[1, 1] * Xc[front, 1] / z[front] + K[1, 2]
    ok = (u >= 1) & (u < depth.shape[1] - 2) & (v >= 1) & (v < depth.shape[0] - 2)
    iu, iv = np.rint(u[ok]).astype(int), np.rint(v[ok]).astype(int)
    nb = np.stack([depth[iv + a, iu + b] for a in (-1, 0, 1) for b in (-1, 0, 1)], axis=1)
    smooth = np.isfinite(nb).all(axis=1) & (np.ptp(nb, axis=1) < 0.05 * nb.min(axis=1))
    return np.abs(z[front][ok][smooth] - depth[iv[smooth], iu[smooth]])


def _scene(root) -> dict:
    return json.loads((root / "sequences" / SEQ / "gt" / "scene.json").read_text())


def test_compensated_scans_land_at_the_lidars_instant(rig_twin):
    scene = _scene(rig_twin)
    assert scene["lidar"]["motion_compensated"] and scene["lidar"]["sweep_s"] == 0.0
    assert KittiOdometry(rig_twin, SEQ).scans_compensated  # read as KITTI's: not deskewed again
    T_true = np.array(scene["realism"]["calibration"]["T_cam_velo_true"])
    res = _depth_residual(rig_twin, 3, _lidar_in_world(rig_twin, 3, T_true, RIG.time_offset_s))
    assert len(res) > 10_000
    assert np.median(res) < 0.02 and np.mean(res < 0.1) > 0.95


def test_time_offset_measured_between_lidar_and_camera(rig_twin):
    T_true = np.array(_scene(rig_twin)["realism"]["calibration"]["T_cam_velo_true"])
    offsets = np.arange(-0.01, 0.061, 0.005)
    cost = [np.median(_depth_residual(rig_twin, 3, _lidar_in_world(rig_twin, 3, T_true, dt))) for dt in offsets]
    assert offsets[int(np.argmin(cost))] == pytest.approx(RIG.time_offset_s, abs=0.0051)
    assert max(cost) > 3 * min(cost)


def test_extrinsic_error_measured_between_lidar_and_camera(rig_twin):
    """Point-to-plane ICP of the lidar's returns (taken with the calibration the twin states) onto the camera's
    depth recovers the error recorded in scene.json."""
    scene = _scene(rig_twin)
    stated_file = KittiOdometry(rig_twin, SEQ).calib.T_cam_velo
    recorded = np.array(scene["realism"]["rig"]["extrinsic_error"]["T_stated_true_cam"])
    T_true = np.array(scene["realism"]["calibration"]["T_cam_velo_true"])
    np.testing.assert_allclose(stated_file, recorded @ T_true, atol=1e-9)
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(recorded[:3, :3]).as_rotvec()))
    assert angle > 0.3 and np.linalg.norm(recorded[:3, 3]) > 0.03
    ds = KittiOdometry(rig_twin, SEQ)
    gt, K = ds.gt_T_world_cam, ds.calib.K
    i = 3
    X = _lidar_in_world(rig_twin, i, stated_file, RIG.time_offset_s)
    source = (X - gt[i, :3, 3]) @ gt[i, :3, :3]  # cam0 at the frame's time, as the stated calibration has it
    depth = np.load(rig_twin / "sequences" / SEQ / "gt" / "depth" / f"{i:06d}.npy")
    v, u = np.nonzero(np.isfinite(depth) & (depth < 30.0))
    z = depth[v, u].astype(np.float64)
    target = np.column_stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source[(source[:, 2] > 2) & (source[:, 2] < 30)]))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(12))
    fit = o3d.pipelines.registration.registration_icp(
        src, tgt, 0.3, np.eye(4), o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=60))
    measured = np.linalg.inv(fit.transformation)  # stated = measured @ true
    err = Rotation.from_matrix(measured[:3, :3] @ recorded[:3, :3].T).as_rotvec()
    assert np.degrees(np.linalg.norm(err)) < 0.05
    assert np.linalg.norm(measured[:3, 3] - recorded[:3, 3]) < 0.02


def test_ideal_twin_is_described_as_before(kitti_root, tmp_path):
    settings = TwinSettings(str(kitti_root / "poses" / f"{SEQ}.txt"), "60:62", traffic=0, realism=IDEAL)
    root = generate_twin(tmp_path, SEQ, settings)
    seq = root / "sequences" / SEQ
    scene = json.loads((seq / "gt" / "scene.json").read_text())
    assert "realism" not in scene and "realism" not in scene["settings"]
    assert set(scene["lidar"]) == {"name", "elevations_deg", "azimuth_steps", "max_range_m", "min_range_m",
                                   "range_noise_m", "sweep_s", "timing"}
    assert scene["lidar"]["sweep_s"] == 0.1 and not KittiOdometry(root, SEQ).scans_compensated
    assert (seq / "calib.txt").read_text() == sensors.KITTI_CALIB_00_TEXT
    assert KittiOdometry(root, SEQ).calib.width == 1241
    scan = np.fromfile(seq / "velodyne" / "000001.bin", np.float32).reshape(-1, 4)
    assert 0.019 < _range_noise(scan) < 0.024  # the ideal lidar's 2 cm
    assert IDEAL.lidar == IDEAL_LIDAR and IDEAL.is_ideal and not Realism().is_ideal


def _range_noise(scan: np.ndarray) -> float:
    """Robust sigma of the second difference of range between neighbouring returns of a beam (4-25 m), / sqrt(6):
    the range noise, where the surfaces are smooth (about 8 % above it on a twin's slanted ground)."""
    el = np.round(np.degrees(np.arctan2(scan[:, 2], np.hypot(scan[:, 0], scan[:, 1]))), 1)
    az = np.arctan2(scan[:, 1], scan[:, 0])
    r = np.linalg.norm(scan[:, :3], axis=1)
    out = []
    for b in np.unique(el):
        k = np.flatnonzero(el == b)
        rr = r[k[np.argsort(-az[k])]]
        near = (rr[1:-1] > 4) & (rr[1:-1] < 25)
        out.append((rr[:-2] - 2 * rr[1:-1] + rr[2:])[near])
    d = np.concatenate(out)
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(6.0))
