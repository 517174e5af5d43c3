"""Point-line bundle adjustment over a keyframe window (paper II-E): a vectorised sparse Levenberg-Marquardt.

It minimises exactly the cost of the gtsam graph in factors.py (relative-pose factors with information zeta I,
stereo/monocular point factors, 2- or 3-row line factors, Huber kernels; the tests check equal costs at equal
values) but evaluates every factor type in one numpy call with analytic Jacobians, assembles the sparse
Jacobian with scipy.sparse and solves the damped normal equations with SuperLU. gtsam with Python line factors
took 1-13 s on the 8-keyframe window where this takes tens of milliseconds (figures in the report).

Parameterisation: poses as T_cam_world perturbed on the left, T_cw <- exp(xi) T_cw (xi = (rho, phi), as
plvo.geometry.line_jacobians); points additively; lines in orthonormal form, updated by the 4-dof
`orth_update`, re-anchored every iteration. Robust kernels by iteratively reweighted least squares per
observation. Fixed keyframes are not variables. Landmarks seen by a single keyframe (nine in ten of a seq-04
window) carry no pose information and are not variables either: they move rigidly with their keyframe (`_carry`).
The cost reported is gtsam's: sum of rho(|whitened r|) with rho(s) = s^2/2 up to the Huber threshold k and
k s - k^2/2 beyond.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from plvo.backend import factors
from plvo.backend.factors import DEFAULT_STEREO_BASELINE_M, usable_landmarks
from plvo.backend.problem import BAProblem, BAResult, stereo_row_sigma
from plvo.backend.relpose import relpose_residuals
from plvo.config import BackendConfig
from plvo.geometry import se3
from plvo.geometry.line_jacobians import line_residuals_batch
from plvo.geometry.lines import hat_batch, orth_to_plucker, orth_update, plucker_from_points, plucker_to_orth

log = logging.getLogger(__name__)


# --- vectorised residual blocks for the sparse Levenberg-Marquardt in bundle_adjustment.py -------------------
# Poses there are perturbed as in plvo.geometry.line_jacobians: T_cam_world <- exp(xi) T_cam_world, xi=(rho,phi).
# Each block returns whitened residuals r (N,d) and Jacobians (N,d,6) w.r.t. the pose and (N,d,k) w.r.t. the
# landmark; robust weighting is applied by the solver per row of N. The *_residuals forms give r and a function
# that computes the Jacobians later from what r was computed from: the LM's trial steps need the cost alone, and
# the Jacobians only of a step that is accepted.

_Later = Callable[[], tuple[np.ndarray, np.ndarray]]


def point_block(
    K: np.ndarray, T_cw: np.ndarray, X_w: np.ndarray, uv: np.ndarray, depth: np.ndarray, baseline: float,
    sigma: float, jacobians: bool = True,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(3,3), (N,4,4), (N,3) world, (N,2) px, (N,) z or NaN -> r (N,3), J_pose (N,3,6), J_point (N,3,3), whitened.

    Row 3 is the virtual right-image column u_R (ORB-SLAM2's stereo form, as gtsam's GenericStereoFactor3D)
    where a depth prior exists and zero (with zero Jacobian) otherwise, so mono and stereo share one array.
    jacobians=False: (r, None, None), r computed by the same operations (the LM's trial steps need the cost only).
    """
    r, later = point_residuals(K, T_cw, X_w, uv, depth, baseline, sigma)
    return (r, *later()) if jacobians else (r, None, None)


