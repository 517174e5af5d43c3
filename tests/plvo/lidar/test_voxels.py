"""plvo.lidar.voxels: the voxel means are open3d's voxel_down_sample's, bit for bit, on the back end's local map of
real KITTI scans and on points far apart; only their order may differ."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from plvo.config import RegistrationConfig
from plvo.data.kitti import KittiOdometry
from plvo.lidar.local_map import LocalMap
from plvo.lidar.registration import prepare
from plvo.lidar.voxels import voxel_means


def _open3d(points: np.ndarray, voxel_m: float, normals: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(normals)
    pc = pc.voxel_down_sample(voxel_m)
    if normals is None:
        return np.asarray(pc.points), None
    pc.normalize_normals()
    return np.asarray(pc.points), np.asarray(pc.normals)


def _same_set(a: np.ndarray, an: np.ndarray | None, b: np.ndarray, bn: np.ndarray | None) -> None:
    oa, ob = np.lexsort(a.T[::-1]), np.lexsort(b.T[::-1])
    assert a.shape == b.shape
    assert np.array_equal(a[oa], b[ob])  # the same floats, not merely close
    if an is not None:
        assert bn is not None and np.array_equal(an[oa], bn[ob])


@pytest.fixture(scope="module")
def real_map(kitti_root):
    """Ten keyframes of real KITTI 04 (every third frame) placed at their true poses, as the back end's map holds
    them: each scan downsampled and given normals in its own frame, then all of them in the world frame."""
    ds = KittiOdometry(kitti_root, "04")
    T_cv = np.asarray(ds.calib.T_cam_velo)
    cfg = RegistrationConfig()
    lmap = LocalMap(10, 0.5, cfg)
    for k, i in enumerate(range(0, 30, 3)):
        lmap.add(k, np.asarray(prepare(ds[i].scan, cfg).fine.points), ds.gt_T_world_cam[i] @ T_cv)
    return lmap


def test_the_local_maps_voxels_are_open3ds(real_map):
    from plvo.geometry import se3

    parts = [(e.T_world_lidar, *e.downsampled(real_map.voxel_m)) for e in real_map._entries]
    pts = np.concatenate([se3.transform_points(T, p) for T, p, _ in parts])
    nrm = np.concatenate([n @ T[:3, :3].T for T, _, n in parts])
    means, normals = voxel_means(pts, 0.5, nrm)
    assert len(means) < len(pts) / 2  # the scans overlap: many voxels hold several points
    _same_set(means, normals, *_open3d(pts, 0.5, nrm))
    built = real_map.cloud()
    _same_set(np.asarray(built.points), np.asarray(built.normals), means, normals)


def test_points_alone_far_apart_and_on_voxel_faces():
    rng = np.random.default_rng(3)
    pts = np.concatenate([rng.normal(0, 20, (5000, 3)), np.round(rng.normal(0, 5, (2000, 3)) / 0.3) * 0.3,
                          [[1e7, -1e7, 3e6]]])  # one far point: the three voxel indices overflow one int64 key
    for voxel in (0.3, 2.0):
        means, none = voxel_means(pts, voxel)
        assert none is None
        _same_set(means, None, *_open3d(pts, voxel, None))


def test_normals_that_cancel_stay_zero_and_nothing_in_gives_nothing_out():
    pts = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [5.0, 5.0, 5.0]])
    nrm = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.6, 0.8, 0.0]])
    means, normals = voxel_means(pts, 1.0, nrm)
    _same_set(means, normals, *_open3d(pts, 1.0, nrm))
    assert np.array_equal(normals[0], [0.0, 0.0, 0.0])
    empty, empty_normals = voxel_means(np.zeros((0, 3)), 0.5, np.zeros((0, 3)))
    assert empty.shape == (0, 3) and empty_normals is not None and empty_normals.shape == (0, 3)
