"""Scan registration between keyframes (paper II-D, II-E): NDT seeded by the tracker, ICP/GICP fallback, zeta.

open3d 0.20's `registration_ndt` is a Gauss-Newton point-to-distribution NDT (target voxels as regularised
Gaussians, Mahalanobis outlier threshold, neighbour search 0 = own voxel, 1 = own + 6 face neighbours). It has no
convergence flag, so `align` judges the result itself. NDT has *failed* when it raises, when fewer than
`min_fitness` of the source points have a correspondence, when one more Gauss-Newton step from its result still
moves it (not converged), or when it lands more than `max_jump_m` / `max_jump_deg` from the initial guess. Then
the fallback (point-to-plane ICP with a Tukey kernel, or GICP) runs from the same guess and is judged likewise;
if it fails too, the result is the initial guess with converged = False and zeta = 0 (no factor).
Measured on sequence 04 (frames k, k+3): a 3 m coarse NDT pass followed by a 1 m pass recovers the relative pose
to a median 3.4 cm from initial errors of 20 % scale, 3 deg yaw or 1 m lateral; a single 1 m pass fails on
20 % scale errors (the straight highway gives NDT little grip along the road).

Alignment error e(T): the mean over source points of the truncated point-to-plane distance
min(|n_q . (T p - q)|, r) to the nearest target point q (normal n_q), r = max_correspondence_m, over the source
points that have a target neighbour within r at the *registered* pose (the same set for both poses, so that e_hat
and e_bar compare like with like). Point-to-plane, because after voxel downsampling point-to-point distances keep
a floor of about half a voxel at perfect alignment, which would hide the difference between good and bad poses;
truncated, so that the car driving ahead and the scan borders cannot dominate.

zeta (paper): exp(-2 (e_hat / e_bar)^2), e_hat = e at the tracker's relative pose, e_bar = e at the registered one.
What it does: registration minimises the alignment error, so e_hat >= e_bar almost always and zeta <= exp(-2)
= 0.135; it is largest when the tracker already agrees with the registration and tends to 0 as the tracker
disagrees (e.g. scale drift). So the paper's formula weakens the lidar factor exactly when the visual estimate is
off, and can only give weight near 1 when e_bar > e_hat, i.e. when the registration made the alignment *worse*
than the tracker's pose - the opposite of "penalising bad ICP". `zeta_formula = "inverse"`, exp(-2 (e_bar/e_hat)^2),
gives weight near 1 to a registration much better than the tracker and exp(-2) when both agree; it is offered,
not the default.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from plvo.config import RegistrationConfig
from plvo.errors import PlvoError
from plvo.geometry import se3

log = logging.getLogger(__name__)
_REG = o3d.pipelines.registration
_MAX_EVAL_POINTS = 4000  # source points used for e; enough for a stable mean, bounds the cost


@dataclass(frozen=True)
class RegistrationResult:
    """T_dst_src (4,4) lidar src -> lidar dst; T_camdst_camsrc (4,4) the same in camera frames; e_hat, e_bar in
    metres; zeta the relative-pose information scale; method "ndt"/"icp"/"gicp" (the one whose result is
    returned); converged False means every method failed and T is the initial guess; fitness = fraction of
    source points with a correspondence; time_s wall time of the whole call."""

    T_dst_src: np.ndarray
    T_camdst_camsrc: np.ndarray
    e_hat: float
    e_bar: float
    zeta: float
    method: str
    converged: bool
    fitness: float
    time_s: float


def preprocess(scan: np.ndarray, cfg: RegistrationConfig, name: str = "scan", voxel_m: float | None = None) -> o3d.geometry.PointCloud:
    """(N,3|4) lidar-frame points -> range-cropped (min_range_m..max_range_m), voxel-downsampled point cloud."""
    pts = np.asarray(scan)
    if pts.ndim != 2 or pts.shape[1] not in (3, 4):
        raise PlvoError(f"registration: {name} must have shape (N,3) or (N,4), got {pts.shape}")
    xyz = pts[:, :3].astype(np.float64)
    xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
    r = np.linalg.norm(xyz, axis=1)
    xyz = xyz[(r >= cfg.min_range_m) & (r <= cfg.max_range_m)]
    if len(xyz) < 100:
        raise PlvoError(f"registration: {name} has {len(xyz)} points in range, need at least 100")
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    voxel = cfg.voxel_m if voxel_m is None else voxel_m
    return pc.voxel_down_sample(voxel) if voxel > 0 else pc


def alignment_error(src: np.ndarray, tree: cKDTree, dst: np.ndarray, normals: np.ndarray, T: np.ndarray,
                    radius: float, subset: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """(N,3) src, target tree/points (M,3)/normals (M,3), (4,4) T_dst_src -> (e metres, (N,) bool within radius).

    e = mean over `subset` (default: the points within radius at T) of min(|n . (T p - q)|, radius).
    """
    p = se3.transform_points(T, src)
    dist, idx = tree.query(p, k=1, distance_upper_bound=radius)
    near = np.isfinite(dist)
    sel = near if subset is None else subset
    if not np.any(sel):
        return float(radius), near
    q_idx = np.minimum(idx, len(dst) - 1)
    plane = np.abs(np.sum(normals[q_idx] * (p - dst[q_idx]), axis=1))
    plane = np.where(near, np.minimum(plane, radius), radius)
    return float(np.mean(plane[sel])), near


def zeta_from_errors(e_hat: float, e_bar: float, formula: str = "paper") -> float:
    """The relative-pose information scale from the two alignment errors (see the module doc)."""
    e_bar = max(e_bar, 1e-9)
    e_hat = max(e_hat, 1e-9)
    if formula == "paper":
        return float(np.exp(-2.0 * (e_hat / e_bar) ** 2))
    if formula == "inverse":
        return float(np.exp(-2.0 * (e_bar / e_hat) ** 2))
    raise PlvoError(f"registration: config field 'zeta_formula' must be 'paper' or 'inverse', got '{formula}'")


def _ndt(src, dst, init, cfg: RegistrationConfig) -> tuple[np.ndarray, float]:
    """NDT on the source at voxel_m against the target at voxel_m / 2: NDT needs >= 6 target points a voxel, which a
    target downsampled to voxel_m cannot give 1 m voxels (fitness fell to 0.16 on sequence 04)."""
    T = init
    if cfg.ndt_coarse_resolution_m > 0:
        opt = _REG.NormalDistributionsTransformOption(
            voxel_size=cfg.ndt_coarse_resolution_m, max_iteration=max(cfg.max_iterations // 2, 1),
            outlier_threshold=25.0, neighbor_search_type=0)
        T = _REG.registration_ndt(src, dst, opt, T).transformation
    opt = _REG.NormalDistributionsTransformOption(
        voxel_size=cfg.ndt_resolution_m, max_iteration=cfg.max_iterations, neighbor_search_type=1)
    res = _REG.registration_ndt(src, dst, opt, T)
    # One more Gauss-Newton step from the result: a converged NDT barely moves.
    step = _REG.NormalDistributionsTransformOption(voxel_size=cfg.ndt_resolution_m, max_iteration=1,
                                                   neighbor_search_type=1)
    T_next = _REG.registration_ndt(src, dst, step, res.transformation).transformation
    moved = se3.inv(res.transformation) @ T_next
    if np.linalg.norm(moved[:3, 3]) > 0.02 or np.degrees(se3.rotation_angle(moved)) > 0.1:
        raise _Failed(f"ndt not converged (a further step moves {np.linalg.norm(moved[:3, 3]):.3f} m)")
    return np.asarray(res.transformation), float(res.fitness)


def _icp(src, dst, init, cfg: RegistrationConfig, method: str) -> tuple[np.ndarray, float]:
    crit = _REG.ICPConvergenceCriteria(max_iteration=cfg.max_iterations)
    if method == "gicp":
        res = _REG.registration_generalized_icp(src, dst, cfg.max_correspondence_m, init,
                                                _REG.TransformationEstimationForGeneralizedICP(), crit)
    else:
        est = _REG.TransformationEstimationPointToPlane(_REG.TukeyLoss(k=cfg.max_correspondence_m / 2))
        res = _REG.registration_icp(src, dst, cfg.max_correspondence_m, init, est, crit)
    return np.asarray(res.transformation), float(res.fitness)


class _Failed(Exception):
    pass


def _run(method: str, src, dst, init, cfg) -> tuple[np.ndarray, float]:
    try:
        T, fitness = _ndt(src, dst, init, cfg) if method == "ndt" else _icp(src, dst, init, cfg, method)
    except (RuntimeError, ValueError) as exc:  # open3d raises RuntimeError on degenerate input
        raise _Failed(f"{method} raised: {exc}") from None
    if not np.all(np.isfinite(T)):
        raise _Failed(f"{method} gave a non-finite transform")
    if fitness < cfg.min_fitness:
        raise _Failed(f"{method} fitness {fitness:.2f} < {cfg.min_fitness}")
    jump = se3.inv(init) @ T
    if np.linalg.norm(jump[:3, 3]) > cfg.max_jump_m or np.degrees(se3.rotation_angle(jump)) > cfg.max_jump_deg:
        raise _Failed(f"{method} jumped {np.linalg.norm(jump[:3, 3]):.2f} m from the initial guess")
    return T, fitness


def align(scan_src: np.ndarray, scan_dst: np.ndarray, T_dst_src_init: np.ndarray, cfg: RegistrationConfig | None = None,
          T_cam_velo: np.ndarray | None = None) -> RegistrationResult:
    """(N,3|4),(M,3|4) lidar-frame scans, (4,4) initial T_dst_src (lidar frames), (4,4) T_cam_velo -> RegistrationResult."""
    cfg = cfg or RegistrationConfig()
    t0 = time.perf_counter()
    T_cv = np.eye(4) if T_cam_velo is None else np.asarray(T_cam_velo, dtype=float)
    init = np.asarray(T_dst_src_init, dtype=float)
    if init.shape != (4, 4) or not np.all(np.isfinite(init)):
        raise PlvoError(f"registration: T_dst_src_init must be a finite (4,4) matrix, got shape {init.shape}")
    src = preprocess(scan_src, cfg, "scan_src")
    dst_fine = preprocess(scan_dst, cfg, "scan_dst", voxel_m=cfg.voxel_m / 2)
    dst = dst_fine.voxel_down_sample(cfg.voxel_m) if cfg.voxel_m > 0 else dst_fine
    dst.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=10))
    order = [cfg.method] + ([cfg.fallback] if cfg.method == "ndt" and cfg.fallback != "none" else [])
    T, fitness, method, converged = init, 0.0, order[0], False
    for m in order:
        if m not in ("ndt", "icp", "gicp"):
            raise PlvoError(f"registration: config field 'method'/'fallback' must be ndt, icp, gicp or none, got '{m}'")
        try:
            T, fitness = _run(m, src, dst_fine if m == "ndt" else dst, init, cfg)
            method, converged = m, True
            break
        except _Failed as exc:
            log.info("registration: %s", exc)
            method = m
    zeta, e_hat, e_bar = 0.0, float("nan"), float("nan")
    if converged:
        e_hat, e_bar = _errors(src, dst, init, T, cfg.max_correspondence_m)
        zeta = zeta_from_errors(e_hat, e_bar, cfg.zeta_formula)
    return RegistrationResult(T_dst_src=T, T_camdst_camsrc=T_cv @ T @ se3.inv(T_cv), e_hat=e_hat, e_bar=e_bar,
                              zeta=zeta, method=method, converged=converged, fitness=fitness,
                              time_s=time.perf_counter() - t0)


def _errors(src, dst, T_hat: np.ndarray, T_bar: np.ndarray, radius: float) -> tuple[float, float]:
    """-> (e_hat at the tracker's T_hat, e_bar at the registered T_bar) on the same source points."""
    p = np.asarray(src.points)
    if len(p) > _MAX_EVAL_POINTS:
        p = p[np.linspace(0, len(p) - 1, _MAX_EVAL_POINTS).astype(int)]
    q, n = np.asarray(dst.points), np.asarray(dst.normals)
    tree = cKDTree(q)
    e_bar, near = alignment_error(p, tree, q, n, T_bar, radius)
    e_hat, _ = alignment_error(p, tree, q, n, T_hat, radius, subset=near)
    return e_hat, e_bar
