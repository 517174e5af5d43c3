"""LandmarkMap storage, observations, back-end updates; KeyframePolicy; two-view triangulation."""

from __future__ import annotations

import numpy as np
import pytest

from plvo.config import TrackingConfig
from plvo.geometry import se3
from plvo.results import KeyframeReason, KeyframeWhy
from plvo.tracking.association import FrameAssociation
from plvo.tracking.keyframes import KeyframePolicy, triangulate_tracks
from plvo.tracking.map import LandmarkMap

K = np.array([[718.856, 0.0, 607.19], [0.0, 718.856, 185.2], [0.0, 0.0, 1.0]])


def _desc(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, 32), dtype=np.uint8)


def _map_with_landmarks(n_pts=40, n_lines=10):
    m = LandmarkMap()
    kf = m.add_keyframe(7, np.eye(4))
    pos = np.random.default_rng(1).normal(size=(n_pts, 3))
    pids = m.add_points(pos, _desc(n_pts), np.ones(n_pts, bool), kf, np.arange(n_pts), np.zeros((n_pts, 2)))
    ends = np.random.default_rng(2).normal(size=(n_lines, 2, 3))
    lids = m.add_lines(ends, _desc(n_lines, 3), np.zeros(n_lines, bool), kf, np.arange(n_lines),
                       np.zeros((n_lines, 4)))
    return m, kf, pos, pids, ends, lids


def test_add_grow_read_and_remove():
    m, kf, pos, pids, ends, lids = _map_with_landmarks(40, 10)
    assert np.array_equal(pids, np.arange(40)) and np.array_equal(lids, np.arange(10))
    # Growing past the initial capacity (16) kept the earlier rows.
    more = m.add_points(np.ones((100, 3)), _desc(100), np.zeros(100, bool), kf, np.arange(100), np.zeros((100, 2)))
    assert np.array_equal(more, np.arange(40, 140))
    assert np.allclose(m.point_positions(pids), pos) and np.allclose(m.line_endpoints(lids), ends)
    assert m.n_points == 140 and m.n_lines == 10 and m.keyframe_frame(kf) == 7
    m.remove_points(pids[:5])
    m.remove_lines(lids[-1:])
    assert np.isnan(m.point_positions(pids[:5])).all() and np.isfinite(m.point_positions(pids[5:])).all()
    assert not m.point_alive(pids[:5]).any() and m.n_points == 135 and m.n_lines == 9
    snap = m.snapshot()
    assert len(snap.point_ids) == 135 and 0 not in snap.point_ids and snap.line_endpoints.shape == (9, 2, 3)
    assert snap.keyframe_T_world_cam.shape == (1, 4, 4)


def test_observations_and_removed_landmarks_drop_out():
    m, kf, pos, pids, ends, lids = _map_with_landmarks(20, 5)
    kf2 = m.add_keyframe(10, se3.exp(np.array([0, 0, 1.0, 0, 0, 0])))
    m.add_point_observations(pids[:3], kf2, np.array([5, 6, 7]), np.array([[1.0, 2], [3, 4], [5, 6]]))
    m.add_line_observations(lids[:2], kf2, np.array([0, 1]), np.ones((2, 4)))
    obs = m.point_observations(pids[:3])
    assert len(obs.landmark) == 6 and set(obs.keyframe) == {kf, kf2}
    assert np.allclose(obs.measurement[obs.keyframe == kf2], [[1, 2], [3, 4], [5, 6]])
    m.remove_points(pids[:1])
    assert len(m.point_observations().landmark) == 19 + 2
    assert len(m.line_observations().landmark) == 5 + 2


def test_apply_update_moves_landmarks_and_poses_together():
    m, kf, pos, pids, ends, lids = _map_with_landmarks(200, 50)
    v0 = m.version
    T = se3.exp(np.array([0, 0, 299.0, 0, 0, 0]))
    m.apply_update(pids, np.full((200, 3), 299.0), lids, np.full((50, 2, 3), 299.0), [kf], T[None])
    s = m.snapshot()
    assert s.version > v0
    assert np.all(s.point_positions == 299.0) and np.all(s.line_endpoints == 299.0)
    assert s.keyframe_T_world_cam[0, 2, 3] == pytest.approx(299.0)
    assert np.allclose(m.point_positions(pids), 299.0) and m.keyframe_pose(kf)[2, 3] == pytest.approx(299.0)


def test_apply_update_skips_removed_landmarks():
    m, kf, pos, pids, ends, lids = _map_with_landmarks(10, 4)
    m.remove_points(pids[:2])
    m.apply_update(point_ids=pids, point_positions=np.zeros((10, 3)))
    assert np.isnan(m.point_positions(pids[:2])).all() and np.allclose(m.point_positions(pids[2:]), 0)


