"""Factors of the point-line bundle adjustment (paper II-E) for gtsam 4.3.

Keyframe poses are gtsam Pose3 values T_world_cam (gtsam perturbs them on the right, T <- T Exp(omega, v)).
Points are Point3 in the world. gtsam has no 3D line type in Python, so a line is a Vector4 `phi` read as a
chart of the orthonormal representation around an anchor (U0, W0) fixed for one optimisation:
(U, W) = orth_update(U0, W0, phi), i.e. U = U0 Exp(phi[:3]), W = W0 R2(phi[3]). Vector4 retraction is addition,
so the optimiser's step is the paper's minimal 4-dof update; the chart Jacobian (the SO(3) right Jacobian) is
applied so that the Jacobians are exact and not only right at phi = 0.

Point factors: gtsam's GenericStereoFactor3D when the observation has a lidar depth prior z (ORB-SLAM2's
RGB-D trick: a virtual right image u_R = u_L - fx b / z), else GenericProjectionFactorCal3_S2.
Line factors: one CustomFactor per line landmark holding all its observations, vectorised with numpy, so the
Python callback count grows with the number of lines and not of line observations. `build_graph` and
`optimize_gtsam` put a whole BAProblem into gtsam; it is too slow for the budget (timings below), so
bundle_adjustment.py minimises the same cost with its own sparse LM and is tested against this graph.
Residual per observation: the paper's gamma (2 signed endpoint-to-line pixel distances), plus, when the
observation has endpoint priors, the mean distance (metres) of the two priors to the 3D line, both taken in the
observing camera's frame (the priors are measured by that keyframe's lidar scan and move with it).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from plvo.backend.problem import BAProblem, BAResult, stereo_row_sigma
from plvo.config import BackendConfig
from plvo.geometry import se3
from plvo.geometry.line_jacobians import line_residuals_and_jacobians_batch, orth_plucker_jacobian
from plvo.geometry.lines import cross3, hat_batch, orth_to_plucker, orth_update, plucker_from_points, plucker_to_orth

log = logging.getLogger(__name__)

X = gtsam.symbol_shorthand.X  # keyframe poses
P = gtsam.symbol_shorthand.P  # point landmarks
L = gtsam.symbol_shorthand.L  # line landmarks (Vector4 chart)


def pose_jacobian_to_gtsam(J_left: np.ndarray) -> np.ndarray:
    """(...,r,6) Jacobian w.r.t. xi=(rho,phi) of T_cam_world <- exp(xi) T_cam_world -> w.r.t. gtsam's (omega, v).

    T_world_cam <- T_world_cam Exp(omega, v) is T_cam_world <- exp(-(v, omega)) T_cam_world.
    """
    return -np.concatenate([J_left[..., 3:], J_left[..., :3]], axis=-1)


def so3_right_jacobian(phi: np.ndarray) -> np.ndarray:
    """(3,) -> (3,3): Exp(phi + d) = Exp(phi) Exp(Jr(phi) d) to first order."""
    return se3._left_jacobian(-np.asarray(phi, dtype=float))


def line_chart_jacobian(phi: np.ndarray) -> np.ndarray:
    """(4,) chart coordinate -> (4,4) d(delta at the current line)/d(phi)."""
    J = np.eye(4)
    J[:3, :3] = so3_right_jacobian(phi[:3])
    return J


def prior_distance_and_jacobians(
    T_cam_world: np.ndarray, U: np.ndarray, W: np.ndarray, priors_cam: np.ndarray, jacobians: bool = True,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(N,4,4), (N,3,3), (N,2,2), (N,2,3) camera-frame endpoint priors -> mean distance (N,) m, J_pose (N,6),
    J_line (N,4).

    J_pose is w.r.t. the left perturbation xi=(rho,phi) of T_cam_world, J_line w.r.t. the orth_update delta.
    jacobians=False: (distance, None, None).
    """
    dist, later = prior_distance(T_cam_world, U, W, priors_cam)
    return (dist, *later()) if jacobians else (dist, None, None)


