"""The local map of recent keyframe scans (plvo.lidar.local_map): a scan registered to it recovers a known motion
from a guess that is off (also from a few hundred source points), the map follows the poses it is given, keeps the
last keyframes only, and says when an alignment failed."""

from __future__ import annotations

import numpy as np
import pytest

from plvo.config import RegistrationConfig
from plvo.data.kitti import KittiOdometry
from plvo.errors import PlvoError
from plvo.geometry import se3
from plvo.lidar import local_map
from plvo.lidar.local_map import LocalMap
from plvo.lidar.registration import prepare


@pytest.fixture(scope="module")
def town(synth_sequence_factory):
    """A 40-frame town (scans taken at one instant, exact poses): lidar poses T_world_velo and prepared scans."""
    ds = KittiOdometry(synth_sequence_factory(40, seed=2), "00")
    T_cv = np.asarray(ds.calib.T_cam_velo)
    poses = ds.gt_T_world_cam @ T_cv
    cfg = RegistrationConfig()
    scans = [prepare(ds[i].scan, cfg) for i in range(0, 40, 3)]
    return poses[::3], scans, cfg


def _error(T, truth):
    E = se3.inv(truth) @ T
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(se3.rotation_angle(E)))


def test_registration_to_the_map_recovers_a_known_motion(town):
    poses, scans, cfg = town
    lmap = LocalMap(8, 0.5, cfg)
    for k in range(8):
        lmap.add(k, np.asarray(scans[k].fine.points), poses[k])
    truth = poses[8]
    for off in (np.array([0.4, -0.3, 0.05, 0.0, 0.0, np.radians(2.0)]),
                np.array([-0.6, 0.2, 0.0, np.radians(0.5), 0.0, np.radians(-1.5)])):
        guess = truth @ se3.exp(off)
        al = lmap.align(np.asarray(scans[8].cloud.points), guess)
        assert al.converged, al.why
        t_err, r_err = _error(al.T_world_lidar, truth)
        assert t_err < 0.03 and r_err < 0.05, f"{t_err:.3f} m, {r_err:.3f} deg from the truth"
        assert al.e_bar < al.e_hat and 0.0 < al.zeta <= 1.0 and al.fitness > 0.8
        info = al.information
        np.testing.assert_allclose(info, info.T, rtol=1e-9, atol=1e-9)
        assert np.linalg.eigvalsh(info).min() > 0  # a town's walls and ground fix all six directions


def test_the_map_follows_the_poses_it_is_given_and_keeps_the_last_keyframes(town):
    poses, scans, cfg = town
    lmap = LocalMap(3, 0.5, cfg)
    for k in range(5):
        lmap.add(k, np.asarray(scans[k].fine.points), poses[k])
    assert lmap.kf_ids == [2, 3, 4]
    moved = se3.exp(np.array([1.0, 2.0, 0.0, 0.0, 0.0, 0.1]))
    before = lmap.cloud().get_axis_aligned_bounding_box().get_center()
    lmap.place(np.array([3]), moved @ poses[3][None])  # keyframe 3 given a new pose: 2 follows it, 4 is put there
    placed = lmap.poses()
    np.testing.assert_allclose(placed[3], moved @ poses[3], atol=1e-12)
    np.testing.assert_allclose(placed[2], moved @ poses[2], atol=1e-9)  # rigidly with the oldest given
    np.testing.assert_allclose(placed[4], moved @ poses[4], atol=1e-9)
    after = lmap.cloud().get_axis_aligned_bounding_box().get_center()
    assert np.linalg.norm(after - before) > 1.0
    lmap.place(np.array([99]), np.eye(4)[None])  # none of its keyframes: unchanged
    np.testing.assert_allclose(lmap.poses()[3], placed[3])
    with pytest.raises(PlvoError, match="added after"):
        lmap.add(4, np.asarray(scans[4].fine.points), poses[4])


