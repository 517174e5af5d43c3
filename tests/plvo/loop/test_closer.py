"""LoopCloser: pose-graph correction, and detection + verification + correction over a simulated loop drive.

The simulated world: walls along a 150 m square block with point landmarks (random 256-bit descriptors, seen
with 4 % of the bits flipped) and vertical line landmarks; a car drives around it once and 120 m along the
first street again (the revisit), keyframes every 2.5 m, with drifting odometry. The keyframes carry what the
system gives the closer: keypoints, descriptors, camera-frame 3D points (60 % with a depth prior, 1 % noise),
segments, LBD-like descriptors and 3D endpoints. Vocabularies are trained on other observations of the world.
"""

from __future__ import annotations

import numpy as np
import pytest

from plvo.config import LoopConfig
from plvo.geometry import se3
from plvo.loop.closer import LoopCloser, optimize_pose_graph
from plvo.loop.scans import thin_scan
from plvo.loop.verification import LoopKeyframe
from plvo.loop.vocabulary import Vocabulary

K = np.array([[707.0, 0.0, 601.9], [0.0, 707.0, 183.1], [0.0, 0.0, 1.0]])
W, H = 1241, 376
SIDE = 150.0
STEP = 2.5


def yaw_pose(x: float, z: float, yaw: float) -> np.ndarray:
    """Camera pose on the ground plane (world y down): heading yaw about -y from +z."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    T[:3, 3] = [x, 0.0, z]
    return T


def route(length: float) -> np.ndarray:
    """(K,4,4) GT keyframe poses every STEP m clockwise around the square (seen from above), from (0,0) along +z."""
    corners = np.array([[0, 0], [0, SIDE], [SIDE, SIDE], [SIDE, 0], [0, 0]], float)
    s = np.arange(0, length, STEP)
    poses = []
    for d in s:
        k, r = divmod(d, 4 * SIDE)
        seg = int(r // SIDE)
        a, b = corners[seg], corners[seg + 1]
        p = a + (b - a) * ((r - seg * SIDE) / SIDE)
        poses.append(yaw_pose(p[0], p[1], np.arctan2(b[0] - a[0], b[1] - a[1])))
    return np.stack(poses)


class World:
    def __init__(self, seed: int = 0):
        rng = np.random.default_rng(seed)
        pts, lines = [], []
        for side in range(4):
            for off in (-10.0, 10.0):
                n = int(SIDE * 8)
                t = rng.uniform(-15, SIDE + 15, n)
                pts.append(self._wall(side, t, off, rng.uniform(-8, 1.5, n)))
                nl = int(SIDE)
                tl = rng.uniform(-15, SIDE + 15, nl)
                y0 = rng.uniform(-6, -3, nl)
                lines.append(np.stack([self._wall(side, tl, off, y0), self._wall(side, tl, off, y0 + 4.0)], 1))
        self.points = np.concatenate(pts)
        self.lines = np.concatenate(lines)
        self.pdesc = rng.integers(0, 256, (len(self.points), 32), dtype=np.uint8)
        self.ldesc = rng.integers(0, 256, (len(self.lines), 32), dtype=np.uint8)
        self.rng = rng
        self._vocabs = None

    @staticmethod
    def _wall(side: int, t: np.ndarray, off: float, y: np.ndarray) -> np.ndarray:
        # Street `side` runs between square corners; `off` is the lateral distance of the wall from its centre.
        x = {0: off + 0 * t, 1: t, 2: SIDE + off + 0 * t, 3: t}[side]
        z = {0: t, 1: SIDE + off + 0 * t, 2: t, 3: off + 0 * t}[side]
        return np.stack([x, y, z], 1)

    def _noisy(self, desc: np.ndarray) -> np.ndarray:
        flips = np.packbits(self.rng.random((len(desc), 256)) < 0.04, axis=1)
        return desc ^ flips

    def observe(self, kf_id: int, T_world_cam_gt: np.ndarray, T_world_cam_est: np.ndarray) -> LoopKeyframe:
        T_cw = se3.inv(T_world_cam_gt)
        pc = se3.transform_points(T_cw, self.points)
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = pc[:, :2] / pc[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        vis = np.nonzero((pc[:, 2] > 3) & (pc[:, 2] < 50) & (uv[:, 0] >= 0) & (uv[:, 0] < W)
                         & (uv[:, 1] >= 0) & (uv[:, 1] < H))[0]
        vis = self.rng.permutation(vis)[:1000]
        kp = uv[vis] + self.rng.normal(0, 0.7, (len(vis), 2))
        p3 = pc[vis] * (1 + self.rng.normal(0, 0.01, (len(vis), 1)))
        p3[self.rng.random(len(vis)) > 0.6] = np.nan
        lc = se3.transform_points(T_cw, self.lines.reshape(-1, 3)).reshape(-1, 2, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            luv = lc[..., :2] / lc[..., 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        lvis = np.nonzero(np.all((lc[..., 2] > 3) & (lc[..., 2] < 50) & (luv[..., 0] >= 0) & (luv[..., 0] < W)
                                 & (luv[..., 1] >= 0) & (luv[..., 1] < H), axis=1))[0]
        seg = luv[lvis].reshape(-1, 4) + self.rng.normal(0, 0.7, (len(lvis), 4))
        return LoopKeyframe(kf_id, T_world_cam_est, kp, self._noisy(self.pdesc[vis]), p3, seg,
                            self._noisy(self.ldesc[lvis]), lc[lvis].copy())

    def vocabularies(self) -> tuple[Vocabulary, Vocabulary]:
        if self._vocabs is None:
            self._vocabs = self._train()
        return self._vocabs

    def _train(self) -> tuple[Vocabulary, Vocabulary]:
        imgs_p = [self._noisy(self.pdesc[self.rng.choice(len(self.pdesc), 800, replace=False)]) for _ in range(40)]
        imgs_l = [self._noisy(self.ldesc[self.rng.choice(len(self.ldesc), 80, replace=False)]) for _ in range(40)]
        return Vocabulary.train(imgs_p, k=10, depth=4, seed=1), Vocabulary.train(imgs_l, k=10, depth=3, seed=1)


def drifted_step(T_rel: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Odometry of one keyframe step: 0.3 mrad yaw bias, 0.5 % scale error and noise (about 1 % drift)."""
    noise = np.r_[rng.normal(0, 0.01, 3), rng.normal(0, 2e-4, 3)]
    noise[4] += 3e-4
    T = T_rel.copy()
    T[:3, 3] *= 1.005
    return T @ se3.exp(noise)


