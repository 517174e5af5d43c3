"""plvo.tracking.correspondences: the tracker's 3D-2D matches as one typed record; landmarks found by projection
are added after those matched frame to frame, row for row in every array."""

from __future__ import annotations

import numpy as np

from plvo.tracking.correspondences import Correspondences


def _empty_lines():
    return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2, 3)), np.zeros((0, 4))


def test_found_correspondences_follow_the_matched_ones_row_for_row():
    c = Correspondences(np.array([7]), np.array([3]), np.array([[1.0, 2.0, 3.0]]), np.array([[10.0, 20.0]]),
                        *_empty_lines())
    c2 = c.with_points(np.array([9, 4]), np.array([5, 0]), np.array([[4.0, 5, 6], [7, 8, 9]]),
                       np.array([[30.0, 40], [50, 60]]))
    c3 = c2.with_lines(np.array([2]), np.array([1]), np.ones((1, 2, 3)), np.array([[0.0, 0, 5, 5]]))
    assert (c.n_points, c.n_lines) == (1, 0)  # the record it was made from is unchanged
    assert (c3.n_points, c3.n_lines) == (3, 1)
    np.testing.assert_array_equal(c3.point_landmarks, [7, 9, 4])
    np.testing.assert_array_equal(c3.point_features, [3, 5, 0])
    np.testing.assert_array_equal(c3.point_positions[2], [7, 8, 9])
    pts, uv, ends, segs = c3.solver_inputs()
    assert pts.shape == (3, 3) and uv.shape == (3, 2) and ends.shape == (1, 2, 3) and segs.shape == (1, 4)
