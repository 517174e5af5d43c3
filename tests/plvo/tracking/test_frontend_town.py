"""The tracker with the real feature, matching and depth stages on synthetic town sequences (exact ground truth):
final drift, a stop, and a forced tracking loss followed by recovery. Odometry alone (no back end)."""

from __future__ import annotations

import dataclasses
import json
import logging

import numpy as np
import pytest

from plvo.config import SystemConfig, TrackerSections
from plvo.data.kitti import KittiOdometry
from plvo.geometry import se3
from plvo.tracking.frontend import Frontend

CFG = SystemConfig()


def _track(ds, cfg=CFG, image_override=None):
    """Run the tracker over ds; image_override: {frame: (H,W) uint8} replaces those frames' images."""
    fe = Frontend(ds.calib, cfg.sections(TrackerSections), T_world_cam_init=ds.gt_T_world_cam[0])
    res = []
    for i in range(len(ds)):
        frame = ds[i]
        if image_override and i in image_override:
            frame = dataclasses.replace(frame, image=image_override[i])
        res.append(fe.track(frame))
    return fe, res, np.array([r.T_world_cam for r in res])


def _final_drift(gt: np.ndarray, est: np.ndarray) -> tuple[float, float]:
    """Final position error as a share of the path length, final rotation error (deg)."""
    E = se3.inv(gt[-1]) @ est[-1]
    length = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    return float(np.linalg.norm(E[:3, 3])) / length, float(np.degrees(se3.rotation_angle(E)))


@pytest.fixture(scope="module")
def town(synth_seq):
    ds = KittiOdometry(synth_seq, "00")
    return ds, _track(ds)


def test_synthetic_town_points_and_lines_low_drift(town):
    ds, (fe, res, est) = town
    assert all(r.ok and r.status == "tracked" for r in res[1:]), [r.message for r in res if not r.ok]
    frac, rot = _final_drift(ds.gt_T_world_cam, est)
    # Measured 0.40 % and 0.10 deg over the 19 m; 1 % / 0.3 deg leave room for the stages' changes.
    assert frac < 0.01 and rot < 0.3, (frac, rot)
    # Lines take part (measured 20.6 line inliers a frame; without the line search by projection 14 on a 560 m town
    # run).
    n_line = np.array([r.n_line_inliers for r in res[1:]])
    assert n_line.mean() > 15, n_line
    assert np.mean([r.n_point_inliers for r in res[1:]]) > 60
    kfs = [r.frame_index for r in res if r.is_keyframe]
    assert kfs[0] == 0 and max(np.diff(kfs)) <= CFG.tracking.keyframe_max_gap


def test_stopped_car_does_not_drift(synth_sequence_factory):
    # 3 m/s with a stop: braking, 20 frames standing exactly still, starting again.
    root = synth_sequence_factory(48, seed=1, speed_mps=3.0, stops=True)
    still = json.loads((root / "sequences" / "00" / "gt" / "scene.json").read_text())["frames"]["still_frames"]
    assert len(still) >= 15
    ds = KittiOdometry(root, "00")
    _, res, est = _track(ds)
    assert all(r.ok for r in res[1:]), [r.message for r in res if not r.ok]
    first, last = still[0] - 1, still[-1]  # frame still[0] - 1 is where the car came to rest
    moved = np.linalg.norm(est[first:last + 1, :3, 3] - est[first, :3, 3], axis=1).max()
    turned = max(np.degrees(se3.rotation_angle(se3.inv(est[first]) @ T)) for T in est[first:last + 1])
    # Standing still for ~20 frames: measured 0.8 cm and 0.02 deg in total (from the frame before the stop).
    assert moved < 0.02 and turned < 0.1, (moved, turned)
    frac, rot = _final_drift(ds.gt_T_world_cam, est)
    assert frac < 0.02 and rot < 0.3, (frac, rot)


@pytest.mark.parametrize("check", [True, False])
def test_blank_frame_loses_tracking_then_recovers(synth_seq, caplog, check):
    """A black image: with the lidar check (the default) the lidar gives the frame's pose; without it, the motion
    model's guess. Either way landmarks are made anew from the lidar depth and tracking goes on."""
    ds = KittiOdometry(synth_seq, "00")
    lost_at = 10
    blank = np.zeros_like(ds[lost_at].image)
    cfg = CFG if check else dataclasses.replace(CFG, crosscheck=dataclasses.replace(CFG.crosscheck, enabled=False))
    with caplog.at_level(logging.INFO, logger="plvo.tracking.frontend"):
        fe, res, est = _track(ds, cfg, image_override={lost_at: blank})
    lost = res[lost_at]
    assert lost.is_keyframe and "re-initialised from the" in lost.message
    if check:
        assert lost.ok and lost.status == "overruled" and lost.source == "lidar", lost.message
        expected = f"frame {lost_at}: camera overruled by the lidar; tracking lost"
    else:
        assert not lost.ok and lost.status == "reinitialised" and lost.source == "motion model"
        assert "tracking lost" in lost.message and "re-initialised from the current lidar depth" in lost.message
        expected = f"frame {lost_at}: tracking lost"
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and warned[0].startswith(expected), warned
    # The frames before are untouched; the lost frame took the lidar's motion or the constant-velocity prediction
    # (10 m/s, 1 m a frame)
    assert all(r.ok for r in res[1:lost_at])
    gt = ds.gt_T_world_cam
    assert np.linalg.norm(est[lost_at, :3, 3] - gt[lost_at, :3, 3]) < 0.1
    # Recovery: the next frames track again (from the re-initialised and the older keyframes' landmarks).
    after = res[lost_at + 1:]
    assert all(r.ok and r.status == "tracked" for r in after), [r.message for r in after if not r.ok]
    assert all(r.n_point_inliers > 30 for r in after)
    frac, rot = _final_drift(gt, est)
    assert frac < 0.02 and rot < 0.5, (frac, rot)