def run_closer(world: World, gt: np.ndarray, cfg: LoopConfig, seed: int = 3):
    """Drive the closer over the keyframes with drifting odometry -> (closer, results, poses without closure)."""
    orb, lbd = world.vocabularies()
    closer = LoopCloser(K, orb, lbd, cfg)
    rng = np.random.default_rng(seed)
    steps = [drifted_step(se3.inv(gt[i - 1]) @ gt[i], rng) for i in range(1, len(gt))]
    open_loop = [gt[0]]
    for s in steps:
        open_loop.append(open_loop[-1] @ s)
    results = []
    for i in range(len(gt)):
        # The tracker continues from the closer's (possibly corrected) estimate of the previous keyframe.
        est = gt[0] if i == 0 else closer.poses()[1][-1] @ steps[i - 1]
        results.append(closer.on_keyframe(world.observe(i, gt[i], est)))
    return closer, results, np.stack(open_loop)


def test_pose_graph_one_loop_edge_reduces_end_point_error():
    gt = route(4 * SIDE)  # one lap: the last keyframe is 2.5 m before the first
    rng = np.random.default_rng(0)
    steps = [drifted_step(se3.inv(gt[i - 1]) @ gt[i], rng) for i in range(1, len(gt))]
    est = [gt[0]]
    for s in steps:
        est.append(est[-1] @ s)
    est = np.stack(est)
    n = len(gt)
    odometry = [(i - 1, i, steps[i - 1]) for i in range(1, n)]
    loop = [(0, n - 1, se3.inv(gt[0]) @ gt[-1])]
    after = optimize_pose_graph(est, odometry, loop, LoopConfig())
    err_before = np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3])
    err_after = np.linalg.norm(after[-1, :3, 3] - gt[-1, :3, 3])
    ate_before = np.sqrt(np.mean(np.sum((est[:, :3, 3] - gt[:, :3, 3]) ** 2, 1)))
    ate_after = np.sqrt(np.mean(np.sum((after[:, :3, 3] - gt[:, :3, 3]) ** 2, 1)))
    assert err_before > 3.0  # the drift is real (about 1 % of 600 m)
    assert err_after < err_before / 10  # measured: 6.5 m -> 0.09 m
    assert ate_after < ate_before / 2
    np.testing.assert_allclose(after[0], est[0], atol=1e-6)