def test_a_scan_is_downsampled_when_a_map_first_needs_it_to_the_same_points(town):
    """A keyframe's scan is downsampled (and its normals estimated) on the map's first build after it was added,
    or ahead of it when asked (`prepare`, which the back end's worker process calls between jobs), not when it is
    added. Downsampled ahead or at the build, the map is the same to the last bit."""
    poses, scans, cfg = town
    lazy, eager = LocalMap(4, 0.5, cfg), LocalMap(4, 0.5, cfg)
    for k in range(6):
        for lmap in (lazy, eager):
            lmap.add(k, np.asarray(scans[k].fine.points), poses[k])
        eager.prepare()
        assert eager._entries[-1].points is not None and eager._entries[-1].scan is None
        assert lazy._entries[-1].points is None and lazy._entries[-1].scan is not None  # nothing made yet
        if k in (2, 5):
            a, b = lazy.cloud(), eager.cloud()
            np.testing.assert_array_equal(np.asarray(a.points), np.asarray(b.points))
            np.testing.assert_array_equal(np.asarray(a.normals), np.asarray(b.normals))
            assert all(e.points is not None and e.scan is None for e in lazy._entries)
    assert len(np.asarray(lazy.cloud().points)) > 1000


def test_an_alignment_that_cannot_hold_says_why(town):
    poses, scans, cfg = town
    with pytest.raises(PlvoError, match="no keyframe scans"):
        LocalMap(3, 0.5, cfg).align(np.asarray(scans[0].cloud.points), poses[0])
    lmap = LocalMap(3, 0.5, cfg)
    lmap.add(0, np.asarray(scans[0].fine.points), poses[0])
    far = poses[0] @ se3.exp(np.array([0.0, 0.0, 500.0, 0.0, 0.0, 0.0]))  # nothing of the map near it
    al = lmap.align(np.asarray(scans[1].cloud.points), far)
    assert not al.converged and al.why and al.zeta == 0.0
    np.testing.assert_array_equal(al.T_world_lidar, far)
    with pytest.raises(PlvoError, match="finite"):
        lmap.align(np.asarray(scans[1].cloud.points), np.full((4, 4), np.nan))


def test_a_guess_the_registration_has_to_move_far_is_checked_against_the_prediction(town, monkeypatch):
    poses, scans, cfg = town
    lmap = LocalMap(8, 0.5, cfg)
    for k in range(8):
        lmap.add(k, np.asarray(scans[k].fine.points), poses[k])
    truth, src = poses[8], np.asarray(scans[8].cloud.points)
    starts: list[np.ndarray] = []
    align = LocalMap.align
    monkeypatch.setattr(LocalMap, "align", lambda self, s, g: starts.append(g) or align(self, s, g))
    prediction = truth @ se3.exp(np.array([0.1, 0.0, 0.05, 0.0, 0.0, np.radians(0.3)]))
    # a good guess: its alignment moves it 0.05 deg, the prediction is not tried
    al = lmap.align_best(src, [truth @ se3.exp(np.array([0.05, 0.0, 0.0, 0.0, 0.0, np.radians(0.05)])), prediction])
    assert len(starts) == 1 and al.converged and _error(al.T_world_lidar, truth)[1] < 0.05
    # a guess turned 40 deg (the tracker fooled): it cannot be aligned from there; from the prediction it can
    wrong = truth @ se3.exp(np.array([0.0, 0.0, 0.0, 0.0, 0.0, np.radians(40.0)]))
    alone = align(lmap, src, wrong)
    assert not alone.converged or _error(alone.T_world_lidar, truth)[1] > 1.0
    starts.clear()
    al = lmap.align_best(src, [wrong, prediction])
    assert len(starts) == 2 and al.converged
    t_err, r_err = _error(al.T_world_lidar, truth)
    assert t_err < 0.03 and r_err < 0.05, (t_err, r_err)


def test_an_alignment_uses_at_most_max_source_points_and_still_recovers_the_motion(town, monkeypatch):
    poses, scans, cfg = town
    lmap = LocalMap(8, 0.5, cfg, max_source_points=300)
    for k in range(8):
        lmap.add(k, np.asarray(scans[k].fine.points), poses[k])
    used = []
    icp = local_map._icp
    monkeypatch.setattr(local_map, "_icp", lambda src, *rest: (used.append(len(src)), icp(src, *rest))[1])
    source = np.asarray(scans[8].cloud.points)
    assert len(source) > 300
    truth = poses[8]
    al = lmap.align(source, truth @ se3.exp(np.array([0.4, -0.3, 0.05, 0.0, 0.0, np.radians(2.0)])))
    assert used == [300]
    assert al.converged, al.why
    t_err, r_err = _error(al.T_world_lidar, truth)
    assert t_err < 0.05 and r_err < 0.1, f"{t_err:.3f} m, {r_err:.3f} deg from the truth with 300 source points"
    with pytest.raises(PlvoError, match="max_source_points"):
        LocalMap(8, 0.5, cfg, max_source_points=5)