def point_residuals(
    K: np.ndarray, T_cw: np.ndarray, X_w: np.ndarray, uv: np.ndarray, depth: np.ndarray, baseline: float,
    sigma: float, depth_sigma: np.ndarray | None = None,
) -> tuple[np.ndarray, _Later]:
    """point_block's r, and the function that gives its (J_pose, J_point); depth_sigma (N,) m: each prior's own
    sigma, which widens its u_R row's (stereo_row_sigma)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    R, t = T_cw[:, :3, :3], T_cw[:, :3, 3]
    Xc = np.einsum("nij,nj->ni", R, X_w) + t
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    zi = 1.0 / np.where(np.abs(z) > 1e-9, z, 1e-9)
    stereo = np.isfinite(depth) & (depth > 0)
    u_r_meas = uv[:, 0] - fx * baseline / np.where(stereo, depth, 1.0)
    r = np.stack([fx * x * zi + cx - uv[:, 0], fy * y * zi + cy - uv[:, 1],
                  fx * (x - baseline) * zi + cx - u_r_meas], 1)
    r[~stereo, 2] = 0.0
    w = None
    if depth_sigma is not None:
        w = np.full((len(z), 3, 1), 1.0 / sigma)
        w[:, 2, 0] = 1.0 / stereo_row_sigma(fx, baseline, depth, sigma, depth_sigma)

    def jacobians() -> tuple[np.ndarray, np.ndarray]:
        dproj = np.zeros((len(z), 3, 3))  # d(uL, v, uR)/d Xc
        dproj[:, 0, 0], dproj[:, 0, 2] = fx * zi, -fx * x * zi**2
        dproj[:, 1, 1], dproj[:, 1, 2] = fy * zi, -fy * y * zi**2
        dproj[:, 2, 0], dproj[:, 2, 2] = fx * zi, -fx * (x - baseline) * zi**2
        dproj[~stereo, 2] = 0.0
        dXc_dxi = np.concatenate([np.broadcast_to(np.eye(3), (len(z), 3, 3)), -hat_batch(Xc)], axis=2)
        if w is None:
            return dproj @ dXc_dxi / sigma, dproj @ R / sigma
        return dproj @ dXc_dxi * w, dproj @ R * w

    return (r / sigma if w is None else r * w[:, :, 0]), jacobians


def line_block(
    K: np.ndarray, T_cw: np.ndarray, U: np.ndarray, W: np.ndarray, seg: np.ndarray, priors: np.ndarray, sigma: float,
    jacobians: bool = True,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(3,3), (N,4,4), (N,3,3),(N,2,2) world lines, (N,4) px, (N,2,3) priors in camera or NaN -> r (N,3),
    J_pose (N,3,6), J_line (N,3,4), whitened; row 3 (mean prior distance) is zero where there is no prior.
    jacobians=False: (r, None, None)."""
    r, later = line_residuals(K, T_cw, U, W, seg, priors, sigma)
    return (r, *later()) if jacobians else (r, None, None)


def line_residuals(
    K: np.ndarray, T_cw: np.ndarray, U: np.ndarray, W: np.ndarray, seg: np.ndarray, priors: np.ndarray, sigma: float,
) -> tuple[np.ndarray, _Later]:
    """line_block's r, and the function that gives its (J_pose, J_line)."""
    r2, later2, (d_c, m_c) = line_residuals_batch(K, T_cw, U, W, seg)
    n = len(seg)
    has = np.all(np.isfinite(priors.reshape(n, 6)), axis=1)
    r = np.zeros((n, 3))
    r[:, :2] = r2
    later_prior = None
    if np.any(has):
        r[has, 2], later_prior = factors.prior_distance(T_cw[has], U[has], W[has], priors[has], (d_c[has], m_c[has]))

    def jacobians() -> tuple[np.ndarray, np.ndarray]:
        Jp, Jl = np.zeros((n, 3, 6)), np.zeros((n, 3, 4))
        Jp[:, :2], Jl[:, :2] = later2()
        if later_prior is not None:
            Jp[has, 2], Jl[has, 2] = later_prior()
        return Jp / sigma, Jl / sigma

    return r / sigma, jacobians


class _Layout:
    """Column offsets of the free variables: free poses (6), used points (3), used lines (4)."""

    def __init__(self, problem: BAProblem, pt_ok: np.ndarray, ln_ok: np.ndarray) -> None:
        free = ~np.asarray(problem.fixed, bool)
        self.pose = np.where(free, 6 * (np.cumsum(free) - 1), -1)
        n = 6 * int(free.sum())
        self.point = np.where(pt_ok, n + 3 * (np.cumsum(pt_ok) - 1), -1)
        n += 3 * int(pt_ok.sum())
        self.line = np.where(ln_ok, n + 4 * (np.cumsum(ln_ok) - 1), -1)
        self.line_start = n
        self.size = n + 4 * int(ln_ok.sum())
        self.n_pose_vars = 6 * int(free.sum())
        self.n_points, self.n_lines = int(pt_ok.sum()), int(ln_ok.sum())