def _loop_stats(results, gt, closer):
    accepted = [r.accepted for r in results if r.accepted is not None]
    correct = []
    for e in accepted:
        # An edge is right when it is the true relative pose (the two views may be far apart at a corner).
        dT = se3.inv(se3.inv(gt[e.match_id]) @ gt[e.query_id]) @ e.T_match_query
        correct.append(np.linalg.norm(dT[:3, 3]) < 0.5 and np.degrees(se3.rotation_angle(dT)) < 1.0)
    return accepted, correct


@pytest.fixture(scope="module")
def world() -> World:
    return World(seed=0)


def test_closer_finds_the_revisit_and_corrects_drift(world: World):
    gt = route(4 * SIDE + 120)
    closer, results, open_loop = run_closer(world, gt, LoopConfig())
    accepted, correct = _loop_stats(results, gt, closer)
    lap_kfs = int(4 * SIDE / STEP)
    assert accepted, "no loop accepted on a drive that revisits 120 m of its first street"
    assert all(correct), "a wrong loop edge was accepted"  # precision 1
    assert any(e.query_id >= lap_kfs for e in accepted)  # found while driving the first street again
    ids, final = closer.poses()
    end_before = np.linalg.norm(open_loop[-1, :3, 3] - gt[-1, :3, 3])
    end_after = np.linalg.norm(final[-1, :3, 3] - gt[-1, :3, 3])
    assert end_after < end_before / 3, (end_before, end_after)
    corrections = [r for r in results if r.poses_after is not None]
    assert all(r.poses_after.shape == r.poses_before.shape for r in corrections)


def test_closer_accepts_nothing_without_a_revisit(world: World):
    gt = route(3 * SIDE + 60)  # three sides and part of the fourth: never sees the start again
    _, results, _ = run_closer(world, gt, LoopConfig())
    assert not [r.accepted for r in results if r.accepted is not None]


def test_thin_scan_keeps_one_point_per_voxel():
    rng = np.random.default_rng(0)
    scan = np.c_[rng.uniform(-10, 10, (20000, 3)), rng.random(20000)].astype(np.float32)
    thin = thin_scan(scan, 1.0)
    keys = np.floor(thin[:, :3] / 1.0)
    assert len(np.unique(keys, axis=0)) == len(thin)
    assert len(thin) == len(np.unique(np.floor(scan[:, :3]), axis=0))


def _first_of_each_voxel(scan: np.ndarray, voxel_m: float) -> np.ndarray:
    """The definition thin_scan implements faster: the first finite point of each voxel, in the scan's order."""
    scan = scan[np.all(np.isfinite(scan[:, :3]), axis=1)]
    _, first = np.unique(np.floor(scan[:, :3] / voxel_m).astype(np.int64), axis=0, return_index=True)
    return scan[np.sort(first)]


@pytest.mark.parametrize("far", [False, True])
def test_thin_scan_is_the_first_point_of_each_voxel(far):
    """Exactly (same points, same order) on scans with non-finite returns, and with a point so far away that the
    packed voxel keys would overflow (the fallback)."""
    rng = np.random.default_rng(1)
    for _ in range(5):
        scan = np.c_[rng.normal(0, 20, (5000, 3)), rng.random(5000)].astype(np.float32)
        scan[rng.integers(0, 5000, 40), rng.integers(0, 3, 40)] = np.nan
        scan[rng.integers(0, 5000, 5), 0] = np.inf
        if far:
            scan[7, :3] = (3e5, -3e5, 1e5)
        for voxel in (0.2, 0.3, 1.0):
            np.testing.assert_array_equal(thin_scan(scan, voxel), _first_of_each_voxel(scan, voxel))


