"""Loop verification by registering two keyframes' local maps: point-to-plane ICP, accepted only when unambiguous.

A loop edge found without image matches (by the lidar place recognition, plvo.loop.lidar_place, or a bag-of-words
candidate with too few matches with depth) rests on the lidar alone. The query's local map (cropped to
`loop.scan_verify_radius_m` around its keyframe) is registered onto the candidate's (open3d point-to-plane ICP,
Tukey kernel, correspondences within 2 m, then 1 m on the maps thinned to twice their voxel, then 0.5 m on the maps
themselves) from the place recognition's relative pose or the odometry's, its height set so that the two maps'
ground lines up (`_level`), and the result must be unambiguous:

- converged: one more Gauss-Newton step of the last stage (its correspondences, its Tukey weights) moves it less
  than 1 cm and 0.05 degrees;
- overlap: at least `loop.scan_min_overlap` of the query's points have a candidate point within 0.5 m;
- error: the RMS point-to-plane distance of those (each capped at 0.5 m) is at most `loop.scan_max_error_m`;
- constrained: the smallest eigenvalue of the point-to-plane Hessian sum(J^T J) / N over the correspondences within
  0.2 m of their plane, J = [(p x n)^T / 10 m, n^T] (a rotation as the motion it gives 10 m away), is at least
  `loop.scan_min_constraint`. It is the share of the normals' energy along the least constrained direction: a
  corridor or a highway between noise walls has next to none along its axis;
- unique: ICP restarted `loop.scan_basin_m` to either side along the least constrained translation comes back
  within `loop.scan_unique_m`. A street whose facades line up after a shift by a building or two has a second
  minimum there, which the constraint alone may not show.

Measured on local maps of the twins (deskewed with the ground truth) and the town, 0.5 m voxels: true revisits,
started a metre and two degrees off, end 2-7 mm and 0.005-0.03 degrees from the ground truth with overlap
0.6-0.99, error 0.03-0.06 m, constraint 0.028-0.137, and restarts 3 m away come back within 0.00-0.11 m, but
on two stretches of the KITTI 04 twin's country road, whose hedges and fences repeat, they end 3.3-3.8 m away
and those pairs (4 of 12 there) are refused: a loop missed, not a false one. Other
places lined up as if they were the same (one street's keyframes 12-50 m apart, the town's look-alike streets
after different corners of one block) fit well: overlap 0.35-0.8, error 0.06-0.14 m (facades match when slid
along a street); but constraint 0.002-0.034 and restarts that end 0.47-7.4 m away: the restarts alone refuse every
one of them, the constraint alone all but one (0.034). On the twins' raw (swept) scans the error of true
revisits rises to 0.12 m and a registration between opposite directions is biased by 0.05-0.18 m: the caller
deskews the scans.
Cost: 0.2-0.5 s a verification (0.3-1.3 s when refused after the restarts) on the project's loaded 2-core machine,
three quarters of it in open3d's ICP, which builds its search tree again at each call.

The last ICP stage runs to its fixed point (criteria 1e-12), which starts a metre apart reach to within 1e-9; the
result is rounded to 1e-5 (`_round`), so a start a few centimetres different, as map_closures' RANSAC may give
from run to run, ends on the same edge, and a run inline, in a thread or in a process gives the same.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from plvo.config import LoopConfig
from plvo.geometry import se3

_REG = o3d.pipelines.registration
LEVER_M = 10.0  # a rotation counts as the motion it gives this far away, against a translation
INLIER_RESIDUAL_M = 0.2  # correspondences this close to their plane make the Hessian (4x the twins' plane noise)
MIN_POINTS = 500
GROUND_RADIUS_M = 15.0  # the ground around the candidate's sensor that sets the start's height (`_level`)
# (max correspondence m, which source cloud, iterations): a wide first stage for a start a metre or two off
_STAGES = ((2.0, "coarse", 50), (1.0, "coarse", 50), (0.5, "fine", 60))


@dataclass(frozen=True)
class MapAlignment:
    """T_dst_src (4,4) lidar frame of the query map -> lidar frame of the candidate's; overlap (share of the
    query's points with a candidate point within 0.5 m), error_m (RMS point-to-plane distance), constraint (smallest
    eigenvalue of the Hessian per point), basin_m (farthest a restart ended from the result; NaN when not run),
    n_points (query points registered), reason (why refused; "" when accepted), time_s."""

    T_dst_src: np.ndarray
    overlap: float
    error_m: float
    constraint: float
    basin_m: float
    n_points: int
    reason: str
    time_s: float

    @property
    def accepted(self) -> bool:
        return not self.reason

    def summary(self) -> str:
        basin = "" if not np.isfinite(self.basin_m) else f", restarts within {self.basin_m:.2f} m"
        return (f"overlap {self.overlap:.2f}, error {self.error_m:.3f} m, constraint {self.constraint:.3f}{basin}")


def _cloud(pts: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(pts, np.float64)))


def _icp(src: dict[str, o3d.geometry.PointCloud], dst: o3d.geometry.PointCloud, T: np.ndarray,
         stages: tuple[tuple[float, str, int], ...] = _STAGES) -> np.ndarray:
    for corr, which, iterations in stages:
        est = _REG.TransformationEstimationPointToPlane(_REG.TukeyLoss(k=corr))
        crit = _REG.ICPConvergenceCriteria(relative_fitness=1e-12, relative_rmse=1e-12, max_iteration=iterations)
        T = np.asarray(_REG.registration_icp(src[which], dst, corr, T, est, crit).transformation)
    return T


@dataclass(frozen=True)
class _Fit:
    overlap: float
    error_m: float
    H: np.ndarray  # (6,6) point-to-plane Hessian per query point, rotation (at LEVER_M) then translation
    weakest: np.ndarray  # (3,) the least constrained translation
    step_m: float  # a Gauss-Newton step on these correspondences: translation (m) and rotation (deg)
    step_deg: float


def _measure(p: np.ndarray, tree: cKDTree, q: np.ndarray, normals: np.ndarray, voxel_m: float) -> _Fit:
    """Query points p (N,3) already in the candidate's frame -> how they fit the candidate's map."""
    dist, idx = tree.query(p, distance_upper_bound=voxel_m)
    near = np.isfinite(dist)
    if near.sum() < 6:
        return _Fit(float(near.mean()), float("inf"), np.zeros((6, 6)), np.array([1.0, 0.0, 0.0]), np.inf, np.inf)
    n = normals[idx[near]]
    r = np.einsum("ij,ij->i", n, p[near] - q[idx[near]])
    error = float(np.sqrt(np.mean(np.minimum(r * r, voxel_m * voxel_m))))
    good = np.abs(r) < INLIER_RESIDUAL_M
    pg, ng = p[near][good], n[good]
    J = np.hstack([np.cross(pg, ng) / LEVER_M, ng])
    H = J.T @ J / len(p)
    _, vecs = np.linalg.eigh(H[3:, 3:])
    # the last ICP stage's own step (its correspondences and Tukey weights), which its fixed point makes zero
    Ja = np.hstack([np.cross(p[near], n) / LEVER_M, n])
    w = np.sqrt(np.clip(1.0 - (r / voxel_m) ** 2, 0.0, None) ** 2)
    step = -np.linalg.lstsq(Ja * w[:, None], r * w, rcond=None)[0]  # (rotation x LEVER_M, translation)
    return _Fit(float(near.mean()), error, H, vecs[:, 0], float(np.linalg.norm(step[3:])),
                float(np.degrees(np.linalg.norm(step[:3]) / LEVER_M)))


def align_maps(src: np.ndarray, dst: np.ndarray, T_init: np.ndarray, cfg: LoopConfig, voxel_m: float = 0.5
               ) -> MapAlignment:
    """Register local map src (N,3) (the query's, its lidar frame) onto dst (M,3) (the candidate's) from T_init
    (4,4) T_dst_src; voxel_m is the maps' voxel -> the alignment and whether it is unambiguous (module doc)."""
    t0 = time.perf_counter()
    T_init = np.asarray(T_init, float)
    src = np.asarray(src, np.float64)
    src = src[np.einsum("ij,ij->i", src[:, :2], src[:, :2]) <= cfg.scan_verify_radius_m ** 2]

    def refuse(reason: str, T: np.ndarray = T_init, overlap: float = 0.0, error: float = float("nan"),
               constraint: float = 0.0, basin: float = float("nan")) -> MapAlignment:
        return MapAlignment(T, overlap, error, constraint, basin, len(src), reason, time.perf_counter() - t0)

    if len(src) < MIN_POINTS or len(dst) < MIN_POINTS:
        return refuse(f"too few points to register ({len(src)} query, {len(dst)} candidate)")
    fine = _cloud(src)
    clouds = {"fine": fine, "coarse": fine.voxel_down_sample(2.0 * voxel_m)}
    target = _cloud(dst)
    target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=10))
    T = _round(_icp(clouds, target, _level(src, dst, T_init)))
    q = np.asarray(target.points)
    normals = np.asarray(target.normals)
    fit = _measure(se3.transform_points(T, src), cKDTree(q), q, normals, voxel_m)
    overlap, error, weak = fit.overlap, fit.error_m, fit.weakest
    constraint = float(np.linalg.eigvalsh(fit.H)[0])
    if not (np.isfinite(fit.step_m) and np.isfinite(fit.step_deg)):  # too few points near the map to measure it
        return refuse(f"no pose: the registration left the local maps apart ({round(overlap * len(src))} of "
                      f"{len(src)} query points within {voxel_m:g} m of the candidate's map)", T, overlap, error,
                      constraint)
    if fit.step_m > 0.01 or fit.step_deg > 0.05:
        return refuse(f"the registration did not converge (one more step would move it {fit.step_m:.3f} m, "
                      f"{fit.step_deg:.3f} deg)", T, overlap, error, constraint)
    found = f"overlap {overlap:.2f}, error {error:.3f} m, constraint {constraint:.3f}"
    if overlap < cfg.scan_min_overlap:
        return refuse(f"the local maps overlap too little ({found}; need overlap {cfg.scan_min_overlap})", T,
                      overlap, error, constraint)
    if error > cfg.scan_max_error_m:
        return refuse(f"the local maps do not fit ({found}; need error <= {cfg.scan_max_error_m} m)", T, overlap,
                      error, constraint)
    if constraint < cfg.scan_min_constraint:
        return refuse(f"ambiguous: the registration is not constrained in every direction ({found}; need "
                      f"constraint {cfg.scan_min_constraint}; least along {_direction(weak)})", T, overlap, error,
                      constraint)
    basin = 0.0
    for sign in (-1.0, 1.0):
        start = T.copy()
        start[:3, 3] += sign * cfg.scan_basin_m * weak
        end = _icp(clouds, target, start, _STAGES[:2])
        basin = max(basin, float(np.linalg.norm(end[:3, 3] - T[:3, 3])))
    if basin > cfg.scan_unique_m:
        return refuse(f"ambiguous: a registration started {cfg.scan_basin_m:.1f} m along {_direction(weak)} ends "
                      f"{basin:.2f} m away ({found})", T, overlap, error, constraint, basin)
    return MapAlignment(T, overlap, error, constraint, basin, len(src), "", time.perf_counter() - t0)


