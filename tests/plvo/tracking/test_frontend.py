"""Frontend logic on a synthetic world of 3D points and lines, with stand-in feature, matching and depth stages.

The stand-ins see the world exactly (pixel noise, partial segments and depth noise added; descriptors encode the
landmark identity, a fraction of matches is made wrong on purpose), so these tests check the tracker itself:
prediction, PnPL, outlier removal, association, keyframes, landmark creation, loss and recovery. The tests on real
images with the real stages are in test_tracking_frontend_real.py.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from plvo.config import SystemConfig, TrackerSections
from plvo.geometry import se3
from plvo.tracking.frontend import Frontend, Stages
from plvo.tracking.keyframes import closest_points_on_lines
from plvo.types import DEPTH_OK, DEPTH_TOO_FEW_POINTS, Calibration, DepthPriors, FeatureSet, Frame, Matches

K = np.array([[718.856, 0.0, 607.19], [0.0, 718.856, 185.2], [0.0, 0.0, 1.0]])
W, H = 1241, 376
CALIB = Calibration(K=K, T_cam_velo=np.eye(4), width=W, height=H)


def trajectory(n: int, speed: float = 1.0, yaw_rate_deg: float = 0.5, stop: tuple[int, int] | None = None,
               turn: tuple[int, int, float] | None = None):
    """(n,4,4) T_world_cam: driving forward (z) at `speed` m/frame while turning; standing still during `stop`;
    turn = (first, end, deg a frame) a sharp turn."""
    yaw, poses = 0.0, []
    pos = np.zeros(3)
    for i in range(n):
        if turn and turn[0] <= i < turn[1]:
            yaw += np.radians(turn[2])
        T = np.eye(4)
        T[:3, :3] = se3.so3_exp(np.array([0.0, yaw, 0.0]))
        T[:3, 3] = pos
        poses.append(T)
        moving = not (stop and stop[0] <= i < stop[1])
        if moving:
            yaw += np.radians(yaw_rate_deg)
            pos = pos + T[:3, :3] @ np.array([0.0, 0.0, speed])
    return np.array(poses)


class World:
    """Points and line segments along a trajectory, and the stand-in stages that observe them."""

    def __init__(self, poses: np.ndarray, seed: int = 0, n_pts: int = 8000, n_lines: int = 900,
                 wrong_match_frac: float = 0.1):
        self.rng = np.random.default_rng(seed)
        self.poses = poses
        self.wrong = wrong_match_frac
        self.current = 0
        self.blind: set[int] = set()  # frames the matcher finds nothing in (forced tracking loss)
        along = self.rng.uniform(0, len(poses) - 1, n_pts + n_lines)
        base = poses[np.round(along).astype(int)]
        side = self.rng.choice([-1.0, 1.0], n_pts + n_lines) * self.rng.uniform(3, 20, n_pts + n_lines)
        local = np.c_[side, self.rng.uniform(-6, 1.6, n_pts + n_lines), self.rng.uniform(-5, 40, n_pts + n_lines)]
        anchor = np.einsum("nij,nj->ni", base[:, :3, :3], local) + base[:, :3, 3]
        self.points = anchor[:n_pts]
        a = anchor[n_pts:]
        vertical = self.rng.random(n_lines) < 0.5
        d = np.where(vertical[:, None], [0.0, 1.0, 0.0], np.c_[self.rng.normal(size=n_lines), np.zeros(n_lines),
                                                                self.rng.normal(size=n_lines)])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        self.lines = np.stack([a, a + d * self.rng.uniform(2, 6, (n_lines, 1))], axis=1)

    # -- stand-in stages -------------------------------------------------------------------------------------
    def extract(self, image, orb_cfg, line_cfg, points_only=False) -> FeatureSet:
        T_cw = se3.inv(self.poses[self.current])
        pc = se3.transform_points(T_cw, self.points)
        uv = pc[:, :2] / pc[:, 2:3] * K[0, 0] + K[:2, 2]
        vis = (pc[:, 2] > 1.0) & (pc[:, 2] < 60) & (uv[:, 0] > 0) & (uv[:, 0] < W) & (uv[:, 1] > 0) & (uv[:, 1] < H)
        pid = np.flatnonzero(vis)
        kp = uv[vis] + self.rng.normal(0, 0.5, (len(pid), 2))
        # Each frame sees a random part of each segment, as LSD does.
        lc = se3.transform_points(T_cw, self.lines.reshape(-1, 3)).reshape(-1, 2, 3)
        f = np.c_[self.rng.uniform(0, 0.15, len(lc)), self.rng.uniform(0.85, 1, len(lc))]
        sub = lc[:, :1] + f[:, :, None] * (lc[:, 1:] - lc[:, :1])
        with np.errstate(divide="ignore", invalid="ignore"):
            suv = sub[..., :2] / sub[..., 2:3] * K[0, 0] + K[:2, 2]
        lvis = ((sub[..., 2] > 1.0) & (sub[..., 2] < 60) & (suv[..., 0] > 0) & (suv[..., 0] < W)
                & (suv[..., 1] > 0) & (suv[..., 1] < H)).all(axis=1)
        lvis &= np.linalg.norm(suv[:, 1] - suv[:, 0], axis=1) > 30
        lid = np.flatnonzero(lvis)
        segs = suv[lvis].reshape(-1, 4) + self.rng.normal(0, 0.5, (len(lid), 4))
        desc, ldesc = _encode(pid), _encode(lid)
        if self.current in self.blind:  # descriptors far from every earlier one: nothing is re-found by projection
            desc, ldesc = ~desc, ~ldesc
        return FeatureSet(
            keypoints=kp, kp_octave=np.zeros(len(pid), int), kp_angle=np.zeros(len(pid)),
            kp_response=np.ones(len(pid)), descriptors=desc, segments=segs,
            line_descriptors=ldesc, raw_segments=segs, segment_sources=tuple(),
            image_size=(W, H),
        )

    def _match(self, ids_prev, ids_cur) -> Matches:
        common, ip, ic = np.intersect1d(ids_prev, ids_cur, return_indices=True)
        if self.current in self.blind:
            ip, ic = ip[:0], ic[:0]
        ic = ic.copy()
        bad = self.rng.random(len(ic)) < self.wrong
        ic[bad] = self.rng.integers(0, len(ids_cur), bad.sum())
        return Matches(np.c_[ip, ic].astype(np.int64), np.zeros(len(ip)))

    def match_points(self, prev, cur, cfg, predicted_uv=None) -> Matches:
        m = self._match(_decode(prev.descriptors), _decode(cur.descriptors))
        if predicted_uv is not None and len(m):
            # Like the real matcher, a prediction restricts the search to a window around it.
            err = np.linalg.norm(predicted_uv[m.pairs[:, 0]] - cur.keypoints[m.pairs[:, 1]], axis=1)
            self.pred_err.append(err)
            m = Matches(m.pairs[err < cfg.point_window_px], m.distance[err < cfg.point_window_px])
        return m

    def match_lines(self, prev, cur, cfg, predicted_segments=None) -> Matches:
        m = self._match(_decode(prev.line_descriptors), _decode(cur.line_descriptors))
        if predicted_segments is not None and len(m):
            p, c = predicted_segments[m.pairs[:, 0]], cur.segments[m.pairs[:, 1]]
            mid = np.linalg.norm((p[:, :2] + p[:, 2:]) / 2 - (c[:, :2] + c[:, 2:]) / 2, axis=1)
            ok = mid < 4 * cfg.line_midpoint_px  # the partial segments move the midpoints: a looser bound
            m = Matches(m.pairs[ok], m.distance[ok])
        return m

    def depth(self, scan, feats: FeatureSet, calib, cfg) -> DepthPriors:
        T_cw = se3.inv(self.poses[self.current])
        pid = _decode(feats.descriptors)
        z = se3.transform_points(T_cw, self.points[pid])[:, 2] + self.rng.normal(0, 0.03, len(pid))
        has = self.rng.random(len(pid)) < 0.6  # lidar misses some features
        lid = _decode(feats.line_descriptors)
        lc = se3.transform_points(T_cw, self.lines[lid].reshape(-1, 3)).reshape(-1, 2, 3)
        rays = np.c_[(feats.segments.reshape(-1, 2) - K[:2, 2]) / K[0, 0], np.ones(2 * len(lid))].reshape(-1, 2, 3)
        ends = closest_points_on_lines(lc[:, 0], lc[:, 1], rays) + self.rng.normal(0, 0.03, (len(lid), 2, 3))
        lhas = self.rng.random(len(lid)) < 0.6
        n, m = len(pid), len(lid)
        return DepthPriors(
            point_depth=np.where(has, z, np.nan), point_reason=np.where(has, DEPTH_OK, DEPTH_TOO_FEW_POINTS),
            point_residual=np.zeros(n), point_inliers=np.zeros(n, int), point_plane=np.full((n, 4), np.nan),
            line_endpoints=np.where(lhas[:, None, None], ends, np.nan),
            line_reason=np.where(lhas, DEPTH_OK, DEPTH_TOO_FEW_POINTS), line_residual=np.zeros(m),
            line_inliers=np.zeros(m, int),
        )

    def stages(self):
        self.pred_err: list[np.ndarray] = []
        return Stages(self.extract, self.match_points, self.match_lines, self.depth)


_HASH = np.random.default_rng(99).integers(0, 256, (20000, 23), dtype=np.uint8)


def _encode(ids: np.ndarray) -> np.ndarray:
    """The id in bytes 0-7 and a random 184-bit signature of it in bytes 8-30, so that different landmarks are
    about 92 bits apart, like real ORB descriptors of different points (byte 31 flags inversion)."""
    out = np.zeros((len(ids), 32), np.uint8)
    out[:, :8] = np.asarray(ids, "<i8").view(np.uint8).reshape(-1, 8)
    out[:, 8:31] = _HASH[np.asarray(ids, np.int64)]
    return out


def _decode(desc: np.ndarray) -> np.ndarray:
    desc = np.where(desc[:, 31:32] == 255, ~desc, desc)  # inverted (blind-frame) descriptors name the same ids
    return np.ascontiguousarray(desc[:, :8]).view("<i8").reshape(-1)


def run(world: World, cfg: SystemConfig):
    # the stand-ins have no images or scans to check the camera against (tests/plvo/tracking/test_lidar_check.py
    # does that)
    cfg = dataclasses.replace(cfg, crosscheck=dataclasses.replace(cfg.crosscheck, enabled=False))
    fe = Frontend(CALIB, cfg.sections(TrackerSections), stages=world.stages())
    results = []
    for i in range(len(world.poses)):
        world.current = i
        frame = Frame(index=i, time=0.1 * i, image=np.zeros((1, 1), np.uint8), scan=np.zeros((1, 4), np.float32),
                      calib=CALIB)
        results.append(fe.track(frame))
    return fe, results


def drift(world: World, results) -> tuple[float, float]:
    """Final translation error (m) and rotation error (deg) against the world's poses."""
    E = se3.inv(world.poses[-1]) @ results[-1].T_world_cam
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(se3.rotation_angle(E)))


