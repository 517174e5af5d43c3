"""Point depth priors on analytic scenes: accuracy by range, foreground at depth edges, reason codes."""

from __future__ import annotations

import numpy as np
import pytest
from depth_scene import (
    HEIGHT,
    K_KITTI,
    TR_KITTI,
    WIDTH,
    Scene,
    kitti_calib,
    lidar_scan,
    street_scene,
    true_depth,
)

from plvo.config import DepthConfig
from plvo.depth.points import point_depths
from plvo.depth.projection import project_scan
from plvo.depth.segmentation import depth_clusters, fit_planes, grow_foreground
from plvo.types import DEPTH_GRAZING_RAY, DEPTH_OK, DEPTH_TOO_FEW_POINTS

CFG = DepthConfig()


def patch_true_depths(scene: Scene, uv: np.ndarray, half: float) -> np.ndarray:
    """(N,2) -> (N,25) exact depths on a 5x5 grid over each feature's patch."""
    off = np.linspace(-half, half, 5)
    grid = np.stack(np.meshgrid(off, off), -1).reshape(-1, 2)
    return true_depth(scene, (uv[:, None, :] + grid[None]).reshape(-1, 2)).reshape(len(uv), -1)


def street_features(step: float = 9.0):
    scene = street_scene()
    proj = project_scan(lidar_scan(scene, noise_m=0.02), kitti_calib())
    uu, vv = np.meshgrid(np.arange(12, WIDTH - 12, step), np.arange(150, HEIGHT - 10, step))
    uv = np.stack([uu.ravel(), vv.ravel()], 1)
    res = point_depths(proj, uv, K_KITTI, CFG)
    zt = true_depth(scene, uv)
    zp = patch_true_depths(scene, uv, CFG.point_patch_px)
    return scene, uv, res, zt, zp


@pytest.fixture(scope="module")
def street():
    return street_features()


def range_stats(res, zt, zp):
    """Median / 90th percentile absolute error of priors at pixels with no depth edge in their patch."""
    interior = np.all(np.isfinite(zp), 1) & (zp.max(1) <= 1.05 * zp.min(1))
    ok = res.reason == DEPTH_OK
    err = np.abs(res.depth - zt)
    out = {}
    for lo, hi in [(0, 10), (10, 20), (20, 40)]:
        m = interior & (zt >= lo) & (zt < hi)
        e = err[m & ok]
        out[(lo, hi)] = (int(m.sum()), int((m & ok).sum()), float(np.median(e)), float(np.percentile(e, 90)))
    return out


def test_point_depth_accuracy_by_range(street):
    _, _, res, zt, zp = street
    stats = range_stats(res, zt, zp)
    # (n interior, n with prior, median |error| m, p90 |error| m); 2 cm lidar range noise.
    for (lo, hi), (n, n_ok, med, p90) in stats.items():
        assert n_ok >= 0.6 * n, (lo, hi, n, n_ok)
        assert med <= 0.01 + 0.001 * hi, (lo, hi, med)
        assert p90 <= 0.03 + 0.004 * hi, (lo, hi, p90)


def test_depth_edges_take_the_foreground_never_a_mix(street):
    _, _, res, zt, zp = street
    edge = np.all(np.isfinite(zp), 1) & (zp.max(1) > 1.2 * zp.min(1))
    ok = edge & (res.reason == DEPTH_OK)
    fg = zp.min(1)
    near_fg = np.abs(res.depth - fg) <= 0.05 * fg
    near_own = np.abs(res.depth - zt) <= 0.05 * zt
    assert edge.sum() > 100 and ok.sum() > 0.4 * edge.sum()
    mix = ok & ~near_fg & ~near_own
    assert mix.sum() <= 0.03 * ok.sum(), mix.sum()