class _Blocks:
    """Whitened residual blocks at one state: items (r (N,d), (cols (N,) of each variable block), huber k or None),
    and each block's Jacobians, (N,d,k) per variable block, computed on first use (`terms`): an LM's trial step
    needs the cost alone, and the Jacobians only once it is accepted."""

    def __init__(self) -> None:
        self.items: list[tuple[np.ndarray, tuple[np.ndarray, ...], float | None]] = []
        self._later: list[Callable[[], tuple[np.ndarray, ...]]] = []
        self._terms: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}

    def add(self, r: np.ndarray, cols: tuple[np.ndarray, ...], later: Callable[[], tuple[np.ndarray, ...]],
            k: float | None) -> None:
        if len(r):
            self.items.append((r, cols, k))
            self._later.append(later)

    def terms(self, i: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """[(cols (N,), J (N,d,k))] of block i."""
        if i not in self._terms:
            self._terms[i] = list(zip(self.items[i][1], self._later[i]()))
        return self._terms[i]

    def weights(self) -> list[np.ndarray]:
        out = []
        for r, _, k in self.items:
            s = np.linalg.norm(r, axis=1)
            out.append(np.ones(len(r)) if k is None else np.minimum(1.0, k / np.maximum(s, 1e-300)))
        return out

    def cost(self) -> float:
        total = 0.0
        for r, _, k in self.items:
            s = np.linalg.norm(r, axis=1)
            total += float(np.sum(0.5 * s * s if k is None else np.where(s <= k, 0.5 * s * s, k * s - 0.5 * k * k)))
        return total

    def normal_equations(self, lay: _Layout, plan: dict | None = None) -> _Normal:
        """Accumulate J^T W J and J^T W r by blocks: poses dense, pose-landmark dense, landmark 3x3/4x4 blocks.

        plan: where each block's rows go (their masks and flat indices into the sums), kept between calls for the
        same layout and observations (an LM's iterations), whose Jacobians change but not where they go."""
        ne = _Normal(lay)
        plan = {} if plan is None else plan
        for b, ((r, _, _), w) in enumerate(zip(self.items, self.weights())):
            terms = self.terms(b)
            rw = r * w[:, None]
            for a, (ca, Ja) in enumerate(terms):
                ka = Ja.shape[2]
                if (b, a) not in plan:
                    oka = ca >= 0
                    plan[b, a] = oka, ne.g_index(ca[oka], ka)
                oka, g_idx = plan[b, a]
                ne.add_g(g_idx, (rw[oka][:, None, :] @ Ja[oka])[:, 0])
                JaW = Ja * w[:, None, None]
                for c, (cb, Jb) in enumerate(terms):
                    if (ka == 6) != (Jb.shape[2] == 6) and ka != 6:
                        continue  # landmark-pose: the transpose of pose-landmark, not stored
                    if ka != 6 and cb is not ca:
                        continue
                    if (b, a, c) not in plan:
                        ok = oka & (cb >= 0)
                        plan[b, a, c] = (ok, *ne.h_index(ca[ok], cb[ok], ka, Jb.shape[2]))
                    ok, part, h_idx = plan[b, a, c]
                    ne.add_H(part, h_idx, JaW[ok].transpose(0, 2, 1) @ Jb[ok])
        return ne


class _Normal:
    """Damped normal equations solved by the Schur complement on the landmarks (block-diagonal)."""

    def __init__(self, lay: _Layout) -> None:
        self.lay = lay
        self.n_p, n_l = lay.n_pose_vars, lay.size - lay.n_pose_vars
        self.Hpp = np.zeros(self.n_p * self.n_p)
        self.Hpl = np.zeros(self.n_p * n_l)
        self.Hpt = np.zeros(9 * lay.n_points)
        self.Hln = np.zeros(16 * lay.n_lines)
        self.g = np.zeros(lay.size)

    @staticmethod
    def g_index(c: np.ndarray, k: int) -> np.ndarray:
        """Flat indices into g of the (N,k) gradient rows of the variables starting at columns c (N,)."""
        return (c[:, None] + np.arange(k)).ravel()

    def add_g(self, idx: np.ndarray, G: np.ndarray) -> None:
        self.g += np.bincount(idx, G.ravel(), minlength=len(self.g))

    def h_index(self, ca: np.ndarray, cb: np.ndarray, ka: int, kb: int) -> tuple[str, np.ndarray]:
        """-> (which of Hpp, Hpl, Hpt, Hln; the flat indices there) of (N,ka,kb) blocks at columns ca, cb (N,)."""
        ii, jj = np.arange(ka)[None, :, None], np.arange(kb)[None, None, :]
        if ka == 6 and kb == 6:
            return "Hpp", ((ca[:, None, None] + ii) * self.n_p + cb[:, None, None] + jj).ravel()
        if ka == 6:
            n_l = self.lay.size - self.n_p
            return "Hpl", ((ca[:, None, None] + ii) * n_l + (cb[:, None, None] - self.n_p) + jj).ravel()
        if ka == 3:
            rank = (ca - self.n_p) // 3
            return "Hpt", (rank[:, None, None] * 9 + ii * 3 + jj).ravel()
        rank = (ca - self.lay.line_start) // 4
        return "Hln", (rank[:, None, None] * 16 + ii * 4 + jj).ravel()

    def add_H(self, part: str, idx: np.ndarray, B: np.ndarray) -> None:
        H = getattr(self, part)
        H += np.bincount(idx, B.ravel(), minlength=len(H))

    def median_diagonal(self) -> float:
        """The median of the diagonal of J^T W J over all variables (1.0 when it has none or it is zero)."""
        n_p = self.n_p
        d = np.concatenate([self.Hpp[:: n_p + 1] if n_p else np.zeros(0),
                            self.Hpt.reshape(-1, 3, 3)[:, np.arange(3), np.arange(3)].ravel(),
                            self.Hln.reshape(-1, 4, 4)[:, np.arange(4), np.arange(4)].ravel()])
        m = float(np.median(d)) if len(d) else 0.0
        return m if np.isfinite(m) and m > 0 else 1.0

    def solve(self, lam: float) -> np.ndarray:
        """-> delta minimising the damped model (H + lam I) delta = -g (gtsam's default damping).

        Not Marquardt's lam diag(H): the point factors make diag(H) of a pose ~1e8, which would damp away the
        weak relative-pose factor along the monocular scale direction (measured: 10 iterations to move 0.8 -> 0.82).
        """
        lay, n_p = self.lay, self.n_p
        n_l = lay.size - n_p
        Hpp = self.Hpp.reshape(n_p, n_p)
        Hpp = Hpp + lam * np.eye(n_p)
        Hpl = self.Hpl.reshape(n_p, n_l)
        inv_blocks = []
        for H, k in ((self.Hpt, 3), (self.Hln, 4)):
            B = H.reshape(-1, k, k).copy()
            B[:, np.arange(k), np.arange(k)] += lam
            try:
                inv_blocks.append(np.linalg.inv(B) if len(B) else B)
            except np.linalg.LinAlgError:
                # a block that lost rank during the iterations (seen on a synthetic run): a relative floor. Not
                # always: summed over hundreds of landmarks it would resist the weak monocular scale direction.
                B[:, np.arange(k), np.arange(k)] += 1e-9 * (np.trace(B, axis1=1, axis2=2)[:, None] / k + 1.0)
                inv_blocks.append(np.linalg.inv(B))
        g_p, g_l = self.g[:n_p], self.g[n_p:]
        n_pt3 = 3 * lay.n_points

        def apply_inv(M: np.ndarray) -> np.ndarray:  # (r, n_l) -> (r, n_l) times Hll^-1
            # one small matmul per landmark, its rows stacked: several times faster than einsum's generic loop
            r = M.shape[0]
            a = M[:, :n_pt3].reshape(r, -1, 3).transpose(1, 0, 2) @ inv_blocks[0]
            b = M[:, n_pt3:].reshape(r, -1, 4).transpose(1, 0, 2) @ inv_blocks[1]
            return np.concatenate([a.transpose(1, 0, 2).reshape(r, -1), b.transpose(1, 0, 2).reshape(r, -1)], 1)

        d_p: np.ndarray = np.zeros(n_p)
        if n_p:
            Y = apply_inv(Hpl)
            S = Hpp - Y @ Hpl.T
            d_p = np.linalg.solve(S, -(g_p - Y @ g_l))
        d_l = -apply_inv((g_l + Hpl.T @ d_p)[None])[0]
        return np.concatenate([d_p, d_l])


def _evaluate(problem: BAProblem, T_cw: np.ndarray, pts: np.ndarray, U: np.ndarray, W: np.ndarray, lay: _Layout,
              sel: dict[str, np.ndarray], cfg: BackendConfig, baseline: float) -> _Blocks:
    """Whitened residual blocks at a state (their Jacobians computed when asked for: _Blocks.terms)."""
    b = _Blocks()
    o = sel["pt"]
    r, later = point_residuals(problem.K, T_cw[problem.pt_kf[o]], pts[problem.pt_idx[o]], problem.pt_uv[o],
                               sel["depth"], baseline, cfg.sigma_point_px, problem.depth_sigmas(o))
    b.add(r, (lay.pose[problem.pt_kf[o]], lay.point[problem.pt_idx[o]]), later, cfg.huber_point / cfg.sigma_point_px)
    o = sel["ln"]
    if len(o):
        j = problem.ln_idx[o]
        T_cl = T_cw[problem.ln_kf[o]].copy()  # camera <- the line's local frame (world shifted to its origin)
        T_cl[:, :3, 3] += np.einsum("nij,nj->ni", T_cl[:, :3, :3], sel["origin"][j])
        r, later = line_residuals(problem.K, T_cl, U[j], W[j], problem.ln_seg[o], sel["prior"], cfg.sigma_line)
        b.add(r, (lay.pose[problem.ln_kf[o]], lay.line[j]), later, cfg.huber_line / cfg.sigma_line)
    o = sel["rel"]
    if len(o):
        i, j = problem.rel_ij[o, 0], problem.rel_ij[o, 1]
        r, later = relpose_residuals(T_cw[i], T_cw[j], problem.rel_T[o], problem.rel_zeta[o],
                                      problem.relative_pose_weights(o))
        b.add(r, (lay.pose[i], lay.pose[j]), later, None)
    return b


def _select(problem: BAProblem, pt_ok: np.ndarray, ln_ok: np.ndarray, use_depth_priors: bool,
            pt_obs_ok: np.ndarray | None = None, ln_obs_ok: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Observation rows of the used landmarks (and of the observations kept, when masks are given)."""
    pt_use, ln_use = pt_ok[problem.pt_idx], ln_ok[problem.ln_idx]
    pt = np.flatnonzero(pt_use if pt_obs_ok is None else pt_use & pt_obs_ok)
    ln = np.flatnonzero(ln_use if ln_obs_ok is None else ln_use & ln_obs_ok)
    depth = problem.pt_depth[pt] if use_depth_priors else np.full(len(pt), np.nan)
    prior = problem.ln_prior[ln] if use_depth_priors else np.full((len(ln), 2, 3), np.nan)
    i, j = problem.rel_ij[:, 0], problem.rel_ij[:, 1]
    rel = np.flatnonzero((problem.rel_zeta > 0) & ~(problem.fixed[i] & problem.fixed[j]))
    return {"pt": pt, "ln": ln, "depth": depth, "prior": prior, "rel": rel}


# the LM state: T_cam_world (K,4,4), points (P,3), lines as U (L,3,3) and W (L,2,2)
_State = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _apply(delta: np.ndarray, lay: _Layout, T_cw: np.ndarray, pts: np.ndarray, U: np.ndarray, W: np.ndarray) -> _State:
    T_new, pts_new, U_new, W_new = T_cw.copy(), pts.copy(), U.copy(), W.copy()
    for k in np.flatnonzero(lay.pose >= 0):
        T_new[k] = se3.exp(delta[lay.pose[k]:lay.pose[k] + 6]) @ T_cw[k]
    i = np.flatnonzero(lay.point >= 0)
    pts_new[i] += delta[lay.point[i][:, None] + np.arange(3)]
    j = np.flatnonzero(lay.line >= 0)
    if len(j):
        U_new[j], W_new[j] = orth_update(U[j], W[j], delta[lay.line[j][:, None] + np.arange(4)])
    return T_new, pts_new, U_new, W_new


# A landmark whose information block (given the poses) has an eigenvalue below these is left out: its worst
# direction has a standard deviation over 1 m (points) or 0.2 in the orthonormal 4-vector (lines).
_MIN_POINT_INFORMATION = 1.0
_MIN_LINE_INFORMATION = 1.0 / 0.2**2


def _weak_landmarks(normal: _Normal) -> tuple[np.ndarray, np.ndarray]:
    """-> (used points,) bool and (used lines,) bool: blocks with too small an eigenvalue."""
    out = []
    for H, k, limit in ((normal.Hpt, 3, _MIN_POINT_INFORMATION), (normal.Hln, 4, _MIN_LINE_INFORMATION)):
        B = H.reshape(-1, k, k)
        if not len(B):
            out.append(np.zeros(0, bool))
            continue
        ev = np.linalg.eigvalsh(B)
        weak = ev[:, 0] < limit
        out.append(weak)
    return out[0], out[1]


_LINE_ORIGIN_OFFSET_M = 10.0
# LM damping: the start (gtsam's default: nearly Gauss-Newton), the factor after a rejected step, and the least
# damping after a rejected step, relative to the median diagonal of the normal equations.
# Gauss-Newton first: a scale correction's first step must walk the weak monocular scale direction, which any
# damping at the problem's scale holds back (every landmark moves along it). When that step is rejected, the LM of
# a seq-04 window climbed x100 at a time through three or four more rejected steps to ~1e3 (the diagonal: ~1e5 at
# the landmarks, which are most variables, ~1e10 at the poses); the floor of 1e-2 of the median diagonal goes there
# at once.
# After an accepted step the damping follows the step's gain ratio rho (actual / predicted decrease), Nielsen's rule
# as in g2o and Ceres: lam *= max(1/3, 1 - (2 rho - 1)^3). A fixed /10 overshoots: on the seq-04 windows every
# other step after it was rejected, and each rejection costs a solve and an evaluation.
# The LM stops when an accepted step lowers the cost by less than _MIN_REL_DROP of it: at 1e-6 the last of the 5
# iterations moved those windows' poses by a millimetre at most. Together, on the 32 windows of a seq-04 run: 285
# solves instead of 369, 35 % less time (docs/results/speed.md).
_LAM0, _LAM_UP, _LAM_FLOOR_REL = 1e-5, 100.0, 1e-2
_MIN_REL_DROP = 1e-4


def _line_origins(ends: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(L,2,3) world endpoints, (3,) a camera centre -> (L,3) local origins for the orthonormal form.

    The form's w = (|m|, |d|) / norm encodes the distance to the origin as tan(psi), so moves towards or away
    from the origin are the nonlinear ones, and moves around it are rotations of U over the offset radius. Lines
    are weakly determined in depth from a driving camera; so the origin sits 10 m from the line's midpoint,
    perpendicular to both the line and the viewing ray: depth moves become rotations over 10 m (nearly linear
    for metre-sized corrections) and the tan(psi) direction lies across the image, where the line is well
    measured. With the world origin (psi ~ 1.52 for lines 20-40 m away, in the depth direction) or a 1 m offset
    along an arbitrary normal, LM steps along the monocular scale direction missed by metres.
    """
    mid = ends.mean(axis=1)
    d = ends[:, 1] - ends[:, 0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ray = mid - centre
    n = np.cross(d, ray)
    bad = np.linalg.norm(n, axis=1) < 1e-9 * np.linalg.norm(ray, axis=1)  # line along the ray: any normal
    n[bad] = np.cross(d[bad], np.eye(3)[np.argmin(np.abs(d[bad]), axis=1)])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return mid - _LINE_ORIGIN_OFFSET_M * n


def _line_endpoints(old: np.ndarray, U: np.ndarray, W: np.ndarray) -> np.ndarray:
    """(L,2,3) old endpoints, (L,3,3),(L,2,2) lines -> (L,2,3): the old endpoints' closest points on the lines."""
    Lp = orth_to_plucker(U, W)
    m, d = Lp[:, :3], Lp[:, 3:]
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    p0 = np.cross(d, m) / np.sum(d * d, axis=1, keepdims=True)
    s = np.einsum("lki,li->lk", old - p0[:, None], u)
    return p0[:, None] + s[:, :, None] * u[:, None]


def _carry(problem: BAProblem, T_cw_old: np.ndarray, T_cw_new: np.ndarray, pts: np.ndarray, lines: np.ndarray,
           pt_ok: np.ndarray, ln_ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Move landmarks seen by a single keyframe rigidly with it (in place) -> (P,) and (L,) bool moved.

    A lone observation fixes a landmark in its camera (it is at its optimum wherever the camera goes), so leaving
    it out of the optimisation and moving it with the camera gives the same result at a fraction of the cost.
    """
    out = []
    for is_point, kf, idx, ok, n in ((True, problem.pt_kf, problem.pt_idx, pt_ok, problem.n_points),
                                     (False, problem.ln_kf, problem.ln_idx, ln_ok, problem.n_lines)):
        single = (np.bincount(idx, minlength=n) == 1) & ~ok
        out.append(np.zeros(n, bool))
        sel = np.flatnonzero(single[idx] & ~problem.fixed[kf])  # observations of such landmarks by free keyframes
        if not len(sel):
            continue
        k, j = kf[sel], idx[sel]
        M = se3.inv_batch(T_cw_new[k]) @ T_cw_old[k]  # world -> world: the keyframe's move
        if is_point:
            pts[j] = np.einsum("nij,nj->ni", M[:, :3, :3], pts[j]) + M[:, :3, 3]
        else:
            lines[j] = np.einsum("nij,nkj->nki", M[:, :3, :3], lines[j]) + M[:, None, :3, 3]
        out[-1][j] = True
    return out[0], out[1]


def _levenberg_marquardt(problem: BAProblem, state: _State, origin: np.ndarray, pt_ok: np.ndarray, ln_ok: np.ndarray,
                         pt_obs_ok: np.ndarray | None, ln_obs_ok: np.ndarray | None, cfg: BackendConfig,
                         use_depth_priors: bool, baseline: float
                         ) -> tuple[_State, float, float, int, np.ndarray, np.ndarray]:
    """LM from state over the selected observations (pt_obs_ok / ln_obs_ok masks, None: all) -> (state, initial
    cost, cost, iterations, pt_ok, ln_ok); landmarks the window cannot determine are dropped first (copies)."""
    pt_ok, ln_ok = pt_ok.copy(), ln_ok.copy()
    for attempt in range(3):  # drop landmarks the window cannot determine, then build again
        lay = _Layout(problem, pt_ok, ln_ok)
        sel = _select(problem, pt_ok, ln_ok, use_depth_priors, pt_obs_ok, ln_obs_ok)
        sel["origin"] = origin
        plan: dict = {}  # where the rows of this layout and selection go in the normal equations
        blocks = _evaluate(problem, *state, lay, sel, cfg, baseline)
        normal = blocks.normal_equations(lay, plan)
        if attempt == 2:
            break
        weak_pt, weak_ln = _weak_landmarks(normal)
        if not (weak_pt.any() or weak_ln.any()):
            break
        pt_ok[np.flatnonzero(pt_ok)[weak_pt]] = False
        ln_ok[np.flatnonzero(ln_ok)[weak_ln]] = False
    initial_cost = cost = blocks.cost()
    lam, it = _LAM0, 0
    lam_floor = _LAM_FLOOR_REL * normal.median_diagonal()
    while it < cfg.iterations and lay.size > 0:
        it += 1
        improved = False
        for _ in range(8):  # raise the damping until a step lowers the cost
            delta = normal.solve(lam)
            # predicted decrease of the damped model: -g.d/2 + lam |d|^2 / 2 (as (H + lam I) d = -g)
            predicted = 0.5 * (lam * float(delta @ delta) - float(normal.g @ delta))
            if predicted < 1e-7 * cost:
                break
            cand = _apply(delta, lay, *state)
            # the cost alone: trial steps may be rejected; the Jacobians are computed of the one accepted
            cand_blocks = _evaluate(problem, *cand, lay, sel, cfg, baseline)
            cand_cost = cand_blocks.cost()
            if np.isfinite(cand_cost) and cand_cost < cost:
                improved = True
                break
            lam = max(lam * _LAM_UP, lam_floor)
        if not improved:
            break
        rel_drop = (cost - cand_cost) / max(cost, 1e-300)
        rho = (cost - cand_cost) / max(predicted, 1e-300)
        lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 1e-12)
        state, cost, blocks = cand, cand_cost, cand_blocks
        if rel_drop < _MIN_REL_DROP or cost < 1e-12 or np.max(np.abs(delta)) < 1e-10 or it >= cfg.iterations:
            break
        normal = blocks.normal_equations(lay, plan)
    return state, initial_cost, cost, it, pt_ok, ln_ok


def _outliers(problem: BAProblem, state: _State, origin: np.ndarray, pt_ok: np.ndarray, ln_ok: np.ndarray,
              cfg: BackendConfig, use_depth_priors: bool, baseline: float) -> tuple[np.ndarray, np.ndarray]:
    """-> (O,) and (M,) bool: point / line observations of used landmarks whose residual (all rows, in the
    factor's units: pixels, and metres for a line's prior row; a weighed depth prior's row in sigma_point_px) exceeds
    cfg.outlier_px at `state`."""
    lay = _Layout(problem, pt_ok, ln_ok)
    sel = _select(problem, pt_ok, ln_ok, use_depth_priors)
    sel.update(origin=origin, rel=sel["rel"][:0])
    bad_pt, bad_ln = np.zeros(len(problem.pt_idx), bool), np.zeros(len(problem.ln_idx), bool)
    only_points = {**sel, "ln": sel["ln"][:0], "prior": sel["prior"][:0]}
    only_lines = {**sel, "pt": sel["pt"][:0], "depth": sel["depth"][:0]}
    for bad, part, rows, sigma in ((bad_pt, only_points, sel["pt"], cfg.sigma_point_px),
                                   (bad_ln, only_lines, sel["ln"], cfg.sigma_line)):
        if len(rows):
            r = _evaluate(problem, *state, lay, part, cfg, baseline).items[0][0]
            bad[rows] = sigma * np.linalg.norm(r, axis=1) > cfg.outlier_px
    return bad_pt, bad_ln


def optimize(
    problem: BAProblem, cfg: BackendConfig | None = None, *, use_depth_priors: bool = True,
    use_lines: bool = True, stereo_baseline_m: float = DEFAULT_STEREO_BASELINE_M,
) -> BAResult:
    """Bundle-adjust the window: free poses T_world_cam (K,4,4), points (P,3) and lines (L,2,3), all world."""
    cfg = cfg or BackendConfig()
    t0 = time.perf_counter()
    pt_ok, ln_ok = usable_landmarks(problem, use_depth_priors)
    if not use_lines:
        ln_ok = np.zeros_like(ln_ok)
    T_cw = np.stack([se3.inv(T) for T in problem.T_world_cam])
    pts = problem.points.astype(float).copy()
    U, W = np.tile(np.eye(3), (problem.n_lines, 1, 1)), np.tile(np.eye(2), (problem.n_lines, 1, 1))
    origin = np.zeros((problem.n_lines, 3))
    if ln_ok.any():  # only sound lines (usable_landmarks): collapsed segments have no Pluecker form
        o = _line_origins(problem.lines[ln_ok], problem.T_world_cam[:, :3, 3].mean(axis=0))
        origin[ln_ok] = o
        U[ln_ok], W[ln_ok] = plucker_to_orth(
            plucker_from_points(problem.lines[ln_ok, 0] - o, problem.lines[ln_ok, 1] - o))
    state = (T_cw, pts, U, W)
    state, initial_cost, cost, it, pt_ok, ln_ok = _levenberg_marquardt(
        problem, state, origin, pt_ok, ln_ok, None, None, cfg, use_depth_priors, stereo_baseline_m)
    if cfg.outlier_px > 0:
        # ORB-SLAM2's two rounds: observations still far off after the first are wrong associations (a facade's
        # repeated windows matched one period off); left in, thousands of them pull the keyframes together.
        bad_pt, bad_ln = _outliers(problem, state, origin, pt_ok, ln_ok, cfg, use_depth_priors, stereo_baseline_m)
        if bad_pt.any() or bad_ln.any():
            pt_obs_ok, ln_obs_ok = ~bad_pt, ~bad_ln
            pt_ok &= np.bincount(problem.pt_idx[pt_obs_ok], minlength=problem.n_points) >= 2
            ln_ok &= np.bincount(problem.ln_idx[ln_obs_ok], minlength=problem.n_lines) >= 2
            state, _, cost, it2, pt_ok, ln_ok = _levenberg_marquardt(
                problem, state, origin, pt_ok, ln_ok, pt_obs_ok, ln_obs_ok, cfg, use_depth_priors, stereo_baseline_m)
            it += it2
            log.debug("BA: %d point and %d line observations over %.1f px left out", int(bad_pt.sum()),
                      int(bad_ln.sum()), cfg.outlier_px)
    T_cw_new, pts, U, W = state
    lines = problem.lines.astype(float).copy()
    if ln_ok.any():
        o = origin[ln_ok][:, None]
        lines[ln_ok] = _line_endpoints(problem.lines[ln_ok] - o, U[ln_ok], W[ln_ok]) + o
    pt_moved, ln_moved = _carry(problem, T_cw, T_cw_new, pts, lines, pt_ok, ln_ok)
    T_cw = T_cw_new
    dt = time.perf_counter() - t0
    log.debug("BA: %d kf, %d pts, %d lines, cost %.4g -> %.4g in %d it, %.1f ms", problem.n_keyframes,
              int(pt_ok.sum()), int(ln_ok.sum()), initial_cost, cost, it, 1e3 * dt)
    return BAResult(T_world_cam=np.stack([se3.inv(T) for T in T_cw]), points=pts, lines=lines,
                    point_used=pt_ok | pt_moved, line_used=ln_ok | ln_moved, initial_cost=initial_cost,
                    final_cost=cost, iterations=it, time_s=dt)
