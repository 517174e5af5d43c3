"""Global bundle adjustment after the pose graph (plvo.loop.global_ba), on a simulated loop with known truth.

The world: point landmarks on two walls along a 60 m square block; 48 keyframes every 5 m around it; each sees the
points in its image with 0.5 px noise, a lidar depth prior on seven in ten (2 % noise). The odometry drifts (2 %
scale, 0.3 deg yaw a keyframe) and one loop edge joins the last keyframe to the first; the back end's
registrations between consecutive keyframes are 1 cm / 0.05 deg off. Start: the pose graph's solution (on the
drifting odometry), landmarks placed from the first keyframe that saw them, as the map has them then.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from plvo.config import BackendConfig, LoopConfig
from plvo.geometry import se3
from plvo.loop import global_ba
from plvo.loop.closer import optimize_pose_graph
from plvo.tracking.map import Observations

K = np.array([[707.0, 0.0, 601.9], [0.0, 707.0, 183.1], [0.0, 0.0, 1.0]])
W, H = 1241, 376
SIDE, STEP = 60.0, 5.0


def _pose(x: float, z: float, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = [x, 0.0, z]
    return T


def _route() -> np.ndarray:
    corners = np.array([[0, 0], [0, SIDE], [SIDE, SIDE], [SIDE, 0], [0, 0]], float)
    out = []
    for d in np.arange(0, 4 * SIDE, STEP):
        seg = int(d // SIDE)
        a, b = corners[seg], corners[seg + 1]
        p = a + (b - a) * ((d - seg * SIDE) / SIDE)
        out.append(_pose(p[0], p[1], np.arctan2(b[0] - a[0], b[1] - a[1])))
    return np.stack(out)


def _points(rng) -> np.ndarray:
    pts = []
    for off in (-8.0, 8.0):  # walls 8 m left and right of the street
        t = rng.uniform(-10, SIDE + 10, 900)
        h = rng.uniform(-6, 1.5, 900)
        for side in range(4):
            along = t if side % 2 == 0 else SIDE - t
            x, z = {0: (off, along), 1: (along, SIDE - off), 2: (SIDE - off, SIDE - along),
                    3: (SIDE - along, off)}[side]
            pts.append(np.c_[np.full(900, x) if side in (0, 2) else x, h, z if side in (0, 2) else np.full(900, z)])
    return np.concatenate(pts)


def _scene(seed: int = 0):
    rng = np.random.default_rng(seed)
    gt = _route()
    X = _points(rng)
    obs_lm, obs_kf, obs_uv, obs_z = [], [], [], []
    for k, T in enumerate(gt):
        Tcw = se3.inv(T)
        Xc = X @ Tcw[:3, :3].T + Tcw[:3, 3]
        z = Xc[:, 2]
        uv = (Xc @ K.T)[:, :2] / np.where(z > 0, z, 1)[:, None]
        vis = np.flatnonzero((z > 2) & (z < 40) & (uv[:, 0] > 0) & (uv[:, 0] < W) & (uv[:, 1] > 0) & (uv[:, 1] < H))
        vis = rng.permutation(vis)[:150]
        obs_lm.append(vis)
        obs_kf.append(np.full(len(vis), k))
        obs_uv.append(uv[vis] + rng.normal(0, 0.5, (len(vis), 2)))
        zz = z[vis] * (1 + rng.normal(0, 0.02, len(vis)))
        zz[rng.random(len(vis)) > 0.7] = np.nan
        obs_z.append(zz)
    obs = Observations(np.concatenate(obs_lm), np.concatenate(obs_kf), np.zeros(sum(map(len, obs_lm)), int),
                       np.concatenate(obs_uv))
    depth = np.concatenate(obs_z)
    # Drifting odometry: 2 % long, 0.3 deg of yaw a keyframe.
    drift = _pose(0, 0, np.radians(0.3))
    odometry = []
    for k in range(1, len(gt)):
        T = se3.inv(gt[k - 1]) @ gt[k]
        T[:3, 3] *= 1.02
        odometry.append((k - 1, k, T @ drift))
    loops = [(0, len(gt) - 1, se3.inv(gt[0]) @ gt[-1])]
    chain = [gt[0]]
    for _, _, T in odometry:
        chain.append(chain[-1] @ T)
    pg = optimize_pose_graph(np.stack(chain), odometry, loops, LoopConfig())
    # Each landmark where its first keyframe puts it (measured depth, or 15 m without one), in the pose graph's frame.
    ids = np.unique(obs.landmark)
    first = np.array([np.flatnonzero(obs.landmark == i)[0] for i in ids])
    zf = np.where(np.isfinite(depth[first]), depth[first], 15.0)
    ray = np.c_[obs.measurement[first], np.ones(len(first))] @ np.linalg.inv(K).T
    Xc0 = ray * zf[:, None]
    Tk = pg[obs.keyframe[first]]
    positions = np.einsum("nij,nj->ni", Tk[:, :3, :3], Xc0) + Tk[:, :3, 3]
    # The back end's registrations: 1 cm and 0.05 deg off the truth (zeta 0.3); the loop edge exact (zeta 1).
    edges = []
    for k in range(1, len(gt)):
        T = se3.inv(gt[k - 1]) @ gt[k] @ se3.exp(rng.normal(0, [0.01] * 3 + [np.radians(0.05)] * 3))
        edges.append((k - 1, k, T, 0.3))
    edges += [(i, j, T, 1.0) for i, j, T in loops]
    return gt, np.stack(chain), pg, edges, obs, depth, X, positions


def _ate(est: np.ndarray, gt: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((est[:, :3, 3] - gt[:, :3, 3]) ** 2, axis=1))))


def test_global_ba_improves_on_the_pose_graph():
    gt, chain, pg, edges, obs, depth, X, positions = _scene()
    problem, pt_ids = global_ba.build_problem(K, pg, edges, obs, positions, depth, LoopConfig(), BackendConfig())
    assert problem.n_keyframes == len(gt) and len(pt_ids) > 500
    res = global_ba.optimize(problem, BackendConfig(), LoopConfig(), True, 0.54)
    correction = float(np.max(np.linalg.norm(pg[:, :3, 3] - chain[:, :3, 3], axis=1)))
    assert global_ba.implausible(pg, res, LoopConfig(), correction) == ""
    before, after = _ate(pg, gt), _ate(res.T_world_cam, gt)
    assert after < before / 3, (before, after)  # measured: odometry 4.99 m, pose graph 1.05 m, global BA 0.07 m
    # The points it adjusted are where the truth has them (within the depth noise), better than before.
    used = res.point_used
    err0 = np.linalg.norm(problem.points[used] - X[pt_ids[used]], axis=1)
    err1 = np.linalg.norm(res.points[used] - X[pt_ids[used]], axis=1)
    # measured 1.10 m -> 0.25 m (2 % depth noise at 5-40 m over a few views)
    assert np.median(err1) < 0.5 * np.median(err0) and np.median(err1) < 0.35, (np.median(err0), np.median(err1))


def test_gross_observations_are_left_out():
    gt, chain, pg, edges, obs, depth, X, positions = _scene()
    bad = np.arange(0, len(obs.landmark), 10)
    uv = obs.measurement.copy()
    uv[bad] += 60.0  # a tenth of the observations 85 px off: wrong associations
    obs_bad = Observations(obs.landmark, obs.keyframe, obs.feature, uv)
    problem, _ = global_ba.build_problem(K, pg, edges, obs_bad, positions, depth, LoopConfig(), BackendConfig())
    assert len(problem.pt_kf) < 0.92 * len(obs.landmark)
    kept = {(int(k), float(u)) for k, u in zip(problem.pt_kf, problem.pt_uv[:, 0])}
    assert not kept & {(int(k), float(u)) for k, u in zip(obs.keyframe[bad], uv[bad, 0])}
    res = global_ba.optimize(problem, BackendConfig(), LoopConfig(), True, 0.54)
    assert _ate(res.T_world_cam, gt) < _ate(pg, gt) / 3


def test_a_result_far_from_the_pose_graph_is_rejected():
    gt, chain, pg, edges, obs, depth, X, positions = _scene()
    problem, _ = global_ba.build_problem(K, pg, edges, obs, positions, depth, LoopConfig(), BackendConfig())
    res = global_ba.optimize(problem, BackendConfig(), LoopConfig(), True, 0.54)
    moved = pg.copy()
    moved[20, :3, 3] += [0.0, 0.0, 2.5]
    why = global_ba.implausible(pg, dataclasses.replace(res, T_world_cam=moved), LoopConfig())
    assert "keyframe 20" in why and "2.5" in why and "2.00 m" in why  # no pose-graph correction given: 2 m
    assert global_ba.implausible(pg, dataclasses.replace(res, T_world_cam=moved), LoopConfig(), 5.0) == ""
    worse = dataclasses.replace(res, T_world_cam=pg, final_cost=res.initial_cost * 2)
    assert "cost rose" in global_ba.implausible(pg, worse, LoopConfig())


def test_a_point_budget_bounds_the_problem_and_keeps_every_keyframe_constrained():
    """With a budget of a quarter of the points, the problem holds at most that many, the same share for every
    keyframe (each observes points), and the adjustment still closes the loop's drift."""
    gt, chain, pg, edges, obs, depth, X, positions = _scene()
    full, _ = global_ba.build_problem(K, pg, edges, obs, positions, depth, LoopConfig(), BackendConfig())
    budget = full.points.shape[0] // 4
    cfg = LoopConfig(global_ba_max_points=budget)
    problem, pt_ids = global_ba.build_problem(K, pg, edges, obs, positions, depth, cfg, BackendConfig())
    assert budget - len(gt) <= len(pt_ids) <= budget
    per_kf = np.bincount(problem.pt_kf, minlength=len(gt))
    assert per_kf.min() >= 4, per_kf  # every keyframe still observes points of the problem (measured 5-21)
    res = global_ba.optimize(problem, BackendConfig(), cfg, True, 0.54)
    assert _ate(res.T_world_cam, gt) < _ate(pg, gt) / 3


def test_point_budget_is_the_same_share_a_keyframe():
    # keyframe k first observes points 10k..10k+9; point p has p % 10 + 2 views
    point = np.concatenate([np.repeat(10 * k + j, j + 2) for k in range(5) for j in range(10)])
    keyframe = np.concatenate([np.arange(j + 2) + k for k in range(5) for j in range(10)])
    kept = global_ba.point_budget(point, keyframe, 20)
    assert len(kept) == 20
    assert sorted(kept % 10) == sorted([9, 8, 7, 6] * 5)  # the four most-viewed of each keyframe
    assert len(global_ba.point_budget(point, keyframe, 0)) == 50  # 0: no budget