def path_length(poses: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())


CFG = SystemConfig()


def test_points_and_lines_track_with_low_drift():
    world = World(trajectory(80, speed=1.2))
    fe, res = run(world, CFG)
    t_err, r_err = drift(world, res)
    length = path_length(world.poses)
    assert t_err / length < 0.01 and r_err < 0.5, (t_err, length, r_err)
    assert all(r.status == "tracked" for r in res[1:])
    assert res[0].status == "initialised" and res[0].is_keyframe
    # Every 3rd frame is a keyframe, lines are used, and the wrong matches that fall inside the search window
    # (10 % are made wrong, about a third of those land inside it) are caught as outliers.
    kfs = [r.frame_index for r in res if r.is_keyframe]
    assert kfs[:4] == [0, 3, 6, 9] and max(np.diff(kfs)) <= 3
    assert np.mean([r.n_line_inliers for r in res[1:]]) > 20
    wrong_frac = np.mean([1 - r.point_inlier.mean() for r in res[1:]])
    assert 0.01 < wrong_frac < 0.1
    # Landmarks were made with depth, lines included; the constant-velocity prediction lands within a few px.
    assert fe.map.n_points > 1000 and fe.map.n_lines > 100
    assert np.median(np.concatenate(world.pred_err[2:])) < 5.0


