"""Line depth priors: endpoint accuracy on box edges, silhouettes, the batched LM and trimming."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from depth_scene import (
    K_KITTI,
    box_edges,
    kitti_calib,
    lidar_scan,
    ray_line_points,
    street_scene,
    visible_segments,
)

from plvo.config import DepthConfig
from plvo.depth.lines import _lm, _plucker, _trim, line_depths
from plvo.depth.projection import project_scan
from plvo.geometry.lines import point_line_distance, trim_endpoints
from plvo.types import DEPTH_OK, DEPTH_TOO_FEW_POINTS

CFG = DepthConfig()


@pytest.fixture(scope="module")
def street_lines():
    scene = street_scene()
    proj = project_scan(lidar_scan(scene, noise_m=0.02), kitti_calib())
    edges = np.concatenate([box_edges(lo, hi) for lo, hi in scene.boxes])
    segs, lines3d = visible_segments(scene, edges)
    res = line_depths(proj, segs, K_KITTI, CFG)
    return segs, lines3d, ray_line_points(segs, lines3d), res, proj


def test_box_edges_endpoint_error(street_lines):
    segs, lines3d, truth, res, _ = street_lines
    ok = res.reason == DEPTH_OK
    assert len(segs) >= 20 and ok.sum() >= 14, (len(segs), ok.sum())
    err = np.linalg.norm(res.endpoints - truth, axis=2)[ok]
    rel = err / truth[ok][..., 2]
    # 2 cm lidar noise; edges at 4-45 m: corners, silhouettes and a wall's foot on the road.
    assert np.median(err) <= 0.06 and np.percentile(err, 90) <= 0.2, (np.median(err), np.percentile(err, 90))
    assert np.max(rel) <= 0.02, np.max(rel)
    assert np.all(res.residual[ok] <= CFG.line_max_rms_m) and np.all(res.reproj_px[ok] <= 1.0)
    # The fitted 3D line lies on the true edge, within a few cm over the whole segment.
    for i in np.flatnonzero(ok):
        a, b = lines3d[i]
        d = point_line_distance(np.stack([a, b]), res.plucker[i])
        assert np.all(d <= 0.03 * np.linalg.norm(a)), (i, d)


def test_edges_without_lidar_coverage_get_no_prior(street_lines):
    segs, _, truth, res, _ = street_lines
    # Top edges of the walls and blocks are above the lidar's +2 deg upper beam.
    high = np.all(segs[:, [1, 3]] < 80.0, axis=1)
    assert high.sum() >= 4
    assert np.all(res.reason[high] == DEPTH_TOO_FEW_POINTS)
    assert np.all(np.isnan(res.endpoints[high]))


def test_lm_recovers_an_exact_line_from_a_perturbed_start():
    rng = np.random.default_rng(7)
    M, P = 30, 40
    a = rng.uniform([-5, -2, 6], [5, 2, 30], (M, 3))
    b = a + rng.normal(0, 2.0, (M, 3))
    s = rng.uniform(0, 1, (M, P, 1))
    pts = a[:, None] + s * (b - a)[:, None] + rng.normal(0, 1e-4, (M, P, 3))
    uv = lambda p: p[..., :2] / p[..., 2:] * K_KITTI[0, 0] + K_KITTI[:2, 2]  # noqa: E731
    seg = np.concatenate([uv(a), uv(b)], axis=1)
    L_true = _plucker(a, b)
    L0 = _plucker(a * 1.05 + 0.05, b * 0.97 - 0.05)  # 5 % off in depth (0.3-1.5 m) and 5 cm aside
    L, iters, conv = _lm(L0, pts, np.ones((M, P), bool), K_KITTI, seg, dataclasses.replace(CFG, line_lm_iterations=30))
    assert conv.all() and np.median(iters) <= 6, np.bincount(iters)
    for i in range(M):
        d = point_line_distance(np.stack([a[i], b[i]]), L[i])
        assert np.all(d < 5e-3), (i, d)  # sub-centimetre: far below the 2 cm range noise of a real scan
        assert np.all(point_line_distance(pts[i], L_true[i]) < 1e-3)


def test_batched_trimming_matches_geometry_module(street_lines):
    segs, _, _, res, _ = street_lines
    ok = np.flatnonzero(res.reason == DEPTH_OK)
    rays = np.stack(
        [(segs[:, [0, 2]] - K_KITTI[0, 2]) / K_KITTI[0, 0], (segs[:, [1, 3]] - K_KITTI[1, 2]) / K_KITTI[1, 1],
         np.ones((len(segs), 2))], axis=-1)
    ends, _ = _trim(res.plucker[ok], rays[ok])
    for j, i in enumerate(ok):
        np.testing.assert_allclose(ends[j], trim_endpoints(K_KITTI, res.plucker[i], segs[i]), atol=1e-9)
        np.testing.assert_allclose(ends[j], res.endpoints[i], atol=1e-9)


def test_empty_inputs():
    proj = project_scan(np.zeros((0, 4), np.float32), kitti_calib())
    res = line_depths(proj, np.array([[100.0, 200.0, 300.0, 210.0]]), K_KITTI, CFG)
    assert res.reason.tolist() == [DEPTH_TOO_FEW_POINTS] and np.isnan(res.endpoints).all()
    res = line_depths(proj, np.zeros((0, 4)), K_KITTI, CFG)
    assert res.endpoints.shape == (0, 2, 3)