def prior_distance(
    T_cam_world: np.ndarray, U: np.ndarray, W: np.ndarray, priors_cam: np.ndarray,
    camera_lines: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, Callable[[], tuple[np.ndarray, np.ndarray]]]:
    """prior_distance_and_jacobians' distance, and a function that gives its (J_pose, J_line) from the quantities
    the distance was computed from (for the bundle adjustment's trial steps, which need the cost alone);
    camera_lines: the lines in the camera frame, (d_c, m_c) (N,3) each, when the caller has them."""
    R, t = T_cam_world[:, :3, :3], T_cam_world[:, :3, 3]
    if camera_lines is None:
        Lw = orth_to_plucker(U, W)
        d_c = np.einsum("nij,nj->ni", R, Lw[:, 3:])
        m_c = np.einsum("nij,nj->ni", R, Lw[:, :3]) + cross3(t, d_c)
    else:
        d_c, m_c = camera_lines
    nd = np.linalg.norm(d_c, axis=1)
    dist = np.zeros(len(R))
    errors = []
    for k in range(2):
        X = priors_cam[:, k]
        e = cross3(X, d_c) - m_c  # (N,3); distance = |e| / |d_c|
        ne = np.linalg.norm(e, axis=1)
        dist += 0.5 * (ne / nd)
        errors.append((X, e, ne))

    def jacobians() -> tuple[np.ndarray, np.ndarray]:
        dL = orth_plucker_jacobian(U, W)
        dmc_dl = R @ dL[:, :3] + hat_batch(t) @ R @ dL[:, 3:]  # (N,3,4)
        ddc_dl = R @ dL[:, 3:]
        # Left pose perturbation: m_c += rho x d_c + phi x m_c, d_c += phi x d_c.
        zero = np.zeros((len(R), 3, 3))
        dmc_dxi = np.concatenate([-hat_batch(d_c), -hat_batch(m_c)], axis=2)
        ddc_dxi = np.concatenate([zero, -hat_batch(d_c)], axis=2)
        J_pose = np.zeros((len(R), 6))
        J_line = np.zeros((len(R), 4))
        for X, e, ne in errors:
            dk = ne / nd
            safe = np.where(ne > 0, ne, 1.0)
            g_e = e / (safe * nd)[:, None]  # d dist / d e
            g_e[ne == 0] = 0.0
            g_d = -(dk / nd**2)[:, None] * d_c  # d dist / d d_c through 1/|d_c|
            # e = X x d_c - m_c: de/dd_c = [X]x, de/dm_c = -I
            g_dc = np.einsum("ni,nij->nj", g_e, hat_batch(X)) + g_d
            g_mc = -g_e
            J_pose += 0.5 * (np.einsum("ni,nij->nj", g_mc, dmc_dxi) + np.einsum("ni,nij->nj", g_dc, ddc_dxi))
            J_line += 0.5 * (np.einsum("ni,nij->nj", g_mc, dmc_dl) + np.einsum("ni,nij->nj", g_dc, ddc_dl))
        return J_pose, J_line

    return dist, jacobians


@dataclass(frozen=True)
class LineObservations:
    """All observations of one line landmark: kf (N,) keyframe index, segments (N,4) px, priors (N,2,3) camera
    frame of each observing keyframe (NaN where none)."""

    kf: np.ndarray
    segments: np.ndarray
    priors: np.ndarray

    @property
    def has_prior(self) -> np.ndarray:
        return np.all(np.isfinite(self.priors.reshape(len(self.kf), 6)), axis=1)

    @property
    def dim(self) -> int:
        return int(2 * len(self.kf) + np.count_nonzero(self.has_prior))