def test_points_only_mode_uses_no_lines():
    world = World(trajectory(40, speed=1.2), seed=1)
    fe, res = run(world, dataclasses.replace(CFG, tracking=dataclasses.replace(CFG.tracking, points_only=True)))
    t_err, _ = drift(world, res)
    assert t_err / path_length(world.poses) < 0.01
    assert fe.map.n_lines == 0 and all(r.n_line_matches == 0 for r in res)


def test_stopped_car_does_not_drift():
    poses = trajectory(50, speed=1.0, stop=(15, 40))
    world = World(poses, seed=2)
    _, res = run(world, CFG)
    stopped = np.array([r.T_world_cam for r in res[16:40]])
    # Standing still for 24 frames: the estimate moves less than 2 cm and 0.05 deg in total.
    assert np.linalg.norm(stopped[:, :3, 3] - stopped[0, :3, 3], axis=1).max() < 0.02
    assert max(np.degrees(se3.rotation_angle(se3.inv(stopped[0]) @ T)) for T in stopped) < 0.05


def test_forced_tracking_loss_reinitialises_and_recovers(caplog):
    world = World(trajectory(40, speed=1.2), seed=3)
    world.blind = {20}
    with caplog.at_level(logging.WARNING, logger="plvo.tracking.frontend"):
        _, res = run(world, CFG)
    lost = res[20]
    assert lost.status == "reinitialised" and lost.is_keyframe and "tracking lost" in lost.message
    assert lost.n_new_points > 100
    assert lost.source == "motion model" and "re-initialised from the current lidar depth" in lost.message
    warned = [r.getMessage() for r in caplog.records]  # one warning for the episode, naming its frame
    assert len(warned) == 1 and warned[0].startswith("frame 20: tracking lost"), warned
    assert all(r.status == "tracked" for r in res[21:])
    # The lost frame took the constant-velocity prediction; tracking then continues from fresh landmarks.
    t_err, _ = drift(world, res)
    assert t_err / path_length(world.poses) < 0.02


