"""The tracker with the real feature, matching and depth stages: the 51 real KITTI seq-04 frames and a synthetic
town sequence, against ground truth (odometry alone, no back end)."""

from __future__ import annotations

import numpy as np
import pytest

from plvo.config import SystemConfig, TrackerSections
from plvo.data.kitti import KittiOdometry
from plvo.geometry import se3
from plvo.tracking.frontend import Frontend
from plvo_eval.kitti_metric import short_relative_error


def _run(ds, cfg=SystemConfig()):
    fe = Frontend(ds.calib, cfg.sections(TrackerSections), T_world_cam_init=ds.gt_T_world_cam[0])
    res = [fe.track(ds[i]) for i in range(len(ds))]
    return fe, res, np.array([r.T_world_cam for r in res])


def _final_drift(gt: np.ndarray, est: np.ndarray) -> tuple[float, float, float]:
    """Final position error (m), its share of the path length, final rotation error (deg)."""
    E = se3.inv(gt[-1]) @ est[-1]
    length = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    t = float(np.linalg.norm(E[:3, 3]))
    return t, t / length, float(np.degrees(se3.rotation_angle(E)))


@pytest.mark.kitti
@pytest.mark.slow
def test_kitti_04_short_relative_error(kitti_root):
    ds = KittiOdometry(kitti_root, "04")
    fe, res, est = _run(ds)
    assert all(r.status == "tracked" and r.ok for r in res[1:]), [r.message for r in res if not r.ok]
    rel = short_relative_error(ds.gt_T_world_cam, est)
    per = {e.length_m: e for e in rel.per_length}
    # Measured 1.09 / 0.90 / 0.78 % and 0.010 / 0.007 / 0.004 deg/m (points and lines with the line search by
    # projection, no back end; points only: 1.15 / 0.98 / 0.90 %).
    assert per[10.0].t_err_pct < 1.6 and per[20.0].t_err_pct < 1.4 and per[40.0].t_err_pct < 1.3, per
    assert per[10.0].r_err_deg_per_m < 0.03
    t, frac, r = _final_drift(ds.gt_T_world_cam, est)
    assert frac < 0.015 and r < 0.6, (t, frac, r)
    # Keyframes every 3 frames or earlier, with landmarks made from the depth priors, points and lines.
    kfs = [r.frame_index for r in res if r.is_keyframe]
    assert kfs[0] == 0 and max(np.diff(kfs)) <= 3
    assert fe.map.n_points > 2000 and fe.map.n_lines > 100
    assert np.mean([r.n_point_inliers for r in res[1:]]) > 40


@pytest.mark.slow
def test_synthetic_town_final_drift(synth_seq):
    ds = KittiOdometry(synth_seq, "00")
    fe, res, est = _run(ds)
    assert all(r.ok for r in res[1:]), [r.message for r in res if not r.ok]
    t, frac, r = _final_drift(ds.gt_T_world_cam, est)
    assert frac < 0.02 and r < 0.5, (t, frac, r)