def _drive(m: LandmarkMap, n_kf: int, per_kf: int = 100, seen_again: int = 20, drop_every: int = 0,
           reach: int = 8, first_kf: int = 0, lines_per_kf: int = 0):
    """Keyframes first_kf.. each making per_kf points and lines_per_kf lines; the first seen_again points and
    every line of each are observed again by the next keyframe (so they have two views, the other points one).
    Drops every drop_every keyframes (0: never). Returns the point ids made by each keyframe."""
    rng = np.random.default_rng(first_kf)
    made, lines = [], []
    for k in range(first_kf, first_kf + n_kf):
        kf = m.add_keyframe(3 * k, _T(z=float(k)))
        if made:
            m.add_point_observations(made[-1][:seen_again], kf, np.arange(seen_again), np.zeros((seen_again, 2)))
            m.add_line_observations(lines[-1], kf, np.arange(len(lines[-1])), np.zeros((len(lines[-1]), 4)))
            m.mark_seen(made[-1][:seen_again], lines[-1], 3 * k)
        ids = m.add_points(rng.normal(size=(per_kf, 3)) + [0, 0, k], _desc(per_kf, k), np.ones(per_kf, bool), kf,
                           np.arange(per_kf), rng.uniform(0, 500, (per_kf, 2)), rng.uniform(5, 40, per_kf))
        made.append(ids)
        lines.append(m.add_lines(rng.normal(size=(lines_per_kf, 2, 3)), _desc(lines_per_kf, k),
                                 np.ones(lines_per_kf, bool), kf, np.arange(lines_per_kf),
                                 rng.uniform(0, 500, (lines_per_kf, 4))))
        if drop_every and kf % drop_every == 0:
            m.drop_unreachable(3 * k, kf - reach)
    return made


def test_drop_unreachable_keeps_every_read_that_matters():
    """Dropping single-view landmarks out of reach changes none of what the back end, the global BA and the
    tracker read, keeps ids valid (dropped ones read as gone), and continues ids after the dropped ones."""
    m = LandmarkMap()
    made = _drive(m, 30, lines_per_kf=5)
    window = np.arange(22, 30)
    before = (m.window_data(window), m.global_data(), m.point_positions(made[-1]))
    dropped = m.drop_unreachable(frame_index=3 * 29, oldest_reachable_kf=22)
    # keyframes 0..21 made 100 points each; 20 of each but the last (21's are seen by 22) have two views. Lines
    # are in no global BA: those last seen before keyframe 22 go whatever their views (keyframe 21's are seen by 22)
    assert dropped == (22 * 80, 21 * 5)
    assert m.n_lines == 9 * 5 and len(m.line_observations().landmark) == 9 * 5 + 8 * 5
    assert m.n_points == 30 * 100 - 22 * 80
    after = (m.window_data(window), m.global_data(), m.point_positions(made[-1]))
    for a, b in zip(before[:2], after[:2]):
        for name in vars(a):
            x, y = getattr(a, name), getattr(b, name)
            if name == "version":
                continue
            if isinstance(x, np.ndarray):
                assert np.array_equal(x, y, equal_nan=True), name
            else:
                assert x == y, name
    assert np.array_equal(before[2], after[2])
    gone = made[3][20:]
    assert not m.point_alive(gone).any() and np.isnan(m.point_positions(gone)).all()
    assert m.point_alive(made[3][:20]).all() and np.isfinite(m.point_positions(made[3][:20])).all()
    assert len(m.point_observations(gone).landmark) == 0
    assert len(m.point_observations(made[3][:20]).landmark) == 40
    # a correction naming dropped landmarks moves the others and skips them
    m.apply_update(point_ids=np.r_[gone[:5], made[3][:5]], point_positions=np.zeros((10, 3)))
    assert np.allclose(m.point_positions(made[3][:5]), 0) and not m.point_alive(gone[:5]).any()
    # observations of a dropped landmark are refused; new ids continue after every id ever handed out
    m.add_point_observations(gone[:3], 29, np.arange(3), np.zeros((3, 2)))
    assert len(m.point_observations(gone).landmark) == 0
    new = m.add_points(np.zeros((2, 3)), _desc(2), np.ones(2, bool), 29, np.arange(2), np.zeros((2, 2)))
    assert new.tolist() == [3000, 3001]


