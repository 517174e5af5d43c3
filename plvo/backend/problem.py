"""The back end's optimisation problem as plain arrays (paper II-D, II-E), independent of the tracker's map.

Frames: keyframe poses are T_world_cam (world = cam0 of frame 0); points and line endpoints are in the world;
point depth priors are z in the observing camera; line endpoint priors are 3D points in the observing camera
(the frame `DepthPriors.line_endpoints` uses: they are measured by that keyframe's scan and move with it).
Relative-pose factors hold T_i_j = T_cam_i_cam_j (the paper's delta T_ij, pose of j in i) with information zeta I.

Noise: the paper writes Sigma^P = 0.1 I and Sigma^L = 0.2 I and calls them covariances. We read the config's
`sigma_point_px` and `sigma_line` as standard deviations (gtsam's sigmas), i.e. information 1/sigma^2 = 100
for points and 25 for lines. Only their ratio to each other and to the relative-pose information zeta matters
for the optimum; the Huber thresholds `huber_point` and `huber_line` are in the residual's units (pixels) and are
whitened internally (k = huber / sigma). The line factor's third row (prior distance, metres) uses the same
sigma, as the paper's single Sigma^L does.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from plvo.errors import PlvoError
from plvo.geometry import se3
from plvo.geometry.camera import in_image, project

if TYPE_CHECKING:
    from collections.abc import Sequence


def _check(name: str, arr: np.ndarray, shape: tuple) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape)):
        raise PlvoError(f"BAProblem: field '{name}' must have shape {shape} (None = any), got {arr.shape}")
    return arr


def depth_prior_sigmas(rms: np.ndarray | None, factor: float) -> np.ndarray | None:
    """BAProblem.pt_depth_sigma of observations whose priors' plane fits left rms (m; NaN unknown): factor x rms,
    None when factor is 0 (backend.depth_prior_rms_factor)."""
    if rms is None or factor <= 0:
        return None
    return factor * np.asarray(rms, float)


def stereo_row_sigma(fx: float, baseline: float, depth: np.ndarray, sigma: float, depth_sigma: np.ndarray
                     ) -> np.ndarray:
    """(N,) sigma (px) of the virtual right column u_R = u_L - fx b / z of priors at depth z whose own sigma is
    depth_sigma (m; NaN or 0: none): the pixel sigma and the prior's, carried through du_R/dz = fx b / z^2, added in
    quadrature."""
    z = np.where(np.isfinite(depth) & (depth > 0), depth, np.inf)
    ds = np.where(np.isfinite(depth_sigma) & (depth_sigma > 0), depth_sigma, 0.0)
    return np.sqrt(sigma**2 + (fx * baseline * ds / z**2) ** 2)


@dataclass(frozen=True)
class BAProblem:
    """A window of keyframes, landmarks and factors.

    K (3,3); T_world_cam (K,4,4); fixed (K,) bool (held at their values); points (P,3) world;
    point_obs: pt_kf (O,), pt_idx (O,), pt_uv (O,2) px, pt_depth (O,) z metres in that camera or NaN;
    lines (L,2,3) world endpoints; line_obs: ln_kf (M,), ln_idx (M,), ln_seg (M,4) px, ln_prior (M,2,3) endpoints
    in that camera or NaN; relative poses: rel_ij (R,2) keyframe indices (i, j), rel_T (R,4,4) T_cam_i_cam_j,
    rel_zeta (R,) information scale; rel_weight (6,) per-component information in (rho, phi) order shared by all
    relative-pose factors, or (R,6) one row per factor (information = rel_zeta[r] * diag(rel_weight[r]); ones: the
    paper's zeta I). `relative_pose_weights` gives a factor's row. pt_depth_sigma (O,) metres: each depth prior's own
    uncertainty, added to what the factor's pixel sigma allows at its depth (None, NaN or 0: the pixel sigma alone).
    """

    K: np.ndarray
    T_world_cam: np.ndarray
    fixed: np.ndarray
    points: np.ndarray
    pt_kf: np.ndarray
    pt_idx: np.ndarray
    pt_uv: np.ndarray
    pt_depth: np.ndarray
    lines: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))
    ln_kf: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    ln_idx: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    ln_seg: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    ln_prior: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))
    rel_ij: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), int))
    rel_T: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    rel_zeta: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rel_weight: np.ndarray = field(default_factory=lambda: np.ones(6))
    pt_depth_sigma: np.ndarray | None = None

    def __post_init__(self) -> None:
        _check("K", self.K, (3, 3))
        n_kf = _check("T_world_cam", self.T_world_cam, (None, 4, 4)).shape[0]
        _check("fixed", self.fixed, (n_kf,))
        n_pt = _check("points", self.points, (None, 3)).shape[0]
        n_o = _check("pt_kf", self.pt_kf, (None,)).shape[0]
        _check("pt_idx", self.pt_idx, (n_o,))
        _check("pt_uv", self.pt_uv, (n_o, 2))
        _check("pt_depth", self.pt_depth, (n_o,))
        if self.pt_depth_sigma is not None:
            _check("pt_depth_sigma", self.pt_depth_sigma, (n_o,))
        n_ln = _check("lines", self.lines, (None, 2, 3)).shape[0]
        n_m = _check("ln_kf", self.ln_kf, (None,)).shape[0]
        _check("ln_idx", self.ln_idx, (n_m,))
        _check("ln_seg", self.ln_seg, (n_m, 4))
        _check("ln_prior", self.ln_prior, (n_m, 2, 3))
        n_r = _check("rel_ij", self.rel_ij, (None, 2)).shape[0]
        _check("rel_T", self.rel_T, (n_r, 4, 4))
        _check("rel_zeta", self.rel_zeta, (n_r,))
        _check("rel_weight", self.rel_weight, (n_r, 6) if np.ndim(self.rel_weight) == 2 else (6,))
        for name, idx, n in (
            ("pt_kf", self.pt_kf, n_kf), ("pt_idx", self.pt_idx, n_pt), ("ln_kf", self.ln_kf, n_kf),
            ("ln_idx", self.ln_idx, n_ln), ("rel_ij", self.rel_ij, n_kf),
        ):
            if np.size(idx) and (np.min(idx) < 0 or np.max(idx) >= n):
                raise PlvoError(f"BAProblem: field '{name}' has indices outside [0, {n})")
        if not np.all(np.isfinite(self.T_world_cam)) or not np.all(np.isfinite(self.points)):
            raise PlvoError("BAProblem: fields 'T_world_cam' and 'points' must be finite")
        if np.any(np.asarray(self.rel_zeta) < 0):
            raise PlvoError("BAProblem: field 'rel_zeta' must be >= 0")
        if np.any(~np.isfinite(self.rel_weight)) or np.any(np.asarray(self.rel_weight) < 0):
            raise PlvoError("BAProblem: field 'rel_weight' must be finite and >= 0")

    def depth_sigmas(self, rows: np.ndarray | None = None) -> np.ndarray | None:
        """The depth priors' own sigmas (m) of point observations rows (all by default; NaN or 0 where none is
        known); None when the problem has none (the factors are then computed exactly as without the weighing)."""
        if self.pt_depth_sigma is None:
            return None
        s = np.asarray(self.pt_depth_sigma, float)
        return s if rows is None else s[rows]

    def relative_pose_weights(self, rows: np.ndarray) -> np.ndarray:
        """The per-component information weights (len(rows),6) of the relative-pose factors rows."""
        w = np.asarray(self.rel_weight, dtype=float)
        return w[rows] if w.ndim == 2 else np.broadcast_to(w, (len(rows), 6))

    @property
    def n_keyframes(self) -> int:
        return int(self.T_world_cam.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_lines(self) -> int:
        return int(self.lines.shape[0])


@dataclass(frozen=True)
class BAResult:
    """Optimised T_world_cam (K,4,4), points (P,3) and line endpoints (L,2,3) in the world (landmarks left out of
    the optimisation, e.g. seen once, are returned unchanged; `point_used`/`line_used` say which were used);
    costs are gtsam's total (robust) graph error before and after; time_s is wall time of the whole call."""

    T_world_cam: np.ndarray
    points: np.ndarray
    lines: np.ndarray
    point_used: np.ndarray
    line_used: np.ndarray
    initial_cost: float
    final_cost: float
    iterations: int
    time_s: float