def test_thin_scan_of_a_real_scan(kitti_root):
    from pykitti.utils import load_velo_scan

    scan = load_velo_scan(str(kitti_root / "sequences" / "04" / "velodyne" / "000010.bin"))
    for voxel in (0.2, 0.3):
        np.testing.assert_array_equal(thin_scan(scan, voxel), _first_of_each_voxel(scan, voxel))


def test_loop_contradicting_the_odometry_is_rejected():
    """A verified edge that would move the query keyframe far more than odometry can drift is a repeated place."""
    # vocabularies unused here; the straight street's "loop" edges are 45 m long, allowed here (see the next test)
    closer = LoopCloser(K, orb_vocab=object(), lbd_vocab=object(), cfg=LoopConfig(max_view_m=60.0))
    empty = np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros((0, 3))
    poses = [se3.exp(np.array([0.0, 0.0, 5.0 * i, 0.0, 0.0, 0.0])) for i in range(10)]  # 5 m apart, straight on
    for i, T in enumerate(poses):
        closer._store(LoopKeyframe(i, T, *empty))
    truth = se3.inv(poses[0]) @ poses[9]  # 45 m driven: up to 0.1 * 45 + 2 = 6.5 m of drift is plausible
    drifted = truth @ se3.exp(np.array([3.0, 0.0, 3.0, 0.0, 0.02, 0.0]))
    assert closer._implausible(9, 0, truth) == ""
    assert closer._implausible(9, 0, drifted) == ""  # 4.2 m off
    reason = closer._implausible(9, 0, np.eye(4))  # "the same place" after 45 m: a look-alike street
    assert "45.0 m" in reason and "repeated place" in reason
    closer.cfg = LoopConfig(max_drift_fraction=0)  # the gate switched off
    assert closer._implausible(9, 0, np.eye(4)) == ""
    closer.cfg = LoopConfig()
    assert "45 m long" in closer._implausible(9, 0, truth)  # further apart than two views of one place can be


def test_candidates_the_odometry_puts_far_away_are_refused_before_verification():
    """On a 40-keyframe street, keyframe 39 is 195 m from keyframe 0 by the odometry: no drift bound (21.5 m) plus
    view distance (40 m) makes that a revisit, so it is refused without a PnP/PnL; a lap back near the start is not;
    and a refused candidate is reported with its reason (the soak counts these)."""
    closer = LoopCloser(K, orb_vocab=object(), lbd_vocab=object(), cfg=LoopConfig())
    empty = np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros((0, 3))
    street = [se3.exp(np.array([0.0, 0.0, 5.0 * i, 0.0, 0.0, 0.0])) for i in range(40)]
    for i, T in enumerate(street):
        closer._store(LoopKeyframe(i, T, *empty))
    reason = closer._too_far(39, 0)
    assert "195 m away" in reason and "repeated place" in reason
    assert closer._too_far(8, 0) == ""  # 40 m apart: within 6 m of drift + 40 m of view
    assert closer._too_far(10, 0) != ""  # 50 m apart: more than 7 m of drift + 40 m of view
    lap = LoopCloser(K, orb_vocab=object(), lbd_vocab=object(), cfg=LoopConfig())
    ring = [se3.exp(np.array([30 * np.sin(a), 0.0, 30 * (1 - np.cos(a)), 0.0, a, 0.0]))
            for a in np.linspace(0, 2 * np.pi, 40)[:-1]]
    for i, T in enumerate(ring):
        lap._store(LoopKeyframe(i, T, *empty))
    assert lap._too_far(38, 0) == ""  # 190 m driven, back within 5 m of the start


