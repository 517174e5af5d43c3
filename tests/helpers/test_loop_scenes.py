"""The loop-closure tests' planar scene (loop_scenes.py): a view moved over the plane moves pixels by its homography."""

from __future__ import annotations

import numpy as np
from loop_scenes import K, backproject, plane_homography


def test_planar_view_moves_pixels_by_the_plane_homography():
    from plvo.geometry import se3

    T_b_a = se3.exp(np.array([0.5, 0.0, 0.3, 0.0, 0.02, 0.0]))
    X_a = backproject(K, np.array([[600.0, 180.0], [100.0, 50.0]]), np.full(2, 10.0))
    X_b = se3.transform_points(T_b_a, X_a)
    uv_b = (X_b[:, :2] / X_b[:, 2:3]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    h = plane_homography(T_b_a, 10.0) @ np.array([[600.0, 180.0, 1.0], [100.0, 50.0, 1.0]]).T
    np.testing.assert_allclose((h[:2] / h[2]).T, uv_b, atol=1e-6)