def test_pillar_and_pole_silhouettes_take_their_own_depth():
    scene = street_scene()
    proj = project_scan(lidar_scan(scene, noise_m=0.02), kitti_calib())
    # Columns of the square pillar's front-face edges (x = 8 m, y = +-0.15 m in the lidar frame).
    uv_edges, want = [], []
    for y in (-0.15, 0.15):
        p = TR_KITTI[:3, :3] @ np.array([8.0, y, 0.0]) + TR_KITTI[:3, 3]
        u = K_KITTI[0, 0] * p[0] / p[2] + K_KITTI[0, 2]
        for du in (-1.5, -0.5, 0.5, 1.5):
            for v in np.arange(200.0, 282.0, 6.0):
                uv_edges.append([u + du, v])
                want.append(p[2])
    # Round pole at (10, 2) lidar frame, radius 0.15: its silhouette columns. Rows stop above the feet of both,
    # where the road in front is the patch's foreground.
    c = TR_KITTI[:3, :3] @ np.array([10.0, 2.0, 0.0]) + TR_KITTI[:3, 3]
    half = K_KITTI[0, 0] * 0.15 / c[2]
    uc = K_KITTI[0, 0] * c[0] / c[2] + K_KITTI[0, 2]
    for du in (-half - 1, -half + 1, half - 1, half + 1):
        for v in np.arange(200.0, 282.0, 6.0):
            uv_edges.append([uc + du, v])
            want.append(c[2] - 0.05)  # the pole's skin near its silhouette is 0-0.15 m before its axis
    uv_edges, want = np.array(uv_edges), np.array(want)
    res = point_depths(proj, uv_edges, K_KITTI, CFG)
    ok = res.reason == DEPTH_OK
    assert ok.mean() >= 0.8, ok.mean()
    err = np.abs(res.depth[ok] - want[ok])
    assert np.max(err) <= 0.15, np.max(err)  # the wall behind is 6 m (pillar) / 4 m (pole) farther: no mixing
    assert np.median(err) <= 0.06


def test_reasons_too_few_points_and_grazing():
    scene = Scene(boxes=[], ground=True)
    proj = project_scan(lidar_scan(scene, noise_m=0.0), kitti_calib())
    # Above the horizon there is no return; on the road far ahead the ray grazes the ground plane.
    far_v = K_KITTI[1, 2] + K_KITTI[1, 1] * 1.65 / 25.0
    uv = np.array([[600.0, 100.0], [600.0, far_v], [600.0, 330.0]])
    res = point_depths(proj, uv, K_KITTI, CFG)
    assert res.reason[0] == DEPTH_TOO_FEW_POINTS and np.isnan(res.depth[0])
    assert res.reason[1] == DEPTH_GRAZING_RAY and np.isnan(res.depth[1])
    assert res.reason[2] == DEPTH_OK
    zt = true_depth(scene, uv[2:])
    assert abs(res.depth[2] - zt[0]) < 0.02
    # The plane found is the road: normal along the camera's y axis.
    assert abs(abs(res.plane[2, 1]) - 1.0) < 0.01
    empty = point_depths(project_scan(np.zeros((0, 4), np.float32), kitti_calib()), uv, K_KITTI, CFG)
    assert np.all(empty.reason == DEPTH_TOO_FEW_POINTS)


def test_segmentation_bridges_scan_rings_of_one_surface_but_not_an_occluder():
    # Road seen at a slant: 3 rings 1.6 m apart in depth, one plane -> one foreground.
    xs = np.linspace(-0.3, 0.3, 12)
    road = np.concatenate([np.c_[xs, np.full(12, 1.65), np.full(12, z)] for z in (18.0, 19.6, 21.3)])
    # Pole (0.3 m wide, vertical) at 10 m in front of a wall at 15 m.
    ys = np.linspace(-0.3, 0.3, 4)
    pole = np.array([[x, y, 10.0] for x in np.linspace(-0.15, 0.0, 5) for y in ys])
    wall = np.array([[x, y, 15.0] for x in np.linspace(0.0, 0.45, 10) for y in ys])
    patches = [road, np.concatenate([pole, wall])]
    P = max(len(p) for p in patches)
    pts = np.zeros((2, P, 3))
    depth = np.full((2, P), np.nan)
    for i, p in enumerate(patches):
        pts[i, : len(p)] = p
        depth[i, : len(p)] = p[:, 2]
    labels = depth_clusters(depth, CFG.depth_jump_ratio, CFG.depth_jump_min_m)
    assert labels[0].max() == 2 and labels[1].max() == 1
    rays = np.array([[0.0, 0.085, 1.0], [0.0, 0.0, 1.0]])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    k = grow_foreground(pts, labels, rays, CFG.plane_max_rms_m, 0.05)
    assert k.tolist() == [2, 0]
    n, d, eig, _ = fit_planes(pts[:1], (labels[:1] >= 0).astype(float))
    assert abs(abs(n[0, 1]) - 1.0) < 1e-6 and abs(abs(d[0]) - 1.65) < 1e-6 and eig[0, 0] < 1e-12
