"""The ray caster of the depth-prior tests' analytic scenes (depth_scene.py) against distances worked by hand."""

from __future__ import annotations

import numpy as np
from depth_scene import K_KITTI, LIDAR_HEIGHT, TR_KITTI, Scene, box, lidar_scan, true_depth


def test_raycast_plane_and_box_distances():
    scene = Scene(boxes=[box(10.0, 11.0, -1.0, 1.0)])
    dirs = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, -0.1], [0.0, 1.0, 0.0]])
    t = scene.raycast(np.zeros(3), dirs)
    np.testing.assert_allclose(t[:3], [10.0, LIDAR_HEIGHT, 10.0], atol=1e-9)
    assert np.isinf(t[3])


def test_true_depth_matches_lidar_geometry():
    scene = Scene(boxes=[box(20.0, 21.0, -5.0, 5.0)], ground=False)
    # Camera at x = 0.27 m in lidar frame (Tr): the wall's x = 20 face is ~19.73 m in front of cam0.
    z = true_depth(scene, np.array([[K_KITTI[0, 2], K_KITTI[1, 2]]]))
    cam_x = np.linalg.inv(TR_KITTI)[0, 3]
    assert abs(z[0] - (20.0 - cam_x)) < 0.01
    scan = lidar_scan(scene, az_step_deg=1.0, fov_deg=5.0)
    assert np.allclose(scan[:, 0], 20.0, atol=1e-6)


