"""A registration's rotation and translation weighed apart by its residual (backend.relative_rotation_residual_power):
the weights, the per-factor rows through both solvers, and a window whose lidar rotation is kept while its
translation gives way to the camera."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from backend_costs import costs, perturbed_window

from plvo.backend.bundle_adjustment import optimize
from plvo.backend.problem import make_synthetic_problem
from plvo.backend.scale_correction import scale_problem
from plvo.backend.worker import edge_information, registration_edge, residual_weight
from plvo.config import BackendConfig
from plvo.geometry import se3


def _base(b: BackendConfig) -> np.ndarray:
    return np.r_[np.full(3, b.sigma_relative_pose ** -2), np.full(3, np.radians(b.sigma_relative_rotation_deg) ** -2)]


def test_a_rough_alignment_loosens_its_translation_more_than_its_rotation():
    b = BackendConfig(relative_pose_residual_m=0.04, relative_pose_residual_power=3.0,
                      relative_rotation_residual_power=1.0)
    edge = registration_edge(0, 1, np.eye(4), 0.9, 0.08, b)  # twice the reference residual
    assert edge.weight == pytest.approx(2.0 ** -6) and edge.rotation_weight == pytest.approx(2.0 ** -2)
    assert edge.information == pytest.approx(0.9 * 2.0 ** -6)
    assert edge.zeta * edge.rotation_weight == pytest.approx(0.9 / 4) and edge.rotation_ratio == pytest.approx(16)
    rows = edge_information([edge, registration_edge(1, 2, np.eye(4), 1.0, 0.04, b)], b)
    # beside zeta * weight, the rotation rows carry rotation_weight / weight: 16x for the rough one, 1 at the reference
    np.testing.assert_allclose(rows[0], _base(b) * np.r_[1, 1, 1, 16, 16, 16])
    np.testing.assert_allclose(rows[1], _base(b))
    # an unknown residual (a failed alignment) weighs 1 both ways
    assert residual_weight(float("nan"), b, 1.0) == 1.0 and residual_weight(0.08, b, 0.0) == 1.0


def test_equal_powers_give_the_shared_weights_bit_for_bit():
    b = BackendConfig(relative_pose_residual_power=3.0, relative_rotation_residual_power=3.0)
    edges = [registration_edge(k, k + 1, np.eye(4), 1.0, e, b) for k, e in enumerate((0.03, 0.07, 0.2, np.nan))]
    rows = edge_information(edges, b)
    assert np.array_equal(rows, np.tile(_base(b), (len(edges), 1)))


def test_per_factor_rows_cost_the_same_in_the_fast_solver_and_in_gtsam():
    # large enough for the relative-pose factors to weigh beside the reprojections
    rows = 1e8 * np.array([[1, 1, 1, 1, 1, 1], [2, 2, 2, 50, 50, 50], [0.1, 0.1, 0.1, 7, 7, 7]], float)
    p = dataclasses.replace(perturbed_window(), rel_weight=rows)
    cfg = BackendConfig(huber_point=1e6, huber_line=1e6)
    ours, theirs, _ = costs(p, cfg, use_lines=False)
    assert abs(ours - theirs) <= 1e-6 * ours
    # the rows matter: the same problem with shared unit weights costs something else
    other, _, _ = costs(dataclasses.replace(p, rel_weight=np.full(6, 1e8)), cfg, use_lines=False)
    assert abs(other - ours) > 0.1 * ours
    # the scale correction's problem keeps the rows of the newest keyframe's factors
    sp = scale_problem(p, 3)
    np.testing.assert_array_equal(sp.rel_weight, rows[np.any(p.rel_ij == 3, axis=1)])


def _relative(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Yaw (about the camera's y, deg) and translation of each consecutive pair."""
    rel = np.stack([se3.inv(T[k]) @ T[k + 1] for k in range(len(T) - 1)])
    return np.degrees(np.arctan2(rel[:, 0, 2], rel[:, 2, 2])), rel[:, :3, 3]


def test_a_window_keeps_the_lidar_rotation_and_takes_the_camera_translation():
    """Relative-pose factors 0.3 deg off in yaw and 0.3 m off sideways against exact images: with a tight rotation
    and a loose translation per factor, the adjusted relative yaws are the factors' and the translations are what
    the images make of them, whatever the factors' translations say; with both loose (the shared weights of a rough
    alignment) both are the images'."""
    truth = make_synthetic_problem(n_kf=5, n_points=250, n_lines=40, seed=3, prior_fraction=0.5)
    true_yaw, true_t = _relative(truth.T_world_cam)
    cfg = BackendConfig(iterations=10, outlier_px=0.0)

    def adjusted(weights: np.ndarray, sideways_m: float) -> tuple[np.ndarray, np.ndarray]:
        bias = se3.from_rt(se3.so3_exp(np.r_[0.0, np.radians(0.3), 0.0]), np.r_[sideways_m, 0.0, 0.0])
        rel_T = np.stack([t @ bias for t in truth.rel_T])
        p = dataclasses.replace(truth, rel_T=rel_T, rel_weight=np.tile(weights, (len(rel_T), 1)))
        return _relative(optimize(p, cfg).T_world_cam)

    loose = np.full(6, 1e-4)
    yaw, t = adjusted(loose, 0.3)
    assert np.abs(yaw - true_yaw).max() < 0.01 and np.abs(t - true_t).max() < 0.005
    split = np.r_[np.full(3, 1e-4), np.full(3, 1e14)]  # the rotation far above 250 points' 0.1 px factors
    yaw, t = adjusted(split, 0.3)
    np.testing.assert_allclose(yaw - true_yaw, 0.3, atol=0.01)
    _, t_exact = adjusted(split, 0.0)
    assert np.abs(t - t_exact).max() < 0.005  # the factors' translation, 0.3 m off, does not pull
