"""The synthetic town sequence: KITTI layout and loaders, sensor consistency, ground truth (one 20-frame sequence)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pykitti
import pytest

from plvo.data.kitti import KittiOdometry
from plvo_synth import SynthSettings, plan_trajectory, sensors
from plvo_synth.mesh import EDGE_TEXTURE

N = 20  # conftest.SYNTH_SEQ_FRAMES
SPEED = 10.0


def _read_depth(root, i):
    return np.load(root / "sequences" / "00" / "gt" / "depth" / f"{i:06d}.npy")


def test_pykitti_reads_the_sequence_unchanged(synth_seq):
    data = pykitti.odometry(str(synth_seq), "00")
    assert len(data) == N and len(data.cam0_files) == N and len(data.velo_files) == N
    np.testing.assert_allclose(data.calib.K_cam0, sensors.K_CAM0)
    np.testing.assert_allclose(data.calib.T_cam0_velo, sensors.T_CAM_VELO)
    assert data.calib.b_gray == pytest.approx(0.537, abs=0.002)  # KITTI seq 00 stereo baseline
    assert len(data.poses) == N
    np.testing.assert_allclose(data.poses[0], np.eye(4), atol=1e-9)
    image = data.get_cam0(3)
    assert image.mode == "L" and image.size == (1241, 376)
    scan = data.get_velo(3)
    assert scan.dtype == np.float32 and scan.shape[1] == 4 and 100_000 < len(scan) <= 128_000
    assert np.isfinite(scan).all() and scan[:, 3].min() >= 0.0 and scan[:, 3].max() < 1.0
    assert np.linalg.norm(scan[:, :3], axis=1).max() < sensors.LIDAR_MAX_RANGE_M + 0.1
    assert [t.total_seconds() for t in data.timestamps[:3]] == pytest.approx([0.0, 0.1, 0.2])


def test_calib_is_kittis_sequence_00(synth_seq, kitti_root):
    ours = (synth_seq / "sequences" / "00" / "calib.txt").read_text().split()
    real = (kitti_root / "calib" / "00-02.txt").read_text().split()
    assert ours == real


def test_kitti_loader_reads_frames_with_ground_truth(synth_seq):
    ds = KittiOdometry(synth_seq, "00")
    assert len(ds) == N
    gt = ds.gt_T_world_cam
    assert gt is not None and gt.shape == (N, 4, 4)
    planned = plan_trajectory(SynthSettings(n_frames=N, seed=0, speed_mps=SPEED))
    np.testing.assert_allclose(gt, planned.T_world_cam, atol=1e-6)
    frame = ds[7]
    assert frame.image.shape == (376, 1241) and frame.image.dtype == np.uint8
    assert frame.scan.dtype == np.float32 and frame.scan.shape[1] == 4
    np.testing.assert_allclose(frame.calib.K, sensors.K_CAM0)
    np.testing.assert_allclose(frame.calib.T_cam_velo, sensors.T_CAM_VELO)
    np.testing.assert_allclose(frame.gt_T_world_cam, planned.T_world_cam[7], atol=1e-6)
    assert frame.time == pytest.approx(0.7)


def test_ground_truth_motion_is_the_trajectorys(synth_seq):
    poses = np.loadtxt(synth_seq / "poses" / "00.txt").reshape(-1, 3, 4)
    steps = np.linalg.norm(np.diff(poses[:, :, 3], axis=0), axis=1)
    # 10 m/s at 10 Hz: 1 m a frame (a chord on the 8 m turn arcs is at most 0.1 % shorter).
    np.testing.assert_allclose(steps, SPEED * 0.1, rtol=2e-3)
    # The camera stays level at one height: no motion along the world's y (down) axis, rotation about y only.
    np.testing.assert_allclose(poses[:, 1, 3], 0.0, atol=1e-8)
    np.testing.assert_allclose(poses[:, 1, :3], np.tile([0.0, 1.0, 0.0], (N, 1)), atol=1e-8)


def test_camera_is_165_m_above_the_road(synth_seq):
    depth = _read_depth(synth_seq, 0)
    v = np.arange(300, 376)
    z = depth[v, 620]  # the lane straight ahead
    y = (v - sensors.K_CAM0[1, 2]) / sensors.K_CAM0[1, 1] * z  # height below the camera
    np.testing.assert_allclose(y, sensors.CAMERA_HEIGHT_M, atol=0.01)


@pytest.mark.parametrize("i", [0, 13])
def test_lidar_points_land_on_the_rendered_surfaces(synth_seq, i):
    scan = np.fromfile(synth_seq / "sequences" / "00" / "velodyne" / f"{i:06d}.bin", np.float32).reshape(-1, 4)
    depth = _read_depth(synth_seq, i)
    pts = scan[:, :3] @ sensors.T_CAM_VELO[:3, :3].T + sensors.T_CAM_VELO[:3, 3]
    pts = pts[pts[:, 2] > 1.0]
    uv = pts[:, :2] / pts[:, 2:] * np.diag(sensors.K_CAM0)[:2] + sensors.K_CAM0[:2, 2]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < 1240) & (uv[:, 1] >= 0) & (uv[:, 1] < 375)
    uv, z = uv[inside], pts[inside, 2]
    assert len(z) > 10_000
    u0, v0 = np.floor(uv).astype(int).T
    near = np.stack([depth[v0, u0], depth[v0, u0 + 1], depth[v0 + 1, u0], depth[v0 + 1, u0 + 1]])
    # Between the depths of the 4 surrounding pixel centres, give or take 4 sigma of range noise.
    tol = 4 * sensors.LIDAR_RANGE_NOISE_M
    on_surface = (z >= near.min(axis=0) - tol) & (z <= near.max(axis=0) + tol)
    assert on_surface.mean() > 0.97
    nearest = depth[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]
    close = z < 15.0
    assert np.median(np.abs(nearest[close] - z[close])) < 0.05


def test_town_edges_lie_on_the_rendered_surfaces(synth_seq):
    gt = synth_seq / "sequences" / "00" / "gt"
    edges, kind = np.load(gt / "edges.npy"), np.load(gt / "edge_kind.npy")
    assert edges.ndim == 3 and edges.shape[1:] == (2, 3) and len(kind) == len(edges)
    depth = _read_depth(synth_seq, 0)  # frame 0's camera is the world frame
    e = edges[(kind == EDGE_TEXTURE) & (edges[:, :, 2].min(axis=1) > 3.0) & (edges[:, :, 2].max(axis=1) < 40.0)]
    t = np.linspace(0.05, 0.95, 9)
    pts = e[:, None, 0] * (1 - t[None, :, None]) + e[:, None, 1] * t[None, :, None]  # (E,9,3)
    uv = pts[..., :2] / pts[..., 2:] * np.diag(sensors.K_CAM0)[:2] + sensors.K_CAM0[:2, 2]
    ui, vi = np.rint(uv[..., 0]).astype(int), np.rint(uv[..., 1]).astype(int)
    inside = (ui >= 0) & (ui < 1241) & (vi >= 0) & (vi < 376)
    rendered = np.where(inside, depth[np.clip(vi, 0, 375), np.clip(ui, 0, 1240)], np.nan)
    rel = np.abs(rendered - pts[..., 2]) / pts[..., 2]
    with np.errstate(invalid="ignore"):
        visible = (rel < 0.02).mean(axis=1) >= 0.8  # others are behind buildings or out of view
    # Window and door outlines in view and unoccluded lie exactly on the rendered walls.
    assert visible.sum() >= 40, f"only {visible.sum()} of {len(e)} texture edges lie on rendered surfaces"
    assert np.nanmedian(rel[visible]) < 0.002


def test_scene_json_records_the_settings(synth_seq):
    scene = json.loads((synth_seq / "sequences" / "00" / "gt" / "scene.json").read_text())
    assert scene["settings"] == {"n_frames": N, "seed": 0, "speed_mps": SPEED, "loop": False, "stops": False,
                                 "exposure_change": 0.0, "write_depth": True}
    assert scene["frames"]["still_frames"] == []
    assert len(scene["camera"]["exposure_gains"]) == N


def test_frames_give_kitti_like_features(synth_seq):
    image = cv2.imread(str(synth_seq / "sequences" / "00" / "image_0" / "000010.png"), cv2.IMREAD_GRAYSCALE)
    assert len(cv2.ORB_create(1000).detect(image, None)) >= 900  # real KITTI seq 04 frames: 1000
    segs = cv2.createLineSegmentDetector().detect(image)[0].reshape(-1, 4)
    long = np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1]) >= 50
    assert len(segs) >= 300 and long.sum() >= 20  # real KITTI seq 04: about 1100 and 46 on average


def test_exposure_gain_scales_the_image():
    from plvo_synth import path as paths
    from plvo_synth.render import Renderer
    from plvo_synth.textures import build_atlas
    from plvo_synth.town import build_town

    traj = plan_trajectory(SynthSettings(n_frames=2, seed=9))
    T_town_cam = traj.T_town_world
    town = build_town(paths.make_grid(9), T_town_cam[None, :2, 3], 9)
    renderer = Renderer(town, build_atlas(9), 9)
    dark, depth = renderer.render(T_town_cam, 0.8, np.random.default_rng(0))
    bright, depth2 = renderer.render(T_town_cam, 1.2, np.random.default_rng(0))
    np.testing.assert_array_equal(depth, depth2)
    ok = (bright < 250) & (dark > 20)  # unsaturated pixels
    ratio = bright[ok].astype(float).sum() / dark[ok].astype(float).sum()
    assert ratio == pytest.approx(1.5, rel=0.02)
