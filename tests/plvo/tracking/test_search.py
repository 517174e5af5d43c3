"""Line landmarks re-found by projection (plvo.tracking.search): geometry of the candidates, LBD, one-to-one."""

from __future__ import annotations

import numpy as np

from plvo.geometry import se3
from plvo.tracking.search import project_segments, search_lines_by_projection

K = np.array([[700.0, 0.0, 600.0], [0.0, 700.0, 180.0], [0.0, 0.0, 1.0]])


def _desc(rng, n):
    return rng.integers(0, 256, (n, 32), dtype=np.uint8)


def test_project_segments_clips_behind_the_camera_and_drops_invisible():
    ends = np.array([
        [[-1.0, 0.0, 10.0], [1.0, 0.0, 10.0]],  # in front: 140 px long, centred
        [[2.0, 1.0, -5.0], [2.0, 1.0, 5.0]],  # crosses the camera plane: clipped at 0.5 m
        [[0.0, 0.0, -5.0], [1.0, 0.0, -6.0]],  # behind
        [[500.0, 0.0, 10.0], [501.0, 0.0, 10.0]],  # far outside the image
    ])
    seg = project_segments(K, np.eye(4), ends, 1200, 370)
    np.testing.assert_allclose(seg[0], [530.0, 180.0, 670.0, 180.0])
    # clipped to z = 0.5 m: from (2, 1, 0.5) to (2, 1, 5)
    np.testing.assert_allclose(seg[1], [600.0 + 700.0 * 2 / 0.5, 180.0 + 700.0 / 0.5, 880.0, 320.0])
    assert np.isnan(seg[2]).all() and np.isnan(seg[3]).all()
    # A camera moved 1 m to the right sees the first segment shifted left by 70 px.
    T = se3.from_rt(np.eye(3), [1.0, 0.0, 0.0])
    np.testing.assert_allclose(project_segments(K, T, ends[:1], 1200, 370)[0], [460.0, 180.0, 600.0, 180.0])


def test_partial_detections_on_the_projected_line_are_found_and_others_rejected():
    rng = np.random.default_rng(0)
    proj = np.array([[100.0, 100.0, 300.0, 100.0], [500.0, 50.0, 500.0, 250.0], [800.0, 100.0, 900.0, 150.0]])
    lm_desc = _desc(rng, 3)
    segs = np.array([
        [150.0, 101.5, 380.0, 102.0],  # landmark 0: other extent (midpoint 65 px away), 2 px off the line
        [500.5, 200.0, 499.5, 330.0],  # landmark 1: a different part of the edge, half overlapping
        [820.0, 110.0, 880.0, 140.0],  # on landmark 2's line, but its descriptor is far
        [160.0, 106.0, 260.0, 106.0],  # parallel to landmark 0, 6 px away: not on the line
        [300.0, 100.0, 100.0, 100.0],  # landmark 0 with the opposite direction (other gradient polarity)
    ])
    desc = _desc(rng, 5)
    desc[0] = lm_desc[0]
    desc[1] = lm_desc[1]
    desc[1, :2] ^= 0xFF  # 16 bits apart: still the best
    desc[3] = lm_desc[0]
    desc[4] = lm_desc[0]
    rows, cols = search_lines_by_projection(proj, lm_desc, segs, desc, np.ones(5, bool), max_dist_px=4.0,
                                            max_angle_deg=3.0, min_overlap=0.3, max_lbd=80)
    assert dict(zip(rows.tolist(), cols.tolist())) == {0: 0, 1: 1}
    # A taken segment is not offered again, and a NaN projection matches nothing.
    free = np.array([False, True, True, True, True])
    proj_nan = proj.copy()
    proj_nan[1] = np.nan
    rows, cols = search_lines_by_projection(proj_nan, lm_desc, segs, desc, free, 4.0, 3.0, 0.3, 80)
    assert len(rows) == 0


def test_one_to_one_goes_to_the_smaller_lbd_distance():
    rng = np.random.default_rng(1)
    proj = np.array([[100.0, 100.0, 300.0, 100.0], [100.0, 101.0, 300.0, 101.0]])  # two landmarks on one edge
    lm_desc = _desc(rng, 2)
    segs = np.array([[120.0, 100.5, 280.0, 100.5]])
    desc = lm_desc[1:2].copy()
    desc[0, 0] ^= 0x01
    rows, cols = search_lines_by_projection(proj, lm_desc, segs, desc, np.ones(1, bool), 4.0, 3.0, 0.3, 80)
    assert rows.tolist() == [1] and cols.tolist() == [0]