def relative_pose_information(sigma_m: float, sigma_deg: float,
                              rotation_ratio: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """BAProblem.rel_weight: the (6,) per-component information of relative-pose factors in (rho, phi) order from
    their translation and rotation sigmas; with rotation_ratio (R,) one row per factor, its rotation's scaled by it
    (plvo.tracking.corrections.GraphEdge.rotation_ratio)."""
    base = np.r_[np.full(3, sigma_m ** -2), np.full(3, np.radians(sigma_deg) ** -2)]
    if rotation_ratio is None:
        return base
    out = np.tile(base, (len(rotation_ratio), 1))
    out[:, 3:] *= np.asarray(rotation_ratio, float).reshape(-1, 1)
    return out


def _rand_rot(rng: np.random.Generator, sigma: float) -> np.ndarray:
    return se3.so3_exp(rng.normal(0.0, sigma, 3))


def make_synthetic_problem(
    n_kf: int = 6, n_points: int = 200, n_lines: int = 50, step_m: float = 1.0, seed: int = 0,
    prior_fraction: float = 0.5, pixel_noise: float = 0.0, sway_m: float = 0.1,
) -> BAProblem:
    """A KITTI-like window at its exact truth (callers perturb a copy with dataclasses.replace).

    Keyframes drive forward along +z, step_m apart, swaying sway_m left-right; landmarks 5-40 m ahead, within
    +-15 m left-right and -3..2 m in height (OpenCV y down). Each landmark is observed by every keyframe that sees
    it in the image; a `prior_fraction` of observations carry depth priors (exact, or with 5 cm noise on line
    endpoints when pixel_noise > 0; point depths stay exact). relative-pose factors link adjacent keyframes with the
    true relative pose and zeta = 1. The first keyframe is fixed.
    """
    rng = np.random.default_rng(seed)
    K = np.array([[707.1, 0.0, 601.9], [0.0, 707.1, 183.1], [0.0, 0.0, 1.0]])
    w, h = 1226, 370
    T = np.stack([se3.from_rt(_rand_rot(rng, 0.01), np.array([sway_m * np.sin(k), 0.0, step_m * k]))
                  for k in range(n_kf)])
    z0 = step_m * (n_kf - 1)
    pts = np.column_stack([rng.uniform(-15, 15, n_points), rng.uniform(-3, 2, n_points),
                           z0 + rng.uniform(5, 40, n_points)])
    mid = np.column_stack([rng.uniform(-12, 12, n_lines), rng.uniform(-3, 1.5, n_lines),
                           z0 + rng.uniform(6, 35, n_lines)])
    dirs = rng.normal(size=(n_lines, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    half = rng.uniform(1.0, 3.0, n_lines)[:, None]
    ends = np.stack([mid - half * dirs, mid + half * dirs], axis=1)
    pt_kf, pt_idx, pt_uv, pt_z, ln_kf, ln_idx, ln_seg, ln_pr = [], [], [], [], [], [], [], []
    for k in range(n_kf):
        T_cw = se3.inv(T[k])
        uv, z = project(K, se3.transform_points(T_cw, pts))
        ok = np.flatnonzero(in_image(uv, w, h) & (z > 0))
        pt_kf += [k] * len(ok)
        pt_idx += ok.tolist()
        pt_uv.append(uv[ok] + rng.normal(0, pixel_noise, (len(ok), 2)) if pixel_noise else uv[ok])
        pt_z.append(np.where(rng.random(len(ok)) < prior_fraction, z[ok], np.nan))
        ec = se3.transform_points(T_cw, ends.reshape(-1, 3)).reshape(-1, 2, 3)
        euv, ez = project(K, ec.reshape(-1, 3))
        euv = euv.reshape(-1, 2, 2)
        ok = np.flatnonzero(np.all(in_image(euv.reshape(-1, 2), w, h).reshape(-1, 2), axis=1))
        ln_kf += [k] * len(ok)
        ln_idx += ok.tolist()
        ln_seg.append(euv[ok].reshape(-1, 4) + (rng.normal(0, pixel_noise, (len(ok), 4)) if pixel_noise else 0))
        pr = ec[ok] + (rng.normal(0, 0.05, (len(ok), 2, 3)) if pixel_noise else 0.0)  # lidar line fits: ~5 cm
        pr[rng.random(len(ok)) >= prior_fraction] = np.nan
        ln_pr.append(pr)
    rel_ij = np.array([[k, k + 1] for k in range(n_kf - 1)], int).reshape(-1, 2)
    rel_T = np.stack([se3.inv(T[i]) @ T[j] for i, j in rel_ij]) if len(rel_ij) else np.zeros((0, 4, 4))
    return BAProblem(
        K=K, T_world_cam=T, fixed=np.arange(n_kf) == 0, points=pts,
        pt_kf=np.array(pt_kf, int), pt_idx=np.array(pt_idx, int), pt_uv=np.concatenate(pt_uv),
        pt_depth=np.concatenate(pt_z), lines=ends, ln_kf=np.array(ln_kf, int), ln_idx=np.array(ln_idx, int),
        ln_seg=np.concatenate(ln_seg), ln_prior=np.concatenate(ln_pr), rel_ij=rel_ij, rel_T=rel_T,
        rel_zeta=np.ones(len(rel_ij)),
    )
