"""The map's drop of unreachable landmarks changes nothing a run computes: same trajectory, fewer rows."""

from __future__ import annotations

import numpy as np

from plvo.config import SystemConfig, merge
from plvo.data.kitti import KittiOdometry
from plvo.runtime.system import System


def _run(ds, cfg):
    system = System(cfg)
    try:
        for i in range(len(ds)):
            system.step(ds[i])
        system.finish()
        return system.poses_cam0(ds.frame_indices), system.map
    finally:
        system.close()


def test_dropping_unreachable_landmarks_leaves_the_trajectory_unchanged(synth_sequence_factory):
    ds = KittiOdometry(synth_sequence_factory(40, seed=3), "00")
    base = merge(SystemConfig(), {"loop": {"enabled": True}})
    kept_all, full_map = _run(ds, merge(base, {"tracking": {"drop_unreachable_every": 0}}))
    dropping, small_map = _run(ds, merge(base, {"tracking": {"drop_unreachable_every": 1}}))
    assert np.abs(dropping - kept_all).max() < 1e-9
    # a third of the landmarks or more had one view and left every window in 40 frames
    assert small_map.n_points < 0.75 * full_map.n_points, (small_map.n_points, full_map.n_points)
    assert small_map.global_data().landmark.tolist() == full_map.global_data().landmark.tolist()