def _level(src: np.ndarray, dst: np.ndarray, T_init: np.ndarray) -> np.ndarray:
    """T_init with its height set so that the two maps' ground (the 10th percentile of height within GROUND_RADIUS_M
    of the candidate's sensor) lines up. The place recognition aligns density images from above and says nothing
    of height, and two passes over one place can differ in it by metres: the KITTI twins' ground truth, which they
    keep, puts some revisits metres higher than the first pass (up to 7.6 m on 08, docs/twins.md); from 7 m off the
    first ICP stage (2 m) does not converge (tests/plvo/loop/test_lidar_place.py)."""
    moved = se3.transform_points(T_init, src)
    ground = []
    for pts in (moved, dst):
        near = pts[np.einsum("ij,ij->i", pts[:, :2], pts[:, :2]) <= GROUND_RADIUS_M ** 2]
        if len(near) < MIN_POINTS:
            return T_init
        ground.append(float(np.percentile(near[:, 2], 10)))
    out = T_init.copy()
    out[2, 3] += ground[1] - ground[0]
    return out


def _round(T: np.ndarray) -> np.ndarray:
    """The registration's fixed point, the same from any start in its basin: starts a metre apart end within 1e-9
    of one another (open3d's sums differ in the last bits even between identical calls), so rounding to 1e-5 (10
    micrometres, 0.0006 degrees), far below the accuracy, gives one edge; then a proper rotation again."""
    return se3.orthonormalize(np.round(T, 5))


def _direction(v: np.ndarray) -> str:
    """A unit vector of the candidate's lidar frame (x forward, y left, z up) in words."""
    names = ("x (forward)", "y (left)", "z (up)")
    k = int(np.argmax(np.abs(v)))
    return f"{names[k]} ({v[0]:+.2f}, {v[1]:+.2f}, {v[2]:+.2f})"