def line_residuals(
    K: np.ndarray,
    T_world_cam: np.ndarray,
    U: np.ndarray,
    W: np.ndarray,
    obs: LineObservations,
    want_jacobians: bool = True,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(3,3), (N,4,4) poses of the observing kfs, (3,3),(2,2) world line -> r (D,), J_pose (D,N,6) gtsam order,
    J_line (D,4).

    Rows: 2 per observation (gamma, px), then one per observation with priors (mean prior distance, m).
    J_pose[:, n] is the Jacobian w.r.t. the n-th observation's pose; J_line w.r.t. the orth_update delta.
    """
    n = len(obs.kf)
    T_cw = np.linalg.inv(T_world_cam)
    Ub, Wb = np.broadcast_to(U, (n, 3, 3)), np.broadcast_to(W, (n, 2, 2))
    r, Jp, Jl = line_residuals_and_jacobians_batch(K, T_cw, Ub, Wb, obs.segments)
    has = obs.has_prior
    res = [r.reshape(-1)]
    if np.any(has):
        dist, Jpd, Jld = prior_distance_and_jacobians(T_cw[has], Ub[has], Wb[has], obs.priors[has])
        res.append(dist)
    if not want_jacobians:
        return np.concatenate(res), None, None
    assert Jp is not None and Jl is not None  # the batch forms compute them by default
    D = 2 * n + int(np.count_nonzero(has))
    J_pose = np.zeros((D, n, 6))
    idx = np.arange(n)
    J_pose[2 * idx, idx] = pose_jacobian_to_gtsam(Jp[:, 0])
    J_pose[2 * idx + 1, idx] = pose_jacobian_to_gtsam(Jp[:, 1])
    J_line = [Jl.reshape(-1, 4)]
    if np.any(has):
        rows = 2 * n + np.arange(int(np.count_nonzero(has)))
        assert Jpd is not None and Jld is not None
        J_pose[rows, np.flatnonzero(has)] = pose_jacobian_to_gtsam(Jpd)
        J_line.append(Jld)
    return np.concatenate(res), J_pose, np.concatenate(J_line, axis=0)


def make_line_factor(
    K: np.ndarray,
    pose_keys: list[int],
    line_key: int,
    U0: np.ndarray,
    W0: np.ndarray,
    obs: LineObservations,
    noise: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """One CustomFactor over the distinct poses observing a line and the line's Vector4 chart key.

    pose_keys[n] is the key of the pose of obs.kf[n]; several observations may share a key only if they are of
    the same keyframe (not expected).
    """
    uniq_keys = list(dict.fromkeys(pose_keys))
    col = np.array([uniq_keys.index(k) for k in pose_keys])
    keys = uniq_keys + [line_key]
    K = np.asarray(K, dtype=float)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        T = np.stack([values.atPose3(k).matrix() for k in pose_keys])
        phi = values.atVector(line_key)
        U, W = orth_update(U0, W0, phi)
        r, Jp, Jl = line_residuals(K, T, U, W, obs, want_jacobians=H is not None)
        if H is not None:
            assert Jp is not None and Jl is not None
            for u in range(len(uniq_keys)):
                H[u] = Jp[:, col == u].sum(axis=1)
            H[len(uniq_keys)] = Jl @ line_chart_jacobian(phi)
        return r

    return gtsam.CustomFactor(noise, keys, error)


# --- the whole problem as a gtsam graph -------------------------------------------------------------------------
# Measured (8 keyframes, 1000 points, 150 lines, 7300 point and 1100 line observations, this 2-core machine):
# building the graph 60-100 ms, one LM iteration 0.3 s without lines and 1.0 s with them (a line CustomFactor
# costs about 1.4 ms a linearisation in Python), a full solve 1-13 s: far over the 150 ms budget. So
# bundle_adjustment.optimize solves the same cost with its own vectorised sparse LM; this graph stays as the
# definition that solver is tested against (equal costs at equal values) and as a slow reference solver.
DEFAULT_STEREO_BASELINE_M = 0.54  # KITTI's stereo baseline; the virtual baseline only sets disparity units


def usable_landmarks(problem: BAProblem, use_depth_priors: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """-> (P,) bool points and (L,) bool lines that the observations determine."""
    # A point seen by one keyframe only, even with a depth prior, is exactly determined by that observation (3
    # residuals, 3 dof): it tells the poses nothing. On sequence 04 nine in ten points of a window are such; they
    # are left out (bundle_adjustment.optimize moves them rigidly with their keyframe).
    n_obs = np.bincount(problem.pt_idx, minlength=problem.n_points)
    pt_ok = n_obs >= 2
    # A line seen twice without priors is exactly determined (4 residuals, 4 dof): it tells the poses nothing
    # and, near its epipolar plane, only slows LM down; it needs a third view or an endpoint prior.
    n_ln = np.bincount(problem.ln_idx, minlength=problem.n_lines)
    ln_prior = (np.all(np.isfinite(problem.ln_prior.reshape(-1, 6)), axis=1) if use_depth_priors
                else np.zeros(len(problem.ln_idx), bool))
    n_lp = np.bincount(problem.ln_idx[ln_prior], minlength=problem.n_lines)
    length = np.linalg.norm(problem.lines[:, 1] - problem.lines[:, 0], axis=1)
    sound = np.isfinite(length) & (length > 1e-6)  # a collapsed segment has no direction (seen on synthetic runs)
    ln_ok = ((n_ln >= 3) | ((n_ln >= 2) & (n_lp >= 1))) & sound
    return pt_ok, ln_ok


def _robust(base: gtsam.noiseModel.Base, huber_px: float, sigma: float) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_px / sigma), base)


def _add_points(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, problem: BAProblem, cfg: BackendConfig,
                pt_ok: np.ndarray, use_depth_priors: bool, baseline: float) -> None:
    K = problem.K
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    cal = gtsam.Cal3_S2(fx, fy, 0.0, cx, cy)
    cal_st = gtsam.Cal3_S2Stereo(fx, fy, 0.0, cx, cy, baseline)
    s = cfg.sigma_point_px
    mono = _robust(gtsam.noiseModel.Isotropic.Sigma(2, s), cfg.huber_point, s)
    stereo = _robust(gtsam.noiseModel.Isotropic.Sigma(3, s), cfg.huber_point, s)
    for i in np.flatnonzero(pt_ok):
        values.insert(P(int(i)), problem.points[i].astype(float))
    sigmas = problem.depth_sigmas()
    s_right = np.full(len(problem.pt_depth), s) if sigmas is None else \
        stereo_row_sigma(fx, baseline, problem.pt_depth, s, sigmas)
    for k, i, uv, z, s_r in zip(problem.pt_kf, problem.pt_idx, problem.pt_uv, problem.pt_depth, s_right):
        if not pt_ok[i]:
            continue
        if use_depth_priors and np.isfinite(z) and z > 0:
            meas = gtsam.StereoPoint2(uv[0], uv[0] - fx * baseline / z, uv[1])
            noise = stereo if s_r == s else _robust(gtsam.noiseModel.Diagonal.Sigmas(np.array([s, s_r, s])),
                                                    cfg.huber_point, s)
            graph.add(gtsam.GenericStereoFactor3D(meas, noise, X(int(k)), P(int(i)), cal_st))
        else:
            graph.add(gtsam.GenericProjectionFactorCal3_S2(uv.astype(float), mono, X(int(k)), P(int(i)), cal))


def _add_lines(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, problem: BAProblem, cfg: BackendConfig,
               ln_ok: np.ndarray, use_depth_priors: bool) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    anchors: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    order = np.argsort(problem.ln_idx, kind="stable")
    idx_sorted = problem.ln_idx[order]
    starts = np.searchsorted(idx_sorted, np.arange(problem.n_lines + 1))
    for j in np.flatnonzero(ln_ok):
        sel = order[starts[j]:starts[j + 1]]
        priors = problem.ln_prior[sel] if use_depth_priors else np.full((len(sel), 2, 3), np.nan)
        obs = LineObservations(kf=problem.ln_kf[sel], segments=problem.ln_seg[sel].astype(float), priors=priors)
        U0, W0 = plucker_to_orth(plucker_from_points(problem.lines[j, 0], problem.lines[j, 1]))
        anchors[int(j)] = (U0, W0)
        values.insert(L(int(j)), np.zeros(4))
        noise = _robust(gtsam.noiseModel.Isotropic.Sigma(obs.dim, cfg.sigma_line), cfg.huber_line, cfg.sigma_line)
        keys = [X(int(k)) for k in obs.kf]
        graph.add(make_line_factor(problem.K, keys, L(int(j)), U0, W0, obs, noise))
    return anchors


def build_graph(
    problem: BAProblem, cfg: BackendConfig, use_depth_priors: bool = True, use_lines: bool = True,
    stereo_baseline_m: float = DEFAULT_STEREO_BASELINE_M,
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, np.ndarray, np.ndarray, dict]:
    """-> graph, initial values, used points (P,), used lines (L,), line anchors {j: (U0, W0)}."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k in range(problem.n_keyframes):
        pose = gtsam.Pose3(problem.T_world_cam[k])
        values.insert(X(k), pose)
        if problem.fixed[k]:
            graph.add(gtsam.NonlinearEqualityPose3(X(k), pose))
    for r, ((i, j), T_ij, zeta) in enumerate(zip(problem.rel_ij, problem.rel_T, problem.rel_zeta)):
        if zeta > 0 and not (problem.fixed[i] and problem.fixed[j]):
            w = float(zeta) * problem.relative_pose_weights(np.array([r]))[0]
            noise = gtsam.noiseModel.Diagonal.Precisions(np.r_[w[3:], w[:3]])  # gtsam's tangent is (omega, v)
            graph.add(gtsam.BetweenFactorPose3(X(int(i)), X(int(j)), gtsam.Pose3(T_ij), noise))
    pt_ok, ln_ok = usable_landmarks(problem, use_depth_priors)
    if not use_lines:
        ln_ok = np.zeros_like(ln_ok)
    _add_points(graph, values, problem, cfg, pt_ok, use_depth_priors, stereo_baseline_m)
    anchors = _add_lines(graph, values, problem, cfg, ln_ok, use_depth_priors)
    return graph, values, pt_ok, ln_ok, anchors


def _line_endpoints(old: np.ndarray, U: np.ndarray, W: np.ndarray) -> np.ndarray:
    """(2,3) old endpoints, new orthonormal line -> (2,3) the old endpoints' closest points on the new line."""
    Lp = orth_to_plucker(U, W)
    m, d = Lp[:3], Lp[3:]
    d2 = float(d @ d)
    p0 = np.cross(d, m) / d2
    u = d / np.sqrt(d2)
    return p0 + ((old - p0) @ u)[:, None] * u


def extract_result(problem: BAProblem, values: gtsam.Values, pt_ok: np.ndarray, ln_ok: np.ndarray,
                   anchors: dict[int, tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """gtsam values -> poses (K,4,4), points (P,3), line endpoints (L,2,3); unused landmarks unchanged."""
    T = np.stack([values.atPose3(X(k)).matrix() for k in range(problem.n_keyframes)])
    pts = problem.points.astype(float).copy()
    for i in np.flatnonzero(pt_ok):
        pts[i] = values.atPoint3(P(int(i)))
    lines = problem.lines.astype(float).copy()
    for j, (U0, W0) in anchors.items():
        U, W = orth_update(U0, W0, values.atVector(L(j)))
        lines[j] = _line_endpoints(problem.lines[j], U, W)
    return T, pts, lines


def optimize_gtsam(
    problem: BAProblem, cfg: BackendConfig | None = None, *, use_depth_priors: bool = True,
    use_lines: bool = True, stereo_baseline_m: float = DEFAULT_STEREO_BASELINE_M,
) -> BAResult:
    """Reference: the same problem through gtsam's LM (10-100x slower, see module doc); same outputs as `optimize`."""
    cfg = cfg or BackendConfig()
    t0 = time.perf_counter()
    graph, values, pt_ok, ln_ok, anchors = build_graph(problem, cfg, use_depth_priors, use_lines, stereo_baseline_m)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(cfg.iterations))
    params.setRelativeErrorTol(1e-6)
    params.setAbsoluteErrorTol(1e-9)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    initial_cost = float(graph.error(values))
    result = opt.optimize()
    final_cost = float(graph.error(result))
    T, pts, lines = extract_result(problem, result, pt_ok, ln_ok, anchors)
    dt = time.perf_counter() - t0
    log.debug("BA: %d kf, %d pts, %d lines, cost %.4g -> %.4g in %d it, %.1f ms", problem.n_keyframes,
              int(pt_ok.sum()), int(ln_ok.sum()), initial_cost, final_cost, opt.iterations(), 1e3 * dt)
    return BAResult(T_world_cam=T, points=pts, lines=lines, point_used=pt_ok, line_used=ln_ok,
                    initial_cost=initial_cost, final_cost=final_cost, iterations=int(opt.iterations()), time_s=dt)
