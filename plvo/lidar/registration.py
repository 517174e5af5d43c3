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

zeta. The paper prints exp(-2 (e_hat / e_bar)^2), e_hat = e at the tracker's relative pose, e_bar = e at the
registered one, and says it is there to penalise bad registrations. Registration minimises e, so e_hat >= e_bar
almost always: the printed formula is <= exp(-2) = 0.135, tends to 0 exactly when the tracker is off (scale
drift, which the factor is there to correct) and gives weight near 1 only when e_bar > e_hat, i.e. to a
registration that made the alignment *worse* than the tracker's pose. The default, `zeta_formula = "inverse"`,
exp(-2 (e_bar / e_hat)^2), swaps the two: exp(-2) when both agree, up to 1 when the registration is much better than
the tracker, near 0 for a registration worse than the tracker's pose. Measured (docs/results/defaults.md): a result
moved 0.5 m / 1 deg from the right one gets 0.010 on sequence 04 frames 10/13 (paper formula: > 0.3) and ~0 on
the synthetic town; in the whole system the paper formula let such a corrupted registration pull the synthetic
trajectory 0.63 m, the inverse one 1 cm (tests/plvo/backend/test_backend_in_system.py). On seq 04 the two formulas
give 0.74 / 0.58 / 0.42 % (paper) and 0.70 / 0.54 / 0.39 % (inverse) short-segment errors at 10 / 20 / 40 m (back end
with a 1 mm relative-pose sigma, 0.5 m voxels).
The dynamic range is limited by e's floor (~0.09 m on seq 04 at the right pose: plane noise, vegetation), so a
corruption of 0.3 m gives only exp(-2 * 1.35^2) = 0.026.

KITTI's scans: every return of the HDL-64E recordings sits about 0.2 deg too low in elevation (IMLS-SLAM found it;
CT-ICP and KISS-ICP raise every KITTI point by 0.205 deg). Uncorrected, registration between keyframes on sequence
04 pitches by -66 mdeg a keyframe pair on average (rms 68; yaw and roll rms ~20); raised, the mean pitch error is
0.4 mdeg (rms 19). `plvo.lidar.scan.registration_scan` does it, with the angle the dataset's Calibration carries
(`lidar_elevation_offset_deg`: 0.205 for KITTI, 0 for the synthetic town); it is applied to the scans registration
uses only, not to the depth priors, whose camera extrinsic KITTI calibrated on the uncorrected scans (measured on
04: correcting the scans the depth extraction sees too gave 0.67 % over 10/20/40 m against 0.58 %).

Speed: each keyframe's scan is downsampled once (`prepare`, reused as the next registration's target); normals
for e are computed only at the target points e uses (a few thousand, not the whole cloud); e uses 2000 source
points.
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
_MAX_EVAL_POINTS = 2000  # source points used for e; enough for a stable mean, bounds the cost


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


class SparseScan(PlvoError):
    """A scan with too few returns in range to register (a lidar that dropped out, a frame of the wrong data)."""


def preprocess(scan: np.ndarray, cfg: RegistrationConfig, name: str = "scan",
               voxel_m: float | None = None) -> o3d.geometry.PointCloud:
    """(N,3|4) lidar-frame points -> range-cropped (min_range_m..max_range_m), voxel-downsampled point cloud."""
    pts = np.asarray(scan)
    if pts.ndim != 2 or pts.shape[1] not in (3, 4):
        raise PlvoError(f"registration: {name} must have shape (N,3) or (N,4), got {pts.shape}")
    xyz = pts[:, :3]
    r2 = np.einsum("ni,ni->n", xyz, xyz)  # NaN/inf rows fail both comparisons and are dropped
    keep = np.flatnonzero((r2 >= cfg.min_range_m**2) & (r2 <= cfg.max_range_m**2))
    xyz = pts.take(keep, axis=0)[:, :3].astype(np.float64)  # whole rows first: faster than a strided mask
    if len(xyz) < 100:
        raise SparseScan(f"registration: {name} has {len(xyz)} points in range, need at least 100")
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    voxel = cfg.voxel_m if voxel_m is None else voxel_m
    return pc.voxel_down_sample(voxel) if voxel > 0 else pc


@dataclass
class PreparedScan:
    """A scan downsampled once for both of its roles: `fine` (voxel_m / 2, NDT target), `cloud` (voxel_m, NDT/ICP
    source, ICP target, alignment error; normals estimated on first use as a target). Each keyframe's scan is
    the source of one registration and the target of the next, so preparing it once halves the preprocessing."""

    fine: o3d.geometry.PointCloud
    cloud: o3d.geometry.PointCloud
    voxel_m: float

    def with_normals(self) -> o3d.geometry.PointCloud:
        if not self.cloud.has_normals():
            self.cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=10))
        return self.cloud


def prepare(scan: np.ndarray, cfg: RegistrationConfig, name: str = "scan") -> PreparedScan:
    """(N,3|4) lidar-frame points -> PreparedScan (range-cropped, downsampled to voxel_m / 2 and voxel_m)."""
    fine = preprocess(scan, cfg, name, voxel_m=cfg.voxel_m / 2)
    cloud = fine.voxel_down_sample(cfg.voxel_m) if cfg.voxel_m > 0 else fine
    return PreparedScan(fine, cloud, cfg.voxel_m)


def _prepared(scan: np.ndarray | PreparedScan, cfg: RegistrationConfig, name: str) -> PreparedScan:
    if isinstance(scan, PreparedScan):
        if scan.voxel_m != cfg.voxel_m:
            raise PlvoError(f"registration: {name} was prepared with voxel_m {scan.voxel_m}, config has {cfg.voxel_m}")
        return scan
    return prepare(scan, cfg, name)