def test_no_depth_priors_ablation_triangulates_points_and_skips_lines():
    world = World(trajectory(40, speed=1.2, yaw_rate_deg=1.0), seed=4, wrong_match_frac=0.05)
    cfg = dataclasses.replace(CFG, tracking=dataclasses.replace(CFG.tracking, use_depth_priors=False))
    fe, res = run(world, cfg)
    assert all(r.status == "tracked" for r in res[1:]), [r.message for r in res if r.status != "tracked"]
    assert fe.map.n_lines == 0
    snap = fe.map.snapshot()
    assert (~snap.point_has_depth).sum() > 200  # triangulated landmarks
    t_err, _ = drift(world, res)
    assert t_err / path_length(world.poses) < 0.03


def test_backend_update_of_last_keyframe_moves_the_tracker():
    world = World(trajectory(12, speed=1.0), seed=5, wrong_match_frac=0.0)
    fe = Frontend(CALIB, CFG.sections(TrackerSections), stages=world.stages())
    res = []
    for i in range(10):
        world.current = i
        res.append(fe.track(Frame(i, 0.0, np.zeros((1, 1), np.uint8), np.zeros((1, 4), np.float32), CALIB)))
    # The back end shifts keyframe 3 (frame 9) and its landmarks by 0.5 m in x, as a scale correction might.
    shift = se3.from_rt(np.eye(3), [0.5, 0, 0])
    snap = fe.map.snapshot()
    kf = int(snap.keyframe_ids[-1])
    fe.map.apply_update(snap.point_ids, snap.point_positions + [0.5, 0, 0], snap.line_ids,
                        snap.line_endpoints + [0.5, 0, 0], [kf], (shift @ snap.keyframe_T_world_cam[kf])[None])
    world.current = 10
    r = fe.track(Frame(10, 0.0, np.zeros((1, 1), np.uint8), np.zeros((1, 4), np.float32), CALIB))
    assert r.status == "tracked"
    assert r.T_world_cam[0, 3] - world.poses[10][0, 3] == pytest.approx(0.5, abs=0.05)


