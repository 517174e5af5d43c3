"""Scale correction (paper II-D): the registration factor pulls a newest keyframe with scaled translation back."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from plvo.backend.problem import make_synthetic_problem
from plvo.backend.scale_correction import correct_scale, scale_factor, scale_problem
from plvo.config import BackendConfig
from plvo.geometry import se3


@pytest.fixture(scope="module")
def scaled():
    """Two keyframes, no depth priors: the monocular scale is unobservable, and the wrong-scale start (newest
    translation x0.8, landmarks scaled about the first camera) reprojects exactly, so only the relative-pose
    factor can move it. (Two-view lines without priors carry no pose information and are left out.)"""
    truth = make_synthetic_problem(n_kf=2, n_points=200, n_lines=50, seed=3, prior_fraction=0.0)
    T = truth.T_world_cam.copy()
    rel = se3.inv(T[0]) @ T[1]
    rel[:3, 3] *= 0.8
    T[1] = T[0] @ rel
    c0 = T[0][:3, 3]
    p = dataclasses.replace(truth, T_world_cam=T, points=c0 + 0.8 * (truth.points - c0),
                            lines=c0 + 0.8 * (truth.lines - c0))
    return truth, p


@pytest.mark.parametrize("zeta", [1.0, 1e-3])
def test_registration_factor_restores_scale(scaled, zeta):
    truth, p = scaled
    # 10 iterations, not the default 5: at information 1e-3 (a million times below what the System's factors carry)
    # LM needs 7 to walk the unobservable scale direction; the optimum is what this test is about
    res = correct_scale(dataclasses.replace(p, rel_zeta=np.full(len(p.rel_zeta), zeta)), newest_kf=1,
                        cfg=BackendConfig(iterations=10))
    s = scale_factor(truth.T_world_cam[1], res.T_world_cam[1], p.T_world_cam[0])
    assert abs(s - 1.0) < 0.01, s
    assert np.linalg.norm(res.T_world_cam[1][:3, 3] - truth.T_world_cam[1][:3, 3]) < 0.01
    assert np.array_equal(res.T_world_cam[0], p.T_world_cam[0])  # older keyframe held fixed
    u = res.point_used
    assert u.sum() > 100
    assert np.median(np.linalg.norm(res.points[u] - truth.points[u], axis=1)) < 0.05  # landmarks rescaled too


def test_without_the_factor_the_scale_stays_wrong(scaled):
    truth, p = scaled
    res = correct_scale(dataclasses.replace(p, rel_zeta=np.zeros(len(p.rel_zeta))), newest_kf=1)
    assert abs(scale_factor(truth.T_world_cam[1], res.T_world_cam[1], p.T_world_cam[0]) - 0.8) < 0.01


def test_scale_problem_frees_only_the_newest_and_its_landmarks():
    truth = make_synthetic_problem(n_kf=5, n_points=100, n_lines=20, seed=4)
    sub = scale_problem(truth, 4)
    assert sub.fixed.tolist() == [True, True, True, True, False]
    seen = set(truth.pt_idx[truth.pt_kf == 4].tolist())
    assert set(sub.pt_idx.tolist()) == seen
    assert len(sub.pt_kf) == int(np.isin(truth.pt_idx, list(seen)).sum())  # all their observations kept
    assert sub.rel_ij.tolist() == [[3, 4]]


@pytest.mark.parametrize("concurrent", [True, False])
def test_scale_corrected_keyframe_is_where_the_adjustment_starts(synth_sequence_factory, monkeypatch, concurrent):
    """Paper II-D: the scale is corrected before the keyframe reaches the bundle adjustment: the adjustment starts
    from the scale correction's pose of the newest keyframe, inline and in a concurrent worker (a thread here, so
    that the spies see it; the worker process runs the same core)."""
    import plvo.backend.worker as worker
    from plvo.config import SystemConfig, merge
    from plvo.data.kitti import KittiOdometry
    from plvo.runtime.run import run_dataset

    events: list[tuple[str, np.ndarray]] = []
    correct, optimize = worker.correct_scale, worker.optimize

    def spy_scale(problem, newest, *args, **kwargs):
        res = correct(problem, newest, *args, **kwargs)
        events.append(("scale", res.T_world_cam[newest].copy()))
        return res

    def spy_ba(problem, *args, **kwargs):
        events.append(("ba", problem.T_world_cam[-1].copy()))
        return optimize(problem, *args, **kwargs)

    monkeypatch.setattr(worker, "correct_scale", spy_scale)
    monkeypatch.setattr(worker, "optimize", spy_ba)
    ds = KittiOdometry(synth_sequence_factory(16, seed=0), "00")
    cfg = merge(SystemConfig(), {"backend": {"concurrent": concurrent, "executor": "thread"},
                                 "loop": {"enabled": False}})
    run_dataset(ds, cfg)
    bas = [n for n, (kind, _) in enumerate(events) if kind == "ba"]
    assert len(bas) >= 3
    for n in bas[1:]:  # the first window has no registration yet
        assert events[n - 1][0] == "scale" and np.array_equal(events[n - 1][1], events[n][1])