def _nearest(src: np.ndarray, tree: cKDTree, T: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> (T p (N,3), distance to the nearest target point (inf beyond radius), its index (M beyond radius))."""
    p = se3.transform_points(T, src)
    dist, idx = tree.query(p, k=1, distance_upper_bound=radius)
    return p, dist, idx


def _plane_error(nearest: tuple[np.ndarray, np.ndarray, np.ndarray], dst: np.ndarray, normals: np.ndarray,
                 radius: float, subset: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """(e metres, (N,) bool within radius) from _nearest's answer for T, target points dst (M,3) and their normals.

    e = mean over `subset` (default: the points within radius at T) of min(|n . (T p - q)|, radius).
    """
    p, dist, idx = nearest
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


def _ndt(src: o3d.geometry.PointCloud, dst: o3d.geometry.PointCloud, init: np.ndarray, cfg: RegistrationConfig
         ) -> tuple[np.ndarray, float]:
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


def _icp(src: o3d.geometry.PointCloud, dst: o3d.geometry.PointCloud, init: np.ndarray, cfg: RegistrationConfig,
         method: str) -> tuple[np.ndarray, float]:
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


def _run(method: str, src: o3d.geometry.PointCloud, dst: o3d.geometry.PointCloud, init: np.ndarray,
         cfg: RegistrationConfig) -> tuple[np.ndarray, float]:
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


def align(scan_src: np.ndarray | PreparedScan, scan_dst: np.ndarray | PreparedScan, T_dst_src_init: np.ndarray,
          cfg: RegistrationConfig | None = None, T_cam_velo: np.ndarray | None = None) -> RegistrationResult:
    """(N,3|4),(M,3|4) lidar-frame scans (or PreparedScan), (4,4) initial T_dst_src (lidar), (4,4) T_cam_velo
    -> result."""
    cfg = cfg or RegistrationConfig()
    t0 = time.perf_counter()
    T_cv = np.eye(4) if T_cam_velo is None else np.asarray(T_cam_velo, dtype=float)
    init = np.asarray(T_dst_src_init, dtype=float)
    if init.shape != (4, 4) or not np.all(np.isfinite(init)):
        raise PlvoError(f"registration: T_dst_src_init must be a finite (4,4) matrix, got shape {init.shape}")
    src = _prepared(scan_src, cfg, "scan_src").cloud
    prepared_dst = _prepared(scan_dst, cfg, "scan_dst")
    dst_fine, dst = prepared_dst.fine, prepared_dst.cloud
    order = [cfg.method] + ([cfg.fallback] if cfg.method == "ndt" and cfg.fallback != "none" else [])
    T, fitness, method, converged = init, 0.0, order[0], False
    for m in order:
        if m not in ("ndt", "icp", "gicp"):
            raise PlvoError(f"registration: config field 'method'/'fallback' must be ndt, icp, gicp or none, got '{m}'")
        try:
            target = dst_fine if m == "ndt" else prepared_dst.with_normals()  # point-to-plane ICP needs normals
            T, fitness = _run(m, src, target, init, cfg)
            # open3d's result differs between identical calls in the last bits (~1e-17); the back end's discrete
            # decisions (outlier gates, kernels) amplified that into millimetres a keyframe and different runs.
            # Rounding far below the registration's accuracy makes runs repeat exactly.
            T, fitness = np.round(T, 9), round(float(fitness), 9)
            method, converged = m, True
            break
        except _Failed as exc:
            log.info("registration: %s", exc)
            method = m
    zeta, e_hat, e_bar = 0.0, float("nan"), float("nan")
    if converged:
        e_hat, e_bar = _errors(src, dst, init, T, cfg.max_correspondence_m)
        zeta = zeta_from_errors(e_hat, e_bar, cfg.zeta_formula)
    return RegistrationResult(T_dst_src=T, T_camdst_camsrc=se3.conjugate(T_cv, T), e_hat=e_hat, e_bar=e_bar,
                              zeta=zeta, method=method, converged=converged, fitness=fitness,
                              time_s=time.perf_counter() - t0)


def _pca_normals(q: np.ndarray, tree: cKDTree, idx: np.ndarray, k: int = 10) -> np.ndarray:
    """(M,3) points, their tree, (n,) indices -> (n,3) unit normals from the k nearest neighbours (as open3d's
    estimate_normals with KNN k), computed only where the error needs them (~5x cheaper than the whole cloud)."""
    _, nn = tree.query(q[idx], k=min(k, len(q)))
    nb = q[nn.reshape(len(idx), -1)]
    d = nb - nb.mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", d, d))
    return vecs[:, :, 0]


def _errors(src: o3d.geometry.PointCloud, dst: o3d.geometry.PointCloud, T_hat: np.ndarray, T_bar: np.ndarray,
            radius: float) -> tuple[float, float]:
    """-> (e_hat at the tracker's T_hat, e_bar at the registered T_bar) on the same source points."""
    p = np.asarray(src.points)
    if len(p) > _MAX_EVAL_POINTS:
        p = p[np.linspace(0, len(p) - 1, _MAX_EVAL_POINTS).astype(int)]
    q = np.asarray(dst.points)
    tree = cKDTree(q)
    at_bar, at_hat = (_nearest(p, tree, T, radius) for T in (T_bar, T_hat))  # each query once: they cost most
    need = np.unique(np.concatenate([idx[np.isfinite(dist)] for _, dist, idx in (at_bar, at_hat)]))
    n = np.zeros_like(q)
    if len(need):
        n[need] = _pca_normals(q, tree, need)
    e_bar, near = _plane_error(at_bar, q, n, radius)
    e_hat, _ = _plane_error(at_hat, q, n, radius, subset=near)
    return e_hat, e_bar
