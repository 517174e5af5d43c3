"""Line depth priors: a 3D line per image segment from the lidar points in a band around it (paper, II-B).

For each segment the band's points are gathered (capped, evenly thinned) into padded (M,P) arrays; the
foreground is kept per stretch of the segment (nearest depth within depth_jump of the stretch's nearest point,
so a silhouette edge takes the occluder). The initial line lies in the segment's interpretation plane: inverse
depth is affine along the image of a 3D line, so a robust fit 1/z = a + b t over the foreground gives the depths
of the two segment ends. Levenberg-Marquardt over the orthonormal 4-dof update then minimises

    sum_i huber(d(p_i, L)) + (w * e(L, l))^2

with d the point-to-line distance (m) and e the paper's reprojection residual (px), batched over all lines with
analytic Jacobians. The endpoints come from trimming with the segment's end rays.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from plvo.config import DepthConfig
from plvo.depth.projection import ProjectedScan, query_segments, to_padded
from plvo.geometry.lines import cross3, line_projection_matrix, orth_to_plucker, orth_update, plucker_to_orth
from plvo.types import (
    DEPTH_BAD_FIT,
    DEPTH_GRAZING_RAY,
    DEPTH_NOT_CONVERGED,
    DEPTH_OK,
    DEPTH_OUT_OF_RANGE,
    DEPTH_TOO_FEW_POINTS,
)

_N_BINS = 8  # stretches along a segment for the foreground choice


@dataclass(frozen=True)
class LineDepthResult:
    """Per segment (M rows), camera frame. endpoints (M,2,3) NaN where none; reason (M,) DEPTH_*; residual (M,)
    RMS point-to-line distance of the inliers (m); inliers (M,) int; reproj_px (M,) RMS of the two end residuals;
    plucker (M,6) fitted line (NaN where none); iterations (M,) LM iterations; band_index (M,P) indices into the
    ProjectedScan (-1 padding); inlier_mask (M,P) bool."""

    endpoints: np.ndarray
    reason: np.ndarray
    residual: np.ndarray
    inliers: np.ndarray
    reproj_px: np.ndarray
    plucker: np.ndarray
    iterations: np.ndarray
    band_index: np.ndarray
    inlier_mask: np.ndarray


def line_depths(proj: ProjectedScan, segments: np.ndarray, K: np.ndarray, cfg: DepthConfig) -> LineDepthResult:
    """(M,4) pixel segments + projected scan -> LineDepthResult (3D lines in the camera frame)."""
    seg = np.asarray(segments, dtype=float).reshape(-1, 4)
    M = len(seg)
    owner, idx, t, perp = query_segments(proj, seg, float(cfg.line_patch_px))
    count = np.bincount(owner, minlength=M)
    keep = _thin(owner, count, cfg.line_max_points)
    owner, idx, t, perp = owner[keep], idx[keep], t[keep], perp[keep]
    bidx, _ = to_padded(owner, idx, M)
    if len(proj) == 0 or M == 0 or len(idx) == 0:
        return _no_lines(M, bidx.shape[1])
    kpad, _ = to_padded(owner, np.arange(len(t)), M)
    valid = bidx >= 0
    pts = np.where(valid[:, :, None], proj.pts_cam[np.maximum(bidx, 0)], np.nan)
    z = np.where(valid, proj.depth[np.maximum(bidx, 0)], np.nan)
    tt = np.where(valid, t[np.maximum(kpad, 0)] if len(t) else 0.0, np.nan)
    pp = np.where(valid, perp[np.maximum(kpad, 0)] if len(t) else 0.0, np.inf)

    fg = _band_foreground(z, tt, pp, cfg)
    za, zb, sel = _init_depths(z, tt, fg, cfg)
    rays = _end_rays(K, seg)
    good_init = np.isfinite(za) & np.isfinite(zb) & (za > 0) & (zb > 0) & (sel.sum(1) >= cfg.line_min_points)
    p0 = np.where(good_init[:, None], rays[:, 0] * za[:, None], rays[:, 0] * 10.0)
    p1 = np.where(good_init[:, None], rays[:, 1] * zb[:, None], rays[:, 1] * 10.0)
    L, iters, converged = _lm(_plucker(p0, p1), pts, sel, K, seg, cfg)
    dist = _distances(pts, L)
    inl = fg & (dist <= cfg.line_inlier_m)
    n_inl = inl.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(np.sum(np.where(inl, dist**2, 0.0), 1) / n_inl)
        span = np.max(np.where(inl, tt, -np.inf), 1) - np.min(np.where(inl, tt, np.inf), 1)
    rep = _reprojection(line_projection_matrix(K), _ends_h(seg), L)
    ends, sin_min = _trim(L, rays)

    reason = np.full(M, DEPTH_OK, dtype=np.int64)
    ez = ends[:, :, 2]
    reason[~np.all((ez > cfg.min_depth_m) & (ez <= cfg.max_depth_m), axis=1)] = DEPTH_OUT_OF_RANGE
    reason[~(sin_min >= cfg.min_ray_line_sin)] = DEPTH_GRAZING_RAY
    reason[~converged | ~np.all(np.isfinite(L), 1)] = DEPTH_NOT_CONVERGED
    reason[~(rms <= cfg.line_max_rms_m) | ~(np.sqrt(np.mean(rep**2, 1)) <= cfg.line_max_reproj_px)] = DEPTH_BAD_FIT
    few = (count < cfg.line_min_points) | ~good_init | (n_inl < cfg.line_min_points)
    reason[few | ~(span >= cfg.line_min_coverage)] = DEPTH_TOO_FEW_POINTS
    ok = reason == DEPTH_OK
    ends[~ok] = np.nan
    Lout = L.copy()
    Lout[~ok] = np.nan
    return LineDepthResult(
        endpoints=ends,
        reason=reason,
        residual=rms,
        inliers=n_inl.astype(np.int64),
        reproj_px=np.sqrt(np.mean(rep**2, 1)),
        plucker=Lout,
        iterations=iters,
        band_index=bidx,
        inlier_mask=inl,
    )


def _thin(owner: np.ndarray, count: np.ndarray, cap: int) -> np.ndarray:
    """(K,) sorted owners -> (K,) bool keeping at most about `cap` points a segment, every k-th of the band."""
    if len(owner) == 0:
        return np.zeros(0, dtype=bool)
    stride = np.maximum(-(-count // max(cap, 1)), 1)
    starts = np.cumsum(count) - count
    rank = np.arange(len(owner)) - starts[owner]
    return rank % stride[owner] == 0


def _band_foreground(z: np.ndarray, tt: np.ndarray, perp: np.ndarray, cfg: DepthConfig) -> np.ndarray:
    """(M,P) depths, positions along and pixel distances from the segment -> (M,P) bool foreground.

    Per stretch of the segment the reference depth is the nearest return within core_px of the segment (the
    nearest of the whole stretch when none is that close); the foreground is the points within depth_jump of it,
    on both sides. So a silhouette takes the occluder, and at a concave fold (a wall's foot) the off-line road
    returns in front of the fold are not taken for the edge.
    """
    M, P = z.shape
    valid = np.isfinite(z)
    b = np.clip((np.nan_to_num(tt) * _N_BINS).astype(np.int64), 0, _N_BINS - 1)
    key = np.arange(M)[:, None] * _N_BINS + b
    core = valid & (perp <= cfg.line_core_px)
    zmin = np.full(M * _N_BINS, np.inf)
    np.minimum.at(zmin, key[valid], z[valid])
    zcore = np.full(M * _N_BINS, np.inf)
    np.minimum.at(zcore, key[core], z[core])
    zref = np.where(np.isfinite(zcore), zcore, zmin)[key]
    with np.errstate(invalid="ignore"):
        return valid & (np.abs(z - zref) <= np.maximum(cfg.depth_jump_min_m, cfg.depth_jump_ratio * zref))


def _init_depths(z: np.ndarray, tt: np.ndarray, fg: np.ndarray, cfg: DepthConfig, n_iter: int = 3
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust affine fit of inverse depth along the segment -> depth at t=0 (M,), at t=1 (M,), inliers (M,P)."""
    w = fg.astype(float)
    iz = np.where(fg, 1.0 / np.where(fg, z, 1.0), 0.0)
    t = np.nan_to_num(tt)
    sel = fg
    for _ in range(n_iter):
        s0, s1, s2 = w.sum(1), (w * t).sum(1), (w * t * t).sum(1)
        r0, r1 = (w * iz).sum(1), (w * t * iz).sum(1)
        det = s0 * s2 - s1 * s1
        with np.errstate(invalid="ignore", divide="ignore"):
            # Too little spread along t to get a slope: a constant inverse depth.
            flat = det <= 1e-9 * np.maximum(s0 * s0, 1e-30)
            a = np.where(flat, r0 / s0, (s2 * r0 - s1 * r1) / det)
            b = np.where(flat, 0.0, (s0 * r1 - s1 * r0) / det)
            zfit = 1.0 / (a[:, None] + b[:, None] * t)
            tol = np.maximum(cfg.depth_jump_min_m, cfg.depth_jump_ratio * zfit)
            sel = fg & (np.abs(z - zfit) <= tol)
        w = sel.astype(float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return 1.0 / a, 1.0 / (a + b), sel


def _end_rays(K: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """(M,4) segments -> (M,2,3) rays with z = 1 through the two ends."""
    ends = seg.reshape(-1, 2, 2)
    x = (ends[..., 0] - K[0, 2]) / K[0, 0]
    y = (ends[..., 1] - K[1, 2]) / K[1, 1]
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def _plucker(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    d = q - p
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return np.concatenate([cross3(p, d), d], axis=1)


def _distances(pts: np.ndarray, L: np.ndarray) -> np.ndarray:
    """(M,P,3) points, (M,6) lines -> (M,P) point-to-line distances |p x d - m| / |d| (NaN on NaN points)."""
    m, d = L[:, :3], L[:, 3:]
    x, y, z = pts[..., 0], pts[..., 1], pts[..., 2]
    dx, dy, dz = d[:, 0, None], d[:, 1, None], d[:, 2, None]
    ex = y * dz - z * dy - m[:, 0, None]
    ey = z * dx - x * dz - m[:, 1, None]
    ez = x * dy - y * dx - m[:, 2, None]
    return np.sqrt((ex * ex + ey * ey + ez * ez) / np.sum(d * d, axis=1)[:, None])


def _ends_h(seg: np.ndarray) -> np.ndarray:
    """(M,4) segments -> (M,2,3) homogeneous end pixels."""
    return np.concatenate([seg.reshape(-1, 2, 2), np.ones((len(seg), 2, 1))], axis=2)


def _reprojection(KL: np.ndarray, ends_h: np.ndarray, L: np.ndarray) -> np.ndarray:
    """Line projection matrix K_L, (M,2,3) homogeneous segment ends, (M,6) camera lines -> (M,2) px residuals."""
    l = L[:, :3] @ KL.T
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.einsum("mki,mi->mk", ends_h, l) / np.hypot(l[:, 0], l[:, 1])[:, None]


def _to_camera(L_loc: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(M,6) lines in frames translated to c (M,3) -> (M,6) camera-frame lines: m = m_loc + c x d."""
    return np.concatenate([L_loc[:, :3] + cross3(c, L_loc[:, 3:]), L_loc[:, 3:]], axis=1)


def _hat_rows(v: np.ndarray, out: np.ndarray, sign: float = 1.0) -> None:
    """Write sign * hat(v) of (M,3) vectors into the (M,3,3) view out: out[:, j, i] = sign * (e_j x v)_i."""
    vx, vy, vz = v[:, 0], v[:, 1], v[:, 2]
    out[:, 0, 0] = out[:, 1, 1] = out[:, 2, 2] = 0.0
    out[:, 0, 1], out[:, 0, 2] = -sign * vz, sign * vy
    out[:, 1, 0], out[:, 1, 2] = sign * vz, -sign * vx
    out[:, 2, 0], out[:, 2, 1] = -sign * vy, sign * vx


class _Lines:
    """Orthonormal lines (U (M,3,3), W (M,2,2)) in frames centred on their points, and what each step needs.

    With u1, u2, u3 the columns of U and a = w1 / w2 (the line's distance to the centroid), a point p has the
    residual r(p) = (p x d - m) / |d| = p x u2 - a u1, and its Jacobian for orth_update's delta is affine in p:
    J(p) = G0 + sum_j p_j G_j with G0 = [0, a u3, -a u2, (1 + a^2) u1] and G_j = [e_j x u3, 0, -e_j x u1, 0].
    """

    def __init__(self, U: np.ndarray, W: np.ndarray) -> None:
        self.U, self.W = U, W
        self.u1, self.u2, self.u3 = U[:, :, 0], U[:, :, 1], U[:, :, 2]
        self.a = W[:, 0, 0] / W[:, 1, 0]

    def distances(self, X: np.ndarray, Y: np.ndarray, Z: np.ndarray) -> np.ndarray:
        """(M,P) distances |p x u2 - a u1| of the points with coordinates X, Y, Z (M,P)."""
        u2, au1 = self.u2, self.a[:, None] * self.u1
        ex = Y * u2[:, 2, None] - Z * u2[:, 1, None] - au1[:, 0, None]
        ey = Z * u2[:, 0, None] - X * u2[:, 2, None] - au1[:, 1, None]
        ez = X * u2[:, 1, None] - Y * u2[:, 0, None] - au1[:, 2, None]
        return np.sqrt(ex * ex + ey * ey + ez * ez)

    def point_normal_equations(self, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(M,4,4) weighted moments of (1, p) -> sum w J^T J (M,4,4) and sum w J^T r (M,4), by contraction."""
        M = len(self.a)
        a = self.a[:, None]
        G = np.zeros((M, 4, 3, 4))
        G[:, 0, :, 1] = a * self.u3
        G[:, 0, :, 2] = -a * self.u2
        G[:, 0, :, 3] = (1.0 + a * a) * self.u1
        _hat_rows(self.u3, G[:, 1:, :, 0])
        _hat_rows(self.u1, G[:, 1:, :, 2], -1.0)
        R = np.empty((M, 4, 3))
        R[:, 0] = -a * self.u1
        _hat_rows(self.u2, R[:, 1:])
        G12 = G.reshape(M, 12, 4)
        SG = (S @ G.reshape(M, 4, 12)).reshape(M, 12, 4)
        H = np.swapaxes(G12, 1, 2) @ SG
        g = (np.swapaxes(G12, 1, 2) @ (S @ R).reshape(M, 12, 1))[..., 0]
        return H, g

    def reprojection(self, KL: np.ndarray, ends_h: np.ndarray, hat_c: np.ndarray, jacobian: bool = False
                     ) -> tuple[np.ndarray, Any]:
        """(M,2) px residuals of the segment ends (M,2,3) against the projected lines, and their (M,2,4)
        Jacobian for delta when asked; hat_c (M,3,3): cross-product matrices of the frames' centres c."""
        w1, w2 = self.W[:, 0, 0, None], self.W[:, 1, 0, None]
        cU = hat_c @ self.U  # columns c x u1, c x u2, c x u3
        l = (w1 * self.u1 + w2 * cU[:, :, 1]) @ KL.T  # K_L (m + c x d)
        norm = np.hypot(l[:, 0], l[:, 1])
        r = (ends_h @ l[:, :, None])[..., 0] / norm[:, None]
        if not jacobian:
            return r, None
        grad_n = np.zeros_like(l)
        grad_n[:, :2] = l[:, :2] / norm[:, None]
        dr_dm = ((ends_h - r[:, :, None] * grad_n[:, None, :]) / norm[:, None, None]) @ KL  # (M,2,3)
        # d(m + c x d)/d delta: dm = [0, -w1 u3, w1 u2, -w2 u1], dd = [w2 u3, 0, -w2 u1, w1 u2]
        dmc = np.empty((len(l), 3, 4))
        dmc[:, :, 0] = w2 * cU[:, :, 2]
        dmc[:, :, 1] = -w1 * self.u3
        dmc[:, :, 2] = w1 * self.u2 - w2 * cU[:, :, 0]
        dmc[:, :, 3] = w1 * cU[:, :, 1] - w2 * self.u1
        return r, dr_dm @ dmc


def _huber(dist: np.ndarray, wsel: np.ndarray, delta: float, weights: bool = True) -> tuple[Any, np.ndarray]:
    """(M,P) distances, (M,P) 0/1 selection -> Huber IRLS weights (M,P) (None unless asked) and costs (M,)."""
    inside = dist <= delta
    rho = np.where(inside, 0.5 * dist * dist, delta * (dist - 0.5 * delta))
    cost = np.einsum("mp,mp->m", rho, wsel)
    if not weights:
        return None, cost
    return np.where(inside, wsel, wsel * delta / np.maximum(dist, 1e-12)), cost


def _lm(L0: np.ndarray, pts: np.ndarray, sel: np.ndarray, K: np.ndarray, seg: np.ndarray, cfg: DepthConfig
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched Levenberg-Marquardt from (M,6) camera lines -> (M,6) camera lines, iterations (M,), converged (M,).

    Each line is solved in a frame translated to the centroid of its points: the orthonormal parameters of a line
    20 m from the origin are badly conditioned (w2 ~ 0.05, one radian of U moves it by metres) and Gauss-Newton
    steps overshoot; near the origin the same problem converges in a few steps. The points' part of the normal
    equations is a contraction of their weighted moments (one batched (4,P)@(P,4) product a step); a step's
    trial distances and residuals are kept for the next step when it is accepted.
    """
    M, P = sel.shape
    wsel = sel.astype(float)
    n_sel = np.maximum(wsel.sum(1), 1.0)
    q = np.where(sel[..., None], np.nan_to_num(pts), 0.0)
    c = q.sum(1) / n_sel[:, None]
    # (M,4,P) rows 1, x, y, z in the centred frames, zero on points not selected
    ph = np.empty((M, 4, P))
    ph[:, 0] = wsel
    for k in range(3):
        ph[:, k + 1] = np.where(sel, q[:, :, k] - c[:, k, None], 0.0)
    U, W = plucker_to_orth(_to_camera(L0, -c))
    KL = line_projection_matrix(K)
    ends_h = _ends_h(seg)
    lam = np.full(M, 1e-3)
    iters = np.zeros(M, dtype=np.int64)
    converged = np.zeros(M, dtype=bool)
    last_rel = np.full(M, np.inf)
    wr2, hub = float(cfg.line_reprojection_weight) ** 2, float(cfg.line_huber_m)
    eye = np.eye(4)
    a = np.arange(M)  # the active lines
    cur = _Lines(U, W)
    dist = cur.distances(ph[:, 1], ph[:, 2], ph[:, 3])
    hat_c = np.zeros((M, 3, 3))
    _hat_rows(c, hat_c)  # hat(c) v = c x v
    rl = cur.reprojection(KL, ends_h, hat_c)[0]
    for _ in range(int(cfg.line_lm_iterations)):
        if len(a) == 0:
            break
        la = _Lines(U[a], W[a])
        pa, wa = ph[a], wsel[a]
        w, hcost = _huber(dist, wa, hub)
        S = (pa * w[:, None, :]) @ np.swapaxes(pa, 1, 2)
        Hp, gp = la.point_normal_equations(S)
        rl, Jl = la.reprojection(KL, ends_h[a], hat_c[a], jacobian=True)
        JlT = np.swapaxes(Jl, 1, 2)
        H = Hp + wr2 * (JlT @ Jl)
        g = gp + wr2 * (JlT @ rl[..., None])[..., 0]
        cost = hcost + 0.5 * wr2 * np.einsum("mk,mk->m", rl, rl)
        A = H + lam[a, None, None] * (H * eye + 1e-9 * eye)
        delta = -np.linalg.solve(A, g[..., None])[..., 0]
        U2, W2 = orth_update(la.U, la.W, delta)
        trial = _Lines(U2, W2)
        dist2 = trial.distances(pa[:, 1], pa[:, 2], pa[:, 3])
        rl2 = trial.reprojection(KL, ends_h[a], hat_c[a])[0]
        cost2 = _huber(dist2, wa, hub, weights=False)[1] + 0.5 * wr2 * np.einsum("mk,mk->m", rl2, rl2)
        better = np.isfinite(cost2) & (cost2 <= cost)
        U[a[better]], W[a[better]] = U2[better], W2[better]
        dist = np.where(better[:, None], dist2, dist)
        lam[a] = np.where(better, lam[a] * 0.1, lam[a] * 10.0)
        iters[a] += 1
        step = np.sqrt(np.einsum("mk,mk->m", delta, delta))
        rel = np.where(better, (cost - cost2) / np.maximum(cost, 1e-300), 0.0)
        last_rel[a[better]] = rel[better]
        # Settled: the step, the relative gain, or the absolute gain (1e-6 m^2, far below lidar noise) is tiny.
        small = (step < 1e-7) | (better & ((rel <= 1e-4) | (step < 1e-5) | (cost - cost2 <= 1e-6)))
        done = small | (lam[a] > 1e6)
        converged[a[small]] = True
        a, dist = a[~done], dist[~done]
    # Robust (Huber) fits of points spread over a surface creep on slowly; a line whose last accepted step
    # gained under 1% is settled for a depth prior.
    active = np.zeros(M, dtype=bool)
    active[a] = True
    converged |= active & (last_rel < 1e-2)
    return _to_camera(orth_to_plucker(U, W), c), iters, converged


def _trim(L: np.ndarray, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M,6) lines, (M,2,3) end rays -> endpoints (M,2,3) on the line nearest each ray, min sin(ray, line) (M,)."""
    d = L[:, 3:] / np.linalg.norm(L[:, 3:], axis=1, keepdims=True)
    p0 = cross3(L[:, 3:], L[:, :3]) / np.sum(L[:, 3:] * L[:, 3:], axis=1, keepdims=True)
    r = rays / np.linalg.norm(rays, axis=2, keepdims=True)
    b = np.einsum("mki,mi->mk", r, d)
    e = np.einsum("mki,mi->mk", r, p0)
    denom = 1.0 - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (b * e - np.einsum("mi,mi->m", d, p0)[:, None]) / denom
    ends = p0[:, None, :] + t[..., None] * d[:, None, :]
    return ends, np.sqrt(np.clip(denom, 0.0, 1.0)).min(axis=1)


def _no_lines(M: int, P: int) -> LineDepthResult:
    """Every segment without a prior (empty scan, no segments or no lidar point near any)."""
    nan = np.full(M, np.nan)
    return LineDepthResult(
        endpoints=np.full((M, 2, 3), np.nan),
        reason=np.full(M, DEPTH_TOO_FEW_POINTS, dtype=np.int64),
        residual=nan,
        inliers=np.zeros(M, dtype=np.int64),
        reproj_px=nan.copy(),
        plucker=np.full((M, 6), np.nan),
        iterations=np.zeros(M, dtype=np.int64),
        band_index=np.full((M, P), -1, dtype=np.int64),
        inlier_mask=np.zeros((M, P), dtype=bool),
    )
