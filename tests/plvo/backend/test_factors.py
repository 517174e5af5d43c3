"""Back-end factors: analytic Jacobians against central differences, and the fast solver's cost against gtsam's."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
from backend_costs import costs, perturbed_window

from plvo.backend import bundle_adjustment as ba
from plvo.backend import factors
from plvo.backend.problem import make_synthetic_problem, stereo_row_sigma
from plvo.backend.relpose import relpose_block
from plvo.config import BackendConfig
from plvo.geometry import se3
from plvo.geometry.lines import orth_update, plucker_from_points, plucker_to_orth

K = np.array([[707.0, 0.0, 601.0], [0.0, 707.0, 183.0], [0.0, 0.0, 1.0]])
EPS = 1e-6


def _poses(rng, n):
    return np.stack([se3.exp(np.r_[rng.normal(0, 1, 3), rng.normal(0, 0.1, 3)]) for _ in range(n)])


def _num_pose(f, T_cw, r0_shape):
    J = np.zeros(r0_shape + (6,))
    for a in range(6):
        d = np.zeros(6)
        d[a] = EPS
        plus, minus = np.stack([se3.exp(d) @ T for T in T_cw]), np.stack([se3.exp(-d) @ T for T in T_cw])
        J[..., a] = (f(plus) - f(minus)) / (2 * EPS)
    return J


def _close(J, Jn, rel=1e-5):
    scale = max(np.abs(Jn).max(), 1.0)
    assert np.abs(J - Jn).max() <= rel * scale, (np.abs(J - Jn).max(), scale)


def test_line_block_jacobians_match_central_differences():
    rng = np.random.default_rng(0)
    n = 6
    T_cw = _poses(rng, n)
    P = rng.normal(0, 3, (n, 3)) + [0, 0, 20]
    Q = P + rng.normal(0, 2, (n, 3))
    U, W = plucker_to_orth(plucker_from_points(P, Q))
    seg = rng.uniform(100, 500, (n, 4))
    pri = np.stack([P, Q], 1) + rng.normal(0, 0.3, (n, 2, 3))
    pri_c = np.einsum("nij,nkj->nki", T_cw[:, :3, :3], pri) + T_cw[:, None, :3, 3]
    pri_c[0] = np.nan  # one observation without priors: row 3 must be zero
    r, Jp, Jl = ba.line_block(K, T_cw, U, W, seg, pri_c, 1.0)
    assert r[0, 2] == 0.0 and np.all(Jp[0, 2] == 0) and np.all(Jl[0, 2] == 0)
    _close(Jp, _num_pose(lambda T: ba.line_block(K, T, U, W, seg, pri_c, 1.0)[0], T_cw, r.shape))
    for a in range(4):
        d = np.zeros((n, 4))
        d[:, a] = EPS
        num = (ba.line_block(K, T_cw, *orth_update(U, W, d), seg, pri_c, 1.0)[0]
               - ba.line_block(K, T_cw, *orth_update(U, W, -d), seg, pri_c, 1.0)[0]) / (2 * EPS)
        _close(Jl[:, :, a], num, rel=1e-4)


def test_point_block_jacobians_mono_and_stereo():
    rng = np.random.default_rng(1)
    n = 8
    T_cw = _poses(rng, n)
    X = np.einsum("nji,nj->ni", T_cw[:, :3, :3], rng.normal(0, 2, (n, 3)) + [0, 0, 15] - T_cw[:, :3, 3])
    uv = rng.uniform(0, 500, (n, 2))
    depth = np.where(np.arange(n) % 2 == 0, 12.0, np.nan)
    r, Jp, Jx = ba.point_block(K, T_cw, X, uv, depth, 0.54, 0.5)
    assert np.all(r[1::2, 2] == 0)  # mono rows
    _close(Jp, _num_pose(lambda T: ba.point_block(K, T, X, uv, depth, 0.54, 0.5)[0], T_cw, r.shape))
    for a in range(3):
        d = np.zeros(3)
        d[a] = EPS
        num = (ba.point_block(K, T_cw, X + d, uv, depth, 0.54, 0.5)[0]
               - ba.point_block(K, T_cw, X - d, uv, depth, 0.54, 0.5)[0]) / (2 * EPS)
        _close(Jx[:, :, a], num)


def test_relpose_block_jacobians():
    rng = np.random.default_rng(2)
    n = 4
    Ti, Tj = _poses(rng, n), _poses(rng, n)
    meas = np.stack([Ti[a] @ se3.inv(Tj[a]) @ se3.exp(rng.normal(0, 0.03, 6)) for a in range(n)])
    zeta = np.array([1.0, 0.5, 2.0, 1e-3])
    r, Ji, Jj = relpose_block(Ti, Tj, meas, zeta)
    # Jr^-1(r) ~ I + ad(r)/2 is exact to second order in |r| ~ 0.05: relative error ~1e-3.
    _close(Ji, _num_pose(lambda T: relpose_block(T, Tj, meas, zeta)[0], Ti, r.shape), rel=2e-3)
    _close(Jj, _num_pose(lambda T: relpose_block(Ti, T, meas, zeta)[0], Tj, r.shape), rel=2e-3)


def test_gtsam_line_factor_jacobians_match_numeric():
    rng = np.random.default_rng(3)
    T_wc = [se3.exp(np.r_[rng.normal(0, 0.5, 3), rng.normal(0, 0.05, 3)]) for _ in range(3)]
    P, Q = np.array([1.0, -1.0, 15.0]), np.array([3.0, 0.5, 18.0])
    U0, W0 = plucker_to_orth(plucker_from_points(P, Q))
    segs = rng.uniform(100, 500, (3, 4))
    pri = np.full((3, 2, 3), np.nan)
    pri[1] = se3.transform_points(se3.inv(T_wc[1]), np.stack([P, Q]) + 0.2)
    obs = factors.LineObservations(kf=np.arange(3), segments=segs, priors=pri)
    keys = [factors.X(k) for k in range(3)]
    f = factors.make_line_factor(K, keys, factors.L(0), U0, W0, obs, gtsam.noiseModel.Unit.Create(obs.dim))
    values = gtsam.Values()
    for k in range(3):
        values.insert(keys[k], gtsam.Pose3(T_wc[k]))
    values.insert(factors.L(0), np.array([0.02, -0.01, 0.03, 0.05]))
    lin = f.linearize(values)
    A = lin.jacobian()[0]  # whitened by the unit model: the raw Jacobian, columns in key order
    cols = []
    for k, key in enumerate(f.keys()):
        dim = 6 if k < 3 else 4
        for a in range(dim):
            d = np.zeros(dim)
            d[a] = EPS

            def err(delta, k=k, key=key):
                v = gtsam.Values(values)
                if k < 3:
                    v.update(key, values.atPose3(key).retract(delta))
                else:
                    v.update(key, values.atVector(key) + delta)
                return f.unwhitenedError(v)

            cols.append((err(d) - err(-d)) / (2 * EPS))
    num = np.stack(cols, axis=1)
    assert A.shape == num.shape
    _close(A, num, rel=1e-4)


def test_fast_solver_cost_equals_gtsam_graph_error():
    p = perturbed_window()
    # gtsam's robust model acts per line, ours per observation
    ours, theirs, ln_ok = costs(p, BackendConfig(huber_point=1e6, huber_line=1e6))
    assert ln_ok.sum() >= 5 and ours > 1.0
    assert abs(ours - theirs) <= 1e-6 * ours
    # and with the robust kernels on, point and relative-pose factors still agree one to one (no lines)
    ours, theirs, _ = costs(p, BackendConfig(), use_lines=False)
    assert abs(ours - theirs) <= 1e-6 * ours


def test_relpose_batch_helpers_match_scalar_se3_and_weights_scale_rows():
    from plvo.backend import relpose

    rng = np.random.default_rng(5)
    xis = [rng.normal(0, 1, 6), rng.normal(0, 1e-5, 6), np.r_[0.3, -0.2, 0.1, 0.0, 0.0, np.pi - 1e-4], np.zeros(6)]
    T = np.stack([se3.exp(x) for x in xis])
    L = relpose.log_batch(T)
    for k in range(len(T)):
        np.testing.assert_allclose(L[k], se3.log(T[k]), atol=1e-9)
        np.testing.assert_allclose(se3.inv_batch(T)[k], se3.inv(T[k]), atol=1e-12)
        np.testing.assert_allclose(relpose.adjoint_batch(T)[k], se3.adjoint(T[k]), atol=1e-12)
    Ti, Tj = T[:2], T[2:]
    meas = np.stack([se3.exp(rng.normal(0, 0.1, 6)) for _ in range(2)])
    w = np.r_[4.0, 4.0, 4.0, 100.0, 100.0, 100.0]
    r1, Ji1, Jj1 = relpose_block(Ti, Tj, meas, np.array([1.0, 0.5]))
    r2, Ji2, Jj2 = relpose_block(Ti, Tj, meas, np.array([1.0, 0.5]), w)
    np.testing.assert_allclose(r2, r1 * np.sqrt(w), rtol=1e-12)
    np.testing.assert_allclose(Ji2, Ji1 * np.sqrt(w)[:, None], rtol=1e-12)
    np.testing.assert_allclose(Jj2, Jj1 * np.sqrt(w)[:, None], rtol=1e-12)


def test_trial_steps_are_priced_without_jacobians_which_come_later_the_same():
    """The LM prices a trial step from its residuals alone and computes the Jacobians only of a step it accepts,
    from what the residuals were computed from: residuals and Jacobians of every block (priors on half the line
    observations, relative-pose factors) must be those of the blocks computed at once, to the last bit; and the
    normal equations assembled with the row plan of an earlier state must be those assembled without one."""
    truth = make_synthetic_problem(n_kf=5, n_points=80, n_lines=20, seed=7, prior_fraction=0.5, pixel_noise=0.5)
    rng = np.random.default_rng(7)
    T = truth.T_world_cam.copy()
    for k in range(1, 5):
        T[k] = T[k] @ se3.exp(rng.normal(0, 0.02, 6))
    p = dataclasses.replace(truth, T_world_cam=T, points=truth.points + rng.normal(0, 0.1, truth.points.shape),
                            rel_zeta=np.full(4, 0.6))
    cfg, baseline = BackendConfig(), factors.DEFAULT_STEREO_BASELINE_M
    pt_ok, ln_ok = factors.usable_landmarks(p)
    lay, sel = ba._Layout(p, pt_ok, ln_ok), ba._select(p, pt_ok, ln_ok, True)
    sel["origin"] = rng.normal(0, 1.0, (p.n_lines, 3))
    U, W = plucker_to_orth(plucker_from_points(p.lines[:, 0] - sel["origin"], p.lines[:, 1] - sel["origin"]))
    T_cw = np.stack([se3.inv(t) for t in p.T_world_cam])
    blocks = ba._evaluate(p, T_cw, p.points, U, W, lay, sel, cfg, baseline)
    assert len(blocks.items) == 3 and not blocks._terms  # residuals only, so far
    assert np.isfinite(p.ln_prior).any() and ln_ok.sum() >= 5
    o = sel["pt"]
    at_once = [ba.point_block(p.K, T_cw[p.pt_kf[o]], p.points[p.pt_idx[o]], p.pt_uv[o], sel["depth"], baseline,
                              cfg.sigma_point_px)]
    o = sel["ln"]
    j = p.ln_idx[o]
    T_cl = T_cw[p.ln_kf[o]].copy()
    T_cl[:, :3, 3] += np.einsum("nij,nj->ni", T_cl[:, :3, :3], sel["origin"][j])
    at_once.append(ba.line_block(p.K, T_cl, U[j], W[j], p.ln_seg[o], sel["prior"], cfg.sigma_line))
    o = sel["rel"]
    at_once.append(relpose_block(T_cw[p.rel_ij[o, 0]], T_cw[p.rel_ij[o, 1]], p.rel_T[o], p.rel_zeta[o],
                                 p.rel_weight))
    for b, ((r, _, _), (r1, Ja, Jb)) in enumerate(zip(blocks.items, at_once)):
        np.testing.assert_array_equal(r, r1)
        (_, Ja_later), (_, Jb_later) = blocks.terms(b)
        np.testing.assert_array_equal(Ja_later, Ja)
        np.testing.assert_array_equal(Jb_later, Jb)
    assert blocks.terms(0) is blocks.terms(0)  # computed once
    # the prior rows reuse the camera-frame lines of the reprojection rows: the same bits as computed apart
    has = np.all(np.isfinite(sel["prior"].reshape(len(j), 6)), axis=1)
    assert 0 < has.sum() < len(j)
    d, jp, jl = factors.prior_distance_and_jacobians(T_cl[has], U[j][has], W[j][has], sel["prior"][has])
    r_line, Jp_line, Jl_line = at_once[1]
    np.testing.assert_array_equal(r_line[has, 2], d / cfg.sigma_line)
    np.testing.assert_array_equal(Jp_line[has, 2], jp / cfg.sigma_line)
    np.testing.assert_array_equal(Jl_line[has, 2], jl / cfg.sigma_line)
    plan: dict = {}
    blocks.normal_equations(lay, plan)
    assert plan
    moved = (T_cw.copy(), p.points + rng.normal(0, 0.05, p.points.shape), U, W)
    moved[0][1:] = np.stack([se3.exp(rng.normal(0, 0.01, 6)) @ t for t in T_cw[1:]])
    planned = ba._evaluate(p, *moved, lay, sel, cfg, baseline).normal_equations(lay, plan)
    fresh = ba._evaluate(p, *moved, lay, sel, cfg, baseline).normal_equations(lay)
    for part in ("Hpp", "Hpl", "Hpt", "Hln", "g"):
        np.testing.assert_array_equal(getattr(planned, part), getattr(fresh, part))
    assert np.abs(fresh.Hpl).max() > 0 and np.abs(fresh.Hln).max() > 0


def test_weighed_depth_priors_cost_the_same_both_ways_and_widen_only_the_stereo_row():
    """Depth priors with their own sigmas (pt_depth_sigma): the fast solver's cost equals gtsam's graph's, with the
    robust kernels on and off; the u_R row's sigma is sqrt(s^2 + (fx b sigma_z / z^2)^2) and the other rows' s."""
    p = perturbed_window()
    rng = np.random.default_rng(2)
    sig = np.where(rng.random(len(p.pt_depth)) < 0.5, rng.uniform(0.05, 0.6, len(p.pt_depth)), np.nan)
    w = dataclasses.replace(p, pt_depth_sigma=sig)
    assert np.isfinite(w.pt_depth[np.isfinite(sig)]).sum() >= 10  # some priors are weighed
    for cfg in (BackendConfig(huber_point=1e6, huber_line=1e6), BackendConfig()):
        ours, theirs, _ = costs(w, cfg, use_lines=False)
        assert abs(ours - theirs) <= 1e-6 * ours
        plain, _, _ = costs(p, cfg, use_lines=False)
        assert ours < plain  # the weighed rows count less
    fx = K[0, 0]
    s_r = stereo_row_sigma(fx, 0.54, np.array([10.0, 20.0, np.nan]), 0.1, np.array([0.2, 0.2, 0.2]))
    np.testing.assert_allclose(s_r, np.hypot(0.1, fx * 0.54 * 0.2 / np.array([100.0, 400.0, np.inf])))
    T_cw = _poses(rng, 3)
    X = np.einsum("nji,nj->ni", T_cw[:, :3, :3], rng.normal(0, 2, (3, 3)) + [0, 0, 15] - T_cw[:, :3, 3])
    uv = rng.uniform(0, 500, (3, 2))
    depth = np.array([10.0, 20.0, 12.0])
    r0, later0 = ba.point_residuals(K, T_cw, X, uv, depth, 0.54, 0.1)
    r1, later1 = ba.point_residuals(K, T_cw, X, uv, depth, 0.54, 0.1, np.array([0.2, 0.2, np.nan]))
    np.testing.assert_allclose(r1[:, :2], r0[:, :2])
    np.testing.assert_allclose(r1[:, 2], r0[:, 2] * 0.1 / np.r_[s_r[:2], 0.1])
    np.testing.assert_allclose(later1()[0][:, 2], later0()[0][:, 2] * (0.1 / np.r_[s_r[:2], 0.1])[:, None])