def test_drop_with_a_global_ba_budget_keeps_what_the_adjustment_picks():
    """With a point budget, out-of-reach points ranked above today's share go: the global BA's pick is the same
    before and after, now and after more keyframes."""
    from plvo.loop.global_ba import point_budget

    def picked(m):
        d = m.global_data()
        return set(point_budget(d.landmark, d.keyframe, 100).tolist())

    full, trimmed = LandmarkMap(), LandmarkMap()
    for m in (full, trimmed):
        rng = np.random.default_rng(5)
        made = _drive(m, 30)
        # more views for some, so that ranks are not by id alone
        for k in range(1, 25):
            extra = made[k - 1][rng.choice(20, 5, replace=False)]
            m.add_point_observations(extra, k, np.arange(5), np.zeros((5, 2)))
    before = picked(trimmed)
    trimmed.drop_unreachable(3 * 29, oldest_reachable_kf=22, global_ba_points=100)
    assert picked(trimmed) == before == picked(full)
    # every out-of-reach keyframe keeps only a few of its 20 two-view points
    kept = trimmed.point_ids_and_first_keyframes()[1]
    assert np.bincount(kept[kept < 21]).max() <= 5 and trimmed.n_points < full.n_points - 21 * 80 - 21 * 14
    for m in (full, trimmed):
        _drive(m, 10, first_kf=30)
    assert picked(trimmed) == picked(full)
    # no global BA: every point out of reach goes
    trimmed.drop_unreachable(3 * 39, oldest_reachable_kf=32, global_ba_points=None)
    assert (trimmed.point_ids_and_first_keyframes()[1] >= 31).all()


def test_drop_unreachable_keeps_what_is_tracked_and_what_is_in_reach():
    m = LandmarkMap()
    made = _drive(m, 12)
    m.mark_seen(made[0][50:60], [], 3 * 11)  # still tracked by the frame-to-frame matching
    m.drop_unreachable(3 * 11, oldest_reachable_kf=4)
    assert m.point_alive(made[0][50:60]).all() and not m.point_alive(made[0][60:]).any()
    assert m.point_alive(np.concatenate(made[4:])).all()


def test_map_memory_follows_what_is_kept_not_the_run_length():
    """1000 keyframes of 300 points, 20 of each seen twice: with the drop, rows and bytes are those of the
    multi-view landmarks plus the reachable keyframes' points; without, every landmark ever made."""
    kept, full = LandmarkMap(), LandmarkMap()
    _drive(kept, 500, per_kf=300, drop_every=10)
    mid = kept.nbytes()
    _drive(kept, 500, per_kf=300, drop_every=10, first_kf=500)
    _drive(full, 1000, per_kf=300)
    rows = kept._pts.n
    assert rows <= 1000 * 20 + (8 + 10) * 300  # multi-view ones, and the keyframes within reach or since a drop
    assert full._pts.n == 300_000 and full.n_points == 300_000
    assert kept.nbytes() < 0.2 * full.nbytes()
    # what is kept per keyframe is the multi-view landmarks and their observations: ~ (20 x 100 B + 40 x 60 B)
    per_kf = (kept.nbytes() - mid) / 500
    assert per_kf < 2 * (20 * 100 + 40 * 60), per_kf


def test_frame_association_counts():
    a = FrameAssociation.empty(5, 3)
    a.point_landmark[[1, 3]] = [10, 11]
    assert a.n_points == 2 and a.n_lines == 0


def _T(z=0.0, yaw_deg=0.0):
    return se3.exp(np.array([0, 0, z, 0, np.radians(yaw_deg), 0]))


def test_keyframe_policy_interval_and_early_reasons():
    cfg = TrackingConfig(keyframe_every=3, min_tracked_landmarks=60, max_rotation_deg=10.0)
    p = KeyframePolicy(cfg)
    d = p.decide(0, _T(), 0)
    assert d.is_keyframe and d.reason == KeyframeWhy(KeyframeReason.FIRST) and str(d.reason) == "first frame"
    p.accept(0, _T())
    made = []
    for i in range(1, 10):
        d = p.decide(i, _T(i), 200)
        if d.is_keyframe:
            made.append(i)
            p.accept(i, _T(i))
    assert made == [3, 6, 9]
    d = p.decide(10, _T(10), 59)
    assert d.reason == KeyframeWhy(KeyframeReason.FEW_TRACKED, "59 < 60")
    assert str(d.reason) == "few tracked landmarks (59 < 60)"  # the sentence the logs and the viewers show
    d = p.decide(10, _T(10, yaw_deg=11.0), 200)
    assert d.reason is not None and d.reason.kind is KeyframeReason.ROTATION and d.rotation_deg == pytest.approx(11.0)
    assert str(d.reason) == "large rotation (11.0 > 10.0 deg)"
    assert p.decide(10, _T(10, yaw_deg=9.0), 200).reason is None
    assert p.decide(10, _T(10), 200, lost=True).reason == KeyframeWhy(KeyframeReason.LOST)
    assert p.decide(12, _T(12), 200).reason == KeyframeWhy(KeyframeReason.INTERVAL, "3 frames")