def test_a_registered_edge_without_a_near_view_is_refused_and_logged(monkeypatch, caplog):
    """A registration that succeeds (its log says "registered") but joins keyframes 30 m apart, with no keyframe near
    the candidate within loop.scan_max_edge_m of the query, is refused: the closer says so in the log as well, so
    that a run's log tells what became of every registered candidate."""
    import logging

    import plvo.loop.closer as closer_module
    from plvo.loop.verification import Verification

    closer = LoopCloser(K, orb_vocab=object(), lbd_vocab=object(), cfg=LoopConfig())
    empty = np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros((0, 3))
    street = [se3.exp(np.array([0.0, 0.0, 5.0 * i, 0.0, 0.0, 0.0])) for i in range(40)]  # along z, 5 m apart
    for i, T in enumerate(street):
        closer._store(LoopKeyframe(i, T, *empty))
    aside = se3.exp(np.array([30.0, 0.0, 0.0, 0.0, 0.0, 0.0]))  # the query 30 m to the side of keyframe 2
    monkeypatch.setattr(closer, "_local_map", lambda kf_id: np.zeros((0, 3)))
    monkeypatch.setattr(closer_module, "verify_by_registration", lambda q, c, *a, **k: Verification(
        q, c, True, aside, 0, 0, 0, 0, True, 0.9, "scan registration: overlap 0.90", 0.0, "bow"))
    with caplog.at_level(logging.DEBUG, logger="plvo.loop.closer"):  # a rejected candidate is DEBUG
        v = closer._register(39, 2, aside, "bow", 0)
    assert not v.accepted and "30.0 m apart" in v.reason and "no keyframe near the candidate" in v.reason
    assert any("candidate 2 (bow) for keyframe 39 rejected" in r.getMessage() and "30.0 m apart" in r.getMessage()
               for r in caplog.records)


def test_an_edge_beyond_the_view_bound_is_handed_to_the_candidates_neighbour(monkeypatch):
    """A street driven out and back: the query's bag-of-words candidate is the keyframe 45 m behind the place, and
    its local maps register (the edge 45 m long, beyond loop.max_view_m 40). The edge goes to the candidate's
    neighbour that saw the query's place (0 m away) and is accepted there; held to the view bound before the hand-off,
    the revisit was refused. The registration is stood in for by one that returns the pose it starts from and
    applies the closer's odometry check, as verify_by_registration does."""
    import plvo.loop.closer as closer_module
    from plvo.loop.verification import Verification

    cfg = LoopConfig()
    closer = LoopCloser(K, orb_vocab=object(), lbd_vocab=object(), cfg=cfg)
    empty = np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros((0, 3))
    out = [5.0 * i for i in range(40)]  # 0 .. 195 m along z
    back = [195.0 - 5.0 * (i - 39) for i in range(40, 70)]  # and back to 45 m
    for i, z in enumerate(out + back):
        closer._store(LoopKeyframe(i, se3.exp(np.array([0.0, 0.0, z, 0.0, 0.0, 0.0])), *empty))
    calls = []

    def registration(q, c, query_map, cand_map, T, cfg_, T_cam_velo, against, *args, **kwargs):
        calls.append((c, float(np.linalg.norm(T[:3, 3]))))
        why = against(T)
        return Verification(q, c, not why, T if not why else np.eye(4), 0, 0, 0, 0, True, 0.9, why or "registered",
                            0.0, "bow")

    monkeypatch.setattr(closer, "_local_map", lambda kf_id: np.zeros((0, 3)))
    monkeypatch.setattr(closer_module, "verify_by_registration", registration)
    first = se3.exp(np.array([0.0, 0.0, 45.0, 0.0, 0.0, 0.0]))  # the query seen 45 m ahead of keyframe 0
    assert 45.0 > cfg.max_view_m > cfg.scan_max_edge_m
    v = closer._register(69, 0, first, "bow", 0)
    assert v.accepted, v.reason
    assert v.cand_id == 9 and np.linalg.norm(v.T_cand_query[:3, 3]) < 1e-9  # keyframe 9 stands where the query is
    assert calls == [(0, 45.0), (9, pytest.approx(0.0, abs=1e-9))]
