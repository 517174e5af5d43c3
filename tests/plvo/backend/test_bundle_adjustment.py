"""Point-line bundle adjustment on a synthetic window with exact truth (6 keyframes, 200 points, 50 lines)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from plvo.backend.bundle_adjustment import optimize
from plvo.backend.problem import BAProblem, make_synthetic_problem
from plvo.config import BackendConfig
from plvo.errors import PlvoError
from plvo.geometry import se3


def _line_dist(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(L,2,3) estimated segments, true segments -> (L,) mean distance of the true endpoints to the estimated lines."""
    d = est[:, 1] - est[:, 0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    out = []
    for k in range(2):
        v = true[:, k] - est[:, 0]
        out.append(np.linalg.norm(v - np.sum(v * d, axis=1, keepdims=True) * d, axis=1))
    return np.mean(out, axis=0)


def _pose_err(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    t = max(np.linalg.norm(T[k][:3, 3] - truth[k][:3, 3]) for k in range(len(T)))
    r = max(np.degrees(se3.rotation_angle(se3.inv(T[k]) @ truth[k])) for k in range(len(T)))
    return float(t), float(r)


@pytest.fixture(scope="module")
def noisy():
    truth = make_synthetic_problem(n_kf=6, n_points=200, n_lines=50, seed=11, pixel_noise=0.3)
    rng = np.random.default_rng(1)
    T = truth.T_world_cam.copy()
    for k in range(1, 6):  # keyframe 0 is fixed (the gauge)
        T[k] = T[k] @ se3.exp(np.r_[rng.normal(0, 0.05, 3), rng.normal(0, 0.005, 3)])
    p = dataclasses.replace(truth, T_world_cam=T, points=truth.points + rng.normal(0, 0.3, truth.points.shape),
                            lines=truth.lines + rng.normal(0, 0.2, truth.lines.shape))
    return truth, p


def test_noise_on_poses_and_landmarks_is_removed(noisy):
    truth, p = noisy
    t0, r0 = _pose_err(p.T_world_cam, truth.T_world_cam)
    assert t0 > 0.1 and r0 > 0.3  # the perturbation is real: 10 cm / 0.3 deg at worst
    res = optimize(p)
    t1, r1 = _pose_err(res.T_world_cam, truth.T_world_cam)
    assert t1 < 0.02 and r1 < 0.05, (t1, r1)  # 0.3 px image noise leaves ~1 cm
    assert np.array_equal(res.T_world_cam[0], p.T_world_cam[0])  # fixed keyframe untouched
    u = res.point_used
    assert u.sum() >= 150
    before = np.median(np.linalg.norm(p.points - truth.points, axis=1)[u])
    after = np.median(np.linalg.norm(res.points - truth.points, axis=1)[u])
    assert after < 0.4 * before, (before, after)
    v = res.line_used
    assert v.sum() >= 15
    lb, la = np.median(_line_dist(p.lines, truth.lines)[v]), np.median(_line_dist(res.lines, truth.lines)[v])
    assert la < 0.5 * lb, (lb, la)
    assert res.final_cost < 0.01 * res.initial_cost
    # landmarks left out come back unchanged
    assert np.array_equal(res.points[~u], p.points[~u]) and np.array_equal(res.lines[~v], p.lines[~v])


def test_bad_relative_pose_with_small_zeta_does_not_pull(noisy):
    truth, p = noisy
    rel_T = p.rel_T.copy()
    rel_T[2] = rel_T[2] @ se3.exp(np.r_[1.0, 0.0, 0.5, 0.0, 0.0, 0.02])  # 1.1 m and 1.1 deg wrong
    zeta = np.ones(len(rel_T))
    zeta[2] = 1e-3
    res = optimize(dataclasses.replace(p, rel_T=rel_T, rel_zeta=zeta))
    t, r = _pose_err(res.T_world_cam, truth.T_world_cam)
    assert t < 0.02 and r < 0.05, (t, r)
    # control: the same factor trusted (zeta huge) does pull the trajectory away, so the test can fail
    zeta[2] = 1e9
    res = optimize(dataclasses.replace(p, rel_T=rel_T, rel_zeta=zeta))
    t, _ = _pose_err(res.T_world_cam, truth.T_world_cam)
    assert t > 0.1, t


def test_points_only_and_no_priors_switches(noisy):
    truth, p = noisy
    res = optimize(p, use_lines=False, use_depth_priors=False)
    assert not res.line_used.any()
    assert np.array_equal(res.lines, p.lines)
    t, _ = _pose_err(res.T_world_cam, truth.T_world_cam)
    assert t < 0.05, t


def test_bad_input_names_the_field():
    truth = make_synthetic_problem(n_kf=2, n_points=20, n_lines=0)
    with pytest.raises(PlvoError, match="pt_idx"):
        dataclasses.replace(truth, pt_idx=truth.pt_idx + 1000)
    with pytest.raises(PlvoError, match="rel_zeta"):
        dataclasses.replace(truth, rel_zeta=-np.ones(len(truth.rel_zeta)))
    with pytest.raises(PlvoError, match="fixed"):
        BAProblem(K=truth.K, T_world_cam=truth.T_world_cam, fixed=np.zeros(3, bool), points=truth.points,
                  pt_kf=truth.pt_kf, pt_idx=truth.pt_idx, pt_uv=truth.pt_uv, pt_depth=truth.pt_depth)


def test_single_view_landmarks_move_rigidly_with_their_keyframe(noisy):
    """A landmark seen by one keyframe tells the poses nothing; it is left out and carried by its keyframe."""
    truth, p = noisy
    extra_pt = np.array([[1.0, 0.5, 20.0 + 5.0 * 5]])  # a point in front of the last keyframe, one observation
    k = 5
    uv = (p.K @ se3.transform_points(se3.inv(truth.T_world_cam[k]), extra_pt).T).T
    uv = uv[:, :2] / uv[:, 2:]
    q = dataclasses.replace(p, points=np.r_[p.points, extra_pt], pt_kf=np.r_[p.pt_kf, k],
                            pt_idx=np.r_[p.pt_idx, p.n_points], pt_uv=np.r_[p.pt_uv, uv],
                            pt_depth=np.r_[p.pt_depth, 25.0])
    res = optimize(q)
    assert res.point_used[-1]
    move = res.T_world_cam[k] @ se3.inv(q.T_world_cam[k])
    np.testing.assert_allclose(res.points[-1], se3.transform_points(move, extra_pt)[0], atol=1e-9)
    assert np.linalg.norm(move[:3, 3]) > 0.01  # the keyframe did move (the noise on it is removed)


def test_damping_goes_to_the_problems_scale_after_a_rejected_step(noisy, monkeypatch):
    """LM starts nearly Gauss-Newton; after a rejected step its damping is at least 1e-2 of the normal equations'
    median diagonal. (Climbing x100 from 1e-5, against a diagonal of ~1e5 at the landmarks and ~1e10 at the poses,
    took three or four more rejected steps in every adjustment of a KITTI window.)"""
    import plvo.backend.bundle_adjustment as ba

    truth, p = noisy
    trials: list[tuple[float, float]] = []
    solve = ba._Normal.solve

    def spy(self, lam):
        trials.append((lam, self.median_diagonal()))
        return solve(self, lam)

    monkeypatch.setattr(ba._Normal, "solve", spy)
    # 5 iterations: with the defaults' 3 this window's rounds reject no step, and the floor would not be reached
    res = optimize(p, BackendConfig(iterations=5))
    t, r = _pose_err(res.T_world_cam, truth.T_world_cam)
    assert t < 0.02 and r < 0.05, (t, r)
    assert trials[0][0] == ba._LAM0 and trials[0][1] > 1e3
    raised, floor = [], None
    for (prev, _), (lam, diag) in zip([(np.inf, 0.0)] + trials, trials):
        if lam == ba._LAM0 and lam < prev:  # an LM round starts (the second round follows the outlier test)
            floor = 1e-2 * diag
        elif lam > prev:
            raised.append((lam, floor))
    assert raised, "no step was rejected: the floor is not exercised"
    assert all(lam >= floor for lam, floor in raised), raised
    assert len(trials) <= 2 * res.iterations + 2, (len(trials), res.iterations)


def test_a_rough_biased_prior_pulls_the_scale_less_when_weighed(noisy):
    """Half the depth priors 5 % too far, as priors fitted to foliage are (the lidar seen through the leaves), each
    with a 1 m sigma of its own; no relative-pose factors, so the priors alone set the scale. Unweighed, the window
    comes out 2-3 % long; weighed by their sigmas (pt_depth_sigma) the exact half sets it, within a third of that."""
    truth, p = noisy
    rng = np.random.default_rng(3)
    rough = rng.random(len(p.pt_depth)) < 0.5
    biased = dataclasses.replace(p, pt_depth=np.where(rough, 1.05 * p.pt_depth, p.pt_depth),
                                 rel_zeta=np.zeros_like(p.rel_zeta))

    def scale_error(problem: BAProblem) -> float:
        T = optimize(problem, BackendConfig(iterations=10)).T_world_cam
        travel = np.linalg.norm(T[-1][:3, 3] - T[0][:3, 3])
        return float(travel / np.linalg.norm(truth.T_world_cam[-1][:3, 3] - truth.T_world_cam[0][:3, 3]) - 1)

    plain = scale_error(biased)
    weighed = scale_error(dataclasses.replace(biased, pt_depth_sigma=np.where(rough, 1.0, np.nan)))
    assert plain > 0.01, plain
    assert abs(weighed) < plain / 3, (plain, weighed)
