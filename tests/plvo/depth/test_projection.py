"""Scan projection, z-buffer and the patch / band index, against brute force."""

from __future__ import annotations

import numpy as np
import pytest
from depth_scene import kitti_calib, lidar_scan, street_scene

from plvo.depth.projection import expand_runs, project_scan, query_boxes, query_patches, query_segments, to_padded
from plvo.errors import PlvoError
from plvo.geometry.camera import project


@pytest.fixture(scope="module")
def proj():
    return project_scan(lidar_scan(street_scene(), noise_m=0.02), kitti_calib())


def test_projection_matches_camera_model_and_zbuffer_keeps_nearest(proj):
    calib = kitti_calib()
    scan = lidar_scan(street_scene(), noise_m=0.02).astype(float)
    pts = scan[proj.scan_index, :3] @ calib.T_cam_velo[:3, :3].T + calib.T_cam_velo[:3, 3]
    uv, z = project(calib.K, pts)
    np.testing.assert_allclose(proj.uv, uv, atol=1e-3)  # float32 transform
    np.testing.assert_allclose(proj.depth, z, atol=1e-4)
    # One point per pixel, and it is the nearest of all in-image returns landing in that pixel.
    pix = proj.uv.astype(int)
    assert len(np.unique(pix[:, 1] * 10000 + pix[:, 0])) == len(proj)
    all_uv, all_z = project(calib.K, scan[:, :3] @ calib.T_cam_velo[:3, :3].T + calib.T_cam_velo[:3, 3])
    ok = (all_z > 0.5) & (all_uv[:, 0] >= 0) & (all_uv[:, 1] >= 0) & (all_uv[:, 0] < 1241) & (all_uv[:, 1] < 376)
    key = all_uv[ok].astype(int) @ np.array([1, 10000])
    zmin = {}
    for k, zz in zip(key, all_z[ok]):
        zmin[k] = min(zz, zmin.get(k, np.inf))
    # The float32 transform may move a return across a pixel border: allow 0.5 % of the pixels to differ.
    assert abs(len(zmin) - len(proj)) <= 0.005 * len(proj)
    kept = dict(zip(pix @ np.array([1, 10000]), proj.depth))
    common = [k for k in zmin if k in kept]
    assert len(common) >= 0.995 * len(zmin)
    diff = np.array([abs(kept[k] - zmin[k]) for k in common])
    assert np.mean(diff < 1e-3) >= 0.995


def test_zbuffer_hides_a_farther_return_in_the_same_pixel():
    calib = kitti_calib()
    Tvc = np.linalg.inv(calib.T_cam_velo)
    near, far = np.array([0.1, 0.05, 5.0]), np.array([0.2, 0.1, 10.0])  # same pixel (x/z, y/z equal)
    scan = np.array([np.r_[Tvc[:3, :3] @ p + Tvc[:3, 3], 0.0] for p in (far, near)])
    proj = project_scan(scan, calib)
    assert len(proj) == 1 and abs(proj.depth[0] - 5.0) < 1e-4 and proj.scan_index[0] == 1


def test_expand_runs():
    out = expand_runs(np.array([5, 0, 9, 2]), np.array([3, 0, 1, 2]))
    assert out.tolist() == [5, 6, 7, 9, 2, 3]
    assert expand_runs(np.array([1]), np.array([0])).size == 0


def test_patch_and_band_queries_match_brute_force(proj):
    rng = np.random.default_rng(3)
    centers = np.c_[rng.uniform(-5, 1246, 300), rng.uniform(-5, 381, 300)]
    owner, idx = query_patches(proj, centers, 7.0)
    assert np.all(np.diff(owner) >= 0)
    for q in range(0, 300, 7):
        inside = np.all(np.abs(proj.uv - centers[q]) <= 7.0, axis=1)
        assert set(idx[owner == q]) == set(np.flatnonzero(inside))
    pidx, count = to_padded(owner, idx, len(centers))
    assert np.array_equal(count, np.bincount(owner, minlength=300))
    assert all(set(pidx[q, : count[q]]) == set(idx[owner == q]) for q in range(300))

    segs = np.c_[rng.uniform(0, 1241, (80, 1)), rng.uniform(150, 376, (80, 1)), rng.uniform(0, 1241, (80, 1)),
                 rng.uniform(150, 376, (80, 1))]
    owner, idx, t, perp = query_segments(proj, segs, 4.0)
    for m in range(80):
        a, b = segs[m, :2], segs[m, 2:]
        d = (b - a) / np.linalg.norm(b - a)
        rel = proj.uv - a
        tt = rel @ d / np.linalg.norm(b - a)
        pp = np.abs(rel[:, 0] * d[1] - rel[:, 1] * d[0])
        want = np.flatnonzero((pp <= 4.0) & (tt >= 0) & (tt <= 1))
        assert set(idx[owner == m]) == set(want)
    assert np.all((t >= 0) & (t <= 1) & (perp <= 4.0))


def test_box_query_empty_and_bad_scan(proj):
    owner, idx = query_boxes(proj, np.zeros((0, 4)))
    assert owner.size == 0 and idx.size == 0
    bad = np.zeros((3, 4), np.float32)
    bad[1, 0] = np.nan
    with pytest.raises(PlvoError, match="scan"):
        project_scan(bad, kitti_calib())
    with pytest.raises(PlvoError, match="scan"):
        project_scan(np.zeros((3, 2)), kitti_calib())
