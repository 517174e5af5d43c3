"""KITTI devkit metric, ATE and short relative error: known answers and an independent loop implementation; the
heading-aligned reading: a heading offset put into the truth recovered and taken out, a consistent estimate left
alone."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plvo.data.trajectory import read_kitti_poses
from plvo.errors import TrajectoryError
from plvo.geometry import se3
from plvo_eval.kitti_metric import (
    DEVKIT_LENGTHS,
    SHORT_LENGTHS,
    absolute_trajectory_error,
    evaluate,
    evaluate_sequence,
    evaluation_json,
    fit_heading_offset,
    heading_rotation,
    kitti_metric,
    pooled_kitti_metric,
    remove_heading_offset,
    short_relative_error,
    trajectory_distances,
    umeyama,
)


def straight_line(n: int, spacing: float, wobble: float = 0.1) -> np.ndarray:
    """(n,4,4) poses moving along z by `spacing` a frame, the orientation swaying about y (path stays straight)."""
    poses = []
    for k in range(n):
        R = se3.so3_exp(np.array([0.0, wobble * math.sin(0.05 * k), 0.02 * math.cos(0.03 * k)]))
        poses.append(se3.from_rt(R, [0.0, 0.0, spacing * k]))
    return np.stack(poses)


def perturbed(gt: np.ndarray, seed: int, sigma_t: float = 0.02, sigma_r: float = 1e-3) -> np.ndarray:
    """An estimate that drifts: the ground-truth relative motions, each with a small random error."""
    rng = np.random.default_rng(seed)
    est = [gt[0]]
    for k in range(1, len(gt)):
        delta = se3.inv(gt[k - 1]) @ gt[k]
        noise = se3.exp(np.concatenate([rng.normal(0, sigma_t, 3), rng.normal(0, sigma_r, 3)]))
        est.append(est[-1] @ delta @ noise)
    return np.stack(est)


# ------------------------------------------------ a second implementation: a literal, loop-based devkit port


def devkit_reference(gt: np.ndarray, est: np.ndarray, lengths, step: int) -> list[tuple[int, float, float, float]]:
    """calcSequenceErrors of evaluate_odometry.cpp, line by line (float32 distances, general matrix inverses)."""
    dist = [np.float32(0.0)]
    for i in range(1, len(gt)):
        dx = np.float32(gt[i - 1][0, 3] - gt[i][0, 3])
        dy = np.float32(gt[i - 1][1, 3] - gt[i][1, 3])
        dz = np.float32(gt[i - 1][2, 3] - gt[i][2, 3])
        dist.append(np.float32(dist[i - 1] + np.sqrt(dx * dx + dy * dy + dz * dz)))
    errors = []
    for first in range(0, len(gt), step):
        for length in lengths:
            last = -1
            for i in range(first, len(dist)):
                if dist[i] > np.float32(dist[first] + np.float32(length)):
                    last = i
                    break
            if last == -1:
                continue
            delta_gt = np.linalg.inv(gt[first]) @ gt[last]
            delta_est = np.linalg.inv(est[first]) @ est[last]
            err = np.linalg.inv(delta_est) @ delta_gt
            a, b, c = err[0, 0], err[1, 1], err[2, 2]
            r_err = math.acos(max(min(0.5 * (a + b + c - 1.0), 1.0), -1.0))
            t_err = math.sqrt(err[0, 3] ** 2 + err[1, 3] ** 2 + err[2, 3] ** 2)
            errors.append((first, float(length), r_err / length, t_err / length))
    return errors


def _reference_summary(errors, lengths):
    t_all = np.mean([e[3] for e in errors]) * 100.0
    r_all = math.degrees(np.mean([e[2] for e in errors]))
    per = {}
    for length in lengths:
        sel = [e for e in errors if abs(e[1] - length) < 1.0]
        if sel:
            per[length] = (len(sel), np.mean([e[3] for e in sel]) * 100, math.degrees(np.mean([e[2] for e in sel])))
    return t_all, r_all, per


# ------------------------------------------------ known answers


def test_estimate_equal_to_ground_truth_gives_zero():
    gt = perturbed(straight_line(1500, 0.8), seed=3, sigma_t=0.05, sigma_r=5e-3)  # a curvy ground truth
    ev = evaluate_sequence(gt, gt.copy())
    assert ev.kitti.n_segments > 100
    assert ev.kitti.t_err_pct < 1e-9 and ev.kitti.r_err_deg_per_m < 1e-6
    assert ev.short.t_err_pct < 1e-9 and ev.ate_se3.rmse_m < 1e-9 and ev.ate_sim3.rmse_m < 1e-9
    assert ev.ate_sim3.scale == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("s", [0.9, 1.05, 1.3])
def test_constant_scale_gives_one_minus_s(s):
    # 0.1 m a frame: a segment overshoots its nominal length by < 0.1 m, i.e. < 0.1 % of 100 m (< 1 % of 10 m)
    gt = straight_line(9000, 0.1)
    est = gt.copy()
    est[:, :3, 3] *= s
    rel = kitti_metric(gt, est)
    assert rel.n_segments > 0
    assert rel.t_err_pct == pytest.approx(abs(1 - s) * 100, rel=1.5e-3)
    assert rel.r_err_deg_per_m < 1e-9
    for e in rel.per_length:
        if e.n_segments:
            assert e.t_err_pct == pytest.approx(abs(1 - s) * 100, rel=1.5e-3)
    short = short_relative_error(gt, est, (10.0, 20.0))
    assert short.t_err_pct == pytest.approx(abs(1 - s) * 100, rel=1.5e-2)
    assert short.n_segments == len(gt) - 101 + len(gt) - 201  # every frame a start while the path lasts
    ate = absolute_trajectory_error(gt, est, with_scale=True)
    assert ate.scale == pytest.approx(1 / s, rel=1e-9) and ate.rmse_m < 1e-8


def test_rigid_transform_of_the_estimate_changes_nothing():
    gt = perturbed(straight_line(1200, 1.0), seed=1, sigma_t=0.05, sigma_r=4e-3)
    est = perturbed(gt, seed=2)
    T = se3.exp(np.array([12.0, -3.0, 40.0, 0.3, -1.1, 2.0]))
    moved = T @ est
    a, b = evaluate_sequence(gt, est), evaluate_sequence(gt, moved)
    assert a.kitti.t_err_pct > 0.1  # the comparison is not between zeros
    assert b.kitti.t_err_pct == pytest.approx(a.kitti.t_err_pct, rel=1e-9)
    assert b.kitti.r_err_deg_per_m == pytest.approx(a.kitti.r_err_deg_per_m, rel=1e-9)
    assert b.short.t_err_pct == pytest.approx(a.short.t_err_pct, rel=1e-9)
    np.testing.assert_allclose(b.kitti.segments.t_err, a.kitti.segments.t_err, rtol=1e-8)
    assert b.ate_se3.rmse_m == pytest.approx(a.ate_se3.rmse_m, rel=1e-8)
    assert b.ate_sim3.rmse_m == pytest.approx(a.ate_sim3.rmse_m, rel=1e-8)
    # transform then align gives the original alignment back
    np.testing.assert_allclose(b.ate_se3.T_gt_est @ T, a.ate_se3.T_gt_est, atol=1e-8)


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(0, 10, (50, 3))
    R = se3.so3_exp(np.array([0.4, -0.2, 1.5]))
    t, s = np.array([3.0, -1.0, 7.0]), 2.5
    R_hat, t_hat, s_hat = umeyama(src, s * src @ R.T + t, with_scale=True)
    np.testing.assert_allclose(R_hat, R, atol=1e-12)
    np.testing.assert_allclose(t_hat, t, atol=1e-10)
    assert s_hat == pytest.approx(s, rel=1e-12)
    R_hat, t_hat, s_hat = umeyama(src, s * src @ R.T + t, with_scale=False)
    np.testing.assert_allclose(R_hat, R, atol=1e-12)  # a scale does not change the best rotation
    assert s_hat == 1.0  # without scale, none is estimated, though 2.5 would fit


def test_ate_of_a_known_offset_error():
    gt = straight_line(200, 1.0)
    est = gt.copy()
    est[::2, 0, 3] += 0.3  # every other position 0.3 m to the side: the best SE(3) shift is 0.15 m
    ate = absolute_trajectory_error(gt, est)
    assert ate.rmse_m == pytest.approx(0.15, abs=1e-3)
    assert absolute_trajectory_error(gt, est, with_scale=True).rmse_m <= ate.rmse_m + 1e-12


def test_distances_and_errors_on_mismatched_input():
    gt = straight_line(11, 2.0)
    np.testing.assert_allclose(trajectory_distances(gt), np.arange(11) * 2.0)
    assert kitti_metric(gt, gt).n_segments == 0 and math.isnan(kitti_metric(gt, gt).t_err_pct)
    with pytest.raises(TrajectoryError, match="11 poses but the estimate 10"):
        kitti_metric(gt, gt[:10])


def test_pooled_is_the_mean_over_all_segments():
    gt_a, gt_b = straight_line(1500, 0.9), perturbed(straight_line(2500, 0.7), seed=5, sigma_t=0.03)
    est_a, est_b = perturbed(gt_a, seed=6), perturbed(gt_b, seed=7)
    a, b = kitti_metric(gt_a, est_a), kitti_metric(gt_b, est_b)
    pooled = pooled_kitti_metric([(gt_a, est_a), (gt_b, est_b)])
    assert pooled.n_segments == a.n_segments + b.n_segments
    expected = (a.t_err_pct * a.n_segments + b.t_err_pct * b.n_segments) / pooled.n_segments
    assert pooled.t_err_pct == pytest.approx(expected, rel=1e-12)
    ev = evaluate({"a": (gt_a, est_a), "b": (gt_b, est_b)})
    assert [s.name for s in ev.sequences] == ["a", "b"]
    assert ev.kitti.t_err_pct == pytest.approx(pooled.t_err_pct, rel=1e-12)
    assert ev.sequences[1].kitti.t_err_pct == pytest.approx(b.t_err_pct, rel=1e-12)


# ------------------------------------------------ against the loop implementation on real ground truth


@pytest.mark.parametrize("seq", ["03", "04", "10"])
def test_matches_loop_reference_on_real_ground_truth(kitti_root, seq):
    gt = read_kitti_poses(kitti_root / "poses" / f"{seq}.txt")
    est = perturbed(gt, seed=int(seq))
    rel = kitti_metric(gt, est)
    ref = devkit_reference(gt, est, DEVKIT_LENGTHS, step=10)
    assert rel.n_segments == len(ref) > 0
    np.testing.assert_array_equal(rel.segments.first_frame, [e[0] for e in ref])
    np.testing.assert_allclose(rel.segments.t_err, [e[3] for e in ref], rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(rel.segments.r_err, [e[2] for e in ref], rtol=1e-6, atol=1e-12)
    t_all, r_all, per = _reference_summary(ref, DEVKIT_LENGTHS)
    assert rel.t_err_pct == pytest.approx(t_all, rel=1e-7) and rel.r_err_deg_per_m == pytest.approx(r_all, rel=1e-6)
    for e in rel.per_length:
        if e.length_m in per:
            n, t, r = per[e.length_m]
            assert (e.n_segments, e.t_err_pct) == (n, pytest.approx(t, rel=1e-7))
            assert e.r_err_deg_per_m == pytest.approx(r, rel=1e-6)
        else:
            assert e.n_segments == 0


def test_short_and_pooled_match_loop_reference_on_real_ground_truth(kitti_root):
    pairs = []
    for seq in ("04", "03"):
        gt = read_kitti_poses(kitti_root / "poses" / f"{seq}.txt")[:400]
        pairs.append((gt, perturbed(gt, seed=10 + int(seq))))
    ref_short = devkit_reference(*pairs[0], (10.0, 20.0, 40.0), step=1)
    short = short_relative_error(*pairs[0], (10.0, 20.0, 40.0))
    assert short.n_segments == len(ref_short) > 700
    t_all, r_all, _ = _reference_summary(ref_short, (10.0, 20.0, 40.0))
    assert short.t_err_pct == pytest.approx(t_all, rel=1e-7)
    assert short.r_err_deg_per_m == pytest.approx(r_all, rel=1e-6)
    ref_pooled = devkit_reference(*pairs[0], DEVKIT_LENGTHS, 10) + devkit_reference(*pairs[1], DEVKIT_LENGTHS, 10)
    pooled = pooled_kitti_metric(pairs)
    t_all, r_all, _ = _reference_summary(ref_pooled, DEVKIT_LENGTHS)
    assert pooled.n_segments == len(ref_pooled) and pooled.t_err_pct == pytest.approx(t_all, rel=1e-7)


# ------------------------------------------------ the heading-aligned reading

# an estimate of good odometry: 5 mm and 0.1 mrad of zero-mean noise on each 1.2 m step. Over 20 seeds on
# curved_drive(600) its fitted angle against its own truth spread 0.013 deg (at most 0.025), so 0.05 deg bounds it
EST_NOISE = {"sigma_t": 0.005, "sigma_r": 1e-4}
FIT_TOL_DEG = 0.05


def curved_drive(n: int, speed: float = 1.2) -> np.ndarray:
    """(n,4,4) cam0 poses (y down, z ahead) driving `speed` m a frame on level ground, turning left and right."""
    poses, yaw, position = [], 0.0, np.zeros(3)
    for k in range(n):
        R = se3.so3_exp(np.array([0.0, yaw, 0.0]))
        poses.append(se3.from_rt(R, position.copy()))
        position = position + R @ np.array([0.0, 0.0, speed])
        yaw += 0.03 * math.sin(0.02 * k)
    return np.stack(poses)


def with_heading_offset(gt: np.ndarray, offset_deg: float) -> np.ndarray:
    """The truth of a body frame turned by a constant angle about y against the camera's, re-based on frame 0:
    R G R^T (what a truth measured by a mis-aligned GPS/INS gives)."""
    R = se3.from_rt(se3.so3_exp(np.array([0.0, math.radians(offset_deg), 0.0])), np.zeros(3))
    return R @ gt @ R.T


def test_heading_rotation_turns_ahead_to_the_right():
    R = heading_rotation(math.radians(90.0))
    np.testing.assert_allclose(R[:3, :3] @ [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], atol=1e-15)
    est = perturbed(curved_drive(50), seed=0)
    turned = remove_heading_offset(est, 0.4)
    np.testing.assert_allclose(turned[0], np.eye(4), atol=1e-15)  # the first pose stays the identity


def test_a_known_offset_is_fitted_exactly_when_the_estimate_is_the_camera_path():
    gt = curved_drive(600)  # 720 m: short and devkit segments
    shifted = with_heading_offset(gt, 1.0)
    assert math.degrees(fit_heading_offset(shifted, gt)) == pytest.approx(1.0, abs=1e-9)
    ev = evaluate_sequence(shifted, gt)
    assert ev.heading_offset_deg == pytest.approx(1.0, abs=1e-9)
    # the offset alone: a floor of about 1 deg in radians (1.75 %) under every segment, nothing once taken out
    assert 1.6 < ev.short.t_err_pct < 1.8 and 1.0 < ev.kitti.t_err_pct < 1.8  # at most 1.75 % where straight
    assert ev.short_aligned.t_err_pct < 1e-9 and ev.kitti_aligned.t_err_pct < 1e-9
    assert ev.kitti_aligned.r_err_deg_per_m < 1e-6


@pytest.mark.parametrize("offset_deg", [1.0, -0.3])
def test_a_known_offset_in_the_truth_is_recovered_and_taken_out(offset_deg):
    gt = curved_drive(600)
    est = perturbed(gt, seed=11, **EST_NOISE)
    shifted = with_heading_offset(gt, offset_deg)
    ev, clean = evaluate_sequence(shifted, est), evaluate_sequence(gt, est)
    assert ev.heading_offset_deg == pytest.approx(offset_deg, abs=FIT_TOL_DEG)
    # the offset raises the raw errors well above the estimate's own ...
    assert ev.short.t_err_pct > clean.short.t_err_pct + 0.5 * abs(math.radians(offset_deg)) * 100
    # ... and taken out, the errors are those of the same estimate against the offset-free truth, aligned alike
    # (the fit turns with the truth: the two aligned readings are the same up to rounding) ...
    assert ev.heading_offset_deg - clean.heading_offset_deg == pytest.approx(offset_deg, abs=1e-9)
    np.testing.assert_allclose(ev.short_aligned.segments.t_err, clean.short_aligned.segments.t_err, rtol=1e-7)
    np.testing.assert_allclose(ev.kitti_aligned.segments.r_err, clean.kitti_aligned.segments.r_err, rtol=1e-6)
    # ... and as they are (the fit's own noise of a few hundredths of a degree moves them by a few %)
    assert ev.short_aligned.t_err_pct == pytest.approx(clean.short.t_err_pct, rel=0.05)
    assert ev.kitti_aligned.t_err_pct == pytest.approx(clean.kitti.t_err_pct, abs=0.03)
    assert ev.short_aligned.r_err_deg_per_m == pytest.approx(clean.short.r_err_deg_per_m, rel=0.05)
    assert ev.ate_se3.rmse_m == pytest.approx(clean.ate_se3.rmse_m, rel=1e-6)  # ATE aligns anyway


@pytest.mark.parametrize("seed", [21, 22, 23])
def test_a_consistent_estimate_keeps_its_errors(seed):
    gt = curved_drive(600)
    ev = evaluate_sequence(gt, perturbed(gt, seed=seed, **EST_NOISE))
    assert abs(ev.heading_offset_deg) < FIT_TOL_DEG
    # short errors within 5 % (20 seeds: at most 2.3 % lower); the devkit's 0.08 % within 0.03 points (the fitted
    # angle, 0.05 deg = 0.087 % of a segment, bounds how far it can move any segment's error; 20 seeds: 0.01)
    assert ev.short_aligned.t_err_pct == pytest.approx(ev.short.t_err_pct, rel=0.05)
    assert ev.kitti_aligned.t_err_pct == pytest.approx(ev.kitti.t_err_pct, abs=0.03)
    assert ev.kitti_aligned.n_segments == ev.kitti.n_segments > 100


def _brute_force_heading(gt: np.ndarray, est: np.ndarray, parts) -> float:
    """The angle minimising sum |g - R_y(th) e|^2 over the segments of parts [(lengths, step)], found by a bounded
    scalar search on the residual itself; segments enumerated by loops as the devkit does (float32 distances)."""
    from scipy.optimize import minimize_scalar

    dist = [np.float32(0.0)]
    for i in range(1, len(gt)):
        d = (gt[i - 1][:3, 3] - gt[i][:3, 3]).astype(np.float32)
        dist.append(np.float32(dist[-1] + np.sqrt(np.sum(d * d))))
    g, e = [], []
    for lengths, step in parts:
        for first in range(0, len(gt), step):
            for length in lengths:
                last = next((i for i in range(first, len(gt)) if dist[i] > np.float32(dist[first] + length)), None)
                if last is not None:
                    g.append((np.linalg.inv(gt[first]) @ gt[last])[:3, 3] / length)
                    e.append((np.linalg.inv(est[first]) @ est[last])[:3, 3] / length)
    G, E = np.array(g), np.array(e)

    def residual(th: float) -> float:
        return float(np.sum((G - E @ heading_rotation(th)[:3, :3].T) ** 2))

    return float(minimize_scalar(residual, bounds=(-0.1, 0.1), method="bounded", options={"xatol": 1e-10}).x)


def test_fit_is_the_least_squares_turn_over_short_and_devkit_segments():
    gt = curved_drive(600)
    # an estimate that also turns 0.1 mrad a frame too far left: long segments see more of it than short ones,
    # so leaving the devkit segments out of the fit would move the angle
    bias = se3.from_rt(se3.so3_exp(np.array([0.0, -1e-4, 0.0])), np.zeros(3))
    est = gt.copy()
    for k in range(1, len(gt)):
        est[k] = est[k - 1] @ se3.inv(gt[k - 1]) @ gt[k] @ bias
    est = perturbed(est, seed=5, **EST_NOISE)
    shifted = with_heading_offset(gt, 0.5)
    both = _brute_force_heading(shifted, est, [(SHORT_LENGTHS, 1), (DEVKIT_LENGTHS, 10)])
    short_only = _brute_force_heading(shifted, est, [(SHORT_LENGTHS, 1)])
    assert abs(math.degrees(both - short_only)) > 0.01  # the devkit segments do pull the angle
    assert math.degrees(fit_heading_offset(shifted, est)) == pytest.approx(math.degrees(both), abs=1e-6)


def test_pooled_aligned_figures_pool_each_sequence_aligned_by_its_own_angle():
    gt_a, gt_b = curved_drive(400), curved_drive(300, speed=0.9)
    pairs = {"a": (with_heading_offset(gt_a, 0.6), perturbed(gt_a, seed=1, **EST_NOISE)),
             "b": (with_heading_offset(gt_b, -1.2), perturbed(gt_b, seed=2, **EST_NOISE))}
    ev = evaluate(pairs)
    a, b = ev.sequences
    assert a.heading_offset_deg == pytest.approx(0.6, abs=FIT_TOL_DEG)
    assert b.heading_offset_deg == pytest.approx(-1.2, abs=FIT_TOL_DEG)
    for pooled, parts in ((ev.short_aligned, (a.short_aligned, b.short_aligned)),
                          (ev.kitti_aligned, (a.kitti_aligned, b.kitti_aligned))):
        assert pooled.n_segments == sum(p.n_segments for p in parts) > 0
        expected = sum(p.t_err_pct * p.n_segments for p in parts) / pooled.n_segments
        assert pooled.t_err_pct == pytest.approx(expected, rel=1e-12)
    assert ev.short_aligned.t_err_pct < 0.5 * ev.short.t_err_pct  # the offsets were the larger part


def test_evaluation_json_carries_both_readings():
    gt = curved_drive(300)
    ev = evaluate_sequence(with_heading_offset(gt, 0.8), perturbed(gt, seed=3, **EST_NOISE))
    data = evaluation_json(ev)
    assert data["short_t_err_pct"] == pytest.approx(ev.short.t_err_pct)  # the devkit reading keeps its keys
    aligned = data["heading_aligned"]
    assert aligned["heading_offset_deg"] == pytest.approx(0.8, abs=FIT_TOL_DEG)
    assert aligned["short_t_err_pct"] == pytest.approx(ev.short_aligned.t_err_pct)
    assert aligned["t_err_pct"] == pytest.approx(ev.kitti_aligned.t_err_pct)
    assert aligned["short"]["20"]["t_err_pct"] == pytest.approx(ev.short_aligned.per_length[1].t_err_pct)
    assert list(aligned["segments"]) == [f"{v:g}" for v in DEVKIT_LENGTHS]
    assert aligned["short_t_err_pct"] < 0.5 * data["short_t_err_pct"]


def test_no_segment_fits_no_angle():
    gt = straight_line(5, 1.0)  # 4 m: shorter than the shortest segment
    ev = evaluate_sequence(gt, gt.copy())
    assert math.isnan(ev.heading_offset_deg) and ev.short_aligned.n_segments == 0
    assert evaluation_json(ev)["heading_aligned"]["heading_offset_deg"] is None


def test_real_truth_with_a_known_offset(kitti_root):
    """KITTI 04's truth (394 m, nearly straight), turned by a known 0.3 deg, against an estimate made from it."""
    gt = read_kitti_poses(kitti_root / "poses" / "04.txt")
    est = perturbed(gt, seed=4, **EST_NOISE)
    ev, clean = evaluate_sequence(with_heading_offset(gt, 0.3), est), evaluate_sequence(gt, est)
    assert ev.kitti.n_segments > 0  # the devkit segments take part in the fit
    assert ev.heading_offset_deg == pytest.approx(0.3, abs=FIT_TOL_DEG)
    assert ev.short.t_err_pct > clean.short.t_err_pct + 0.25  # 0.3 deg: a floor of ~0.5 %
    assert ev.short_aligned.t_err_pct == pytest.approx(clean.short.t_err_pct, rel=0.05)
    assert ev.kitti_aligned.t_err_pct == pytest.approx(clean.kitti.t_err_pct, abs=0.03)