def test_sharp_turn_that_ends_abruptly_is_recovered_without_reinitialising():
    # 8 deg a frame for 10 frames, then straight on: the constant-velocity prediction is then 8 deg (~100 px)
    # off, beyond the matching window; the tracker must fall back to unpredicted matching, not lose the map.
    world = World(trajectory(40, speed=1.0, yaw_rate_deg=0.0, turn=(15, 25, 8.0)), seed=6, n_pts=12000)
    _, res = run(world, CFG)
    assert all(r.status == "tracked" for r in res[1:]), [r.message for r in res if r.status != "tracked"]
    assert "rescue" in res[15].timings and "rescue" in res[25].timings  # both ends of the turn needed it
    t_err, r_err = drift(world, res)
    assert t_err / path_length(world.poses) < 0.01 and r_err < 0.5, (t_err, r_err)


def test_a_keyframe_tracked_before_a_back_end_result_is_solved_again_on_the_refined_map():
    """Deployed, keyframe k+1 is tracked while the back end refines the window of k; the map then carries k+1
    rigidly with k, but the landmarks k+1 was solved on moved each by its own refinement. Here the refinement is a
    scale correction (+10 % about keyframe 0, what the back end's scale step does): carried rigidly, the newest
    keyframe sits 0.3 m from where the scaled landmarks put it; relocalised, where they put it, and the landmarks
    it made itself move with it."""
    from plvo.tracking.corrections import BACKEND, MapCorrection

    world = World(trajectory(7, speed=1.0), wrong_match_frac=0.0)
    fe, res = run(world, CFG)
    m = fe.map
    assert [r.is_keyframe for r in res] == [True, False, False, True, False, False, True]
    newest = m.n_keyframes - 1
    s = 1.1
    window = m.window_data(np.arange(newest))  # the window read before the newest keyframe was made
    origin = window.T_world_cam[0][:3, 3]
    T_after = window.T_world_cam.copy()
    T_after[:, :3, 3] = origin + s * (T_after[:, :3, 3] - origin)
    scaled = origin + s * (window.points - origin)
    m.apply(MapCorrection(BACKEND, window.kf_ids, window.T_world_cam, T_after, point_ids=window.point_ids,
                          point_positions=scaled))
    want = origin + s * (res[-1].T_world_cam[:3, 3] - origin)  # where the scaled map puts the newest keyframe
    carried = m.keyframe_pose(newest)
    assert np.linalg.norm(carried[:3, 3] - want) > 0.25  # rigid carrying alone leaves it off
    own_ids, first = m.point_ids_and_first_keyframes()
    own_ids = own_ids[first == newest]
    own_local = se3.transform_points(se3.inv(carried), m.point_positions(own_ids))
    correction = fe.relocalise_keyframe()
    assert correction is not None and list(correction.keyframe_ids) == [newest]
    m.apply(correction)
    T = m.keyframe_pose(newest)
    assert np.linalg.norm(T[:3, 3] - want) < 0.05, (T[:3, 3], want)
    assert np.allclose(se3.transform_points(se3.inv(T), m.point_positions(own_ids)), own_local, atol=1e-9)
    assert np.allclose(m.keyframe_pose(newest - 1), T_after[-1], atol=1e-12)  # older keyframes untouched