def test_keyframe_policy_max_gap_caps_interval():
    p = KeyframePolicy(TrackingConfig(keyframe_every=10, keyframe_max_gap=4))
    p.accept(0, _T())
    assert [p.decide(i, _T(i), 500).is_keyframe for i in range(1, 5)] == [False, False, False, True]


def test_triangulate_tracks_recovers_points_and_rejects_bad_ones():
    rng = np.random.default_rng(3)
    pw = np.c_[rng.uniform(-8, 8, 50), rng.uniform(-2, 1, 50), rng.uniform(8, 30, 50)]
    T0, T1 = _T(0.0), se3.exp(np.array([0.5, 0.0, 3.0, 0.0, 0.05, 0.0]))
    uv0 = (se3.transform_points(se3.inv(T0), pw) @ K.T)
    uv0 = uv0[:, :2] / uv0[:, 2:]
    uv1 = (se3.transform_points(se3.inv(T1), pw) @ K.T)
    uv1 = uv1[:, :2] / uv1[:, 2:]
    uv1[:5] += 20.0  # wrong matches
    est, ok = triangulate_tracks(K, T0, uv0, T1, uv1, max_reproj_px=2.0)
    assert not ok[:5].any()
    # Points near the focus of expansion have too little parallax to keep; the rest must be exact.
    assert ok[5:].mean() > 0.7
    assert np.allclose(est[ok], pw[ok], atol=1e-6)


def test_search_by_projection_is_one_to_one_and_respects_radius_and_hamming():
    from plvo.tracking.association import hamming, search_by_projection

    desc = _desc(4, 7)
    kp = np.array([[100.0, 100.0], [103.0, 100.0], [300.0, 50.0], [500.0, 200.0]])
    kp_desc = desc.copy()
    kp_desc[1] = desc[0]  # keypoint 1 looks exactly like landmark 0, keypoint 0 slightly less
    kp_desc[0, :2] ^= 0xFF
    uv = np.array([[101.0, 100.0], [102.0, 101.0], [300.0, 70.0], [np.nan, np.nan]])
    lm_desc = desc.copy()
    lm_desc[1] = kp_desc[0]
    free = np.ones(4, bool)
    rows, kps = search_by_projection(uv, lm_desc, kp, kp_desc, free, radius_px=8.0, max_hamming=64)
    got = dict(zip(rows.tolist(), kps.tolist()))
    # Landmark 0 takes its exact twin (keypoint 1), landmark 1 its own (keypoint 0); landmark 2 is 20 px off.
    assert got == {0: 1, 1: 0}
    assert hamming(lm_desc[:1], kp_desc[1:2])[0] == 0
    free[1] = False
    rows, kps = search_by_projection(uv, lm_desc, kp, kp_desc, free, radius_px=8.0, max_hamming=10)
    assert dict(zip(rows.tolist(), kps.tolist())) == {1: 0}


def test_keyframe_poses_are_stored_rigid():
    """Workers chain keyframe poses through rigid inverses (transposes); a rotation block that is slightly off SO(3)
    comes back further off each time. The map projects every written pose back (the runaway this stops squeezed
    keyframe spacing by a quarter after ~35 keyframes on the 1 km synthetic runs)."""
    m = LandmarkMap()
    R = se3.so3_exp(np.array([0.1, -0.2, 0.3]))
    bad = np.eye(4)
    bad[:3, :3] = R @ np.diag([1.001, 0.999, 1.0005])
    bad[:3, 3] = [1.0, 2.0, 3.0]
    kf = m.add_keyframe(0, bad)
    for T in (m.keyframe_pose(kf), None):
        if T is None:
            m.apply_update(keyframe_ids=np.array([kf]), keyframe_T_world_cam=bad[None])
            T = m.keyframe_pose(kf)
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)
        assert np.allclose(T[:3, :3], R, atol=2e-3) and np.allclose(T[:3, 3], [1, 2, 3])
    # The runaway itself: T <- (T T_ba^-1) T_ba with T_ba = inv(inv(T)) by transposes, as the back end's rebase.
    T = bad.copy()
    for _ in range(10):
        T = T @ se3.inv(se3.inv(se3.inv(T))) @ T
    assert np.abs(T[:3, :3] @ T[:3, :3].T - np.eye(3)).max() > 1e-2  # without re-projection it grows
