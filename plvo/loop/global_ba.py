"""Global bundle adjustment after a loop's pose graph (paper II-F, "loop correction is performed using a global
bundle adjustment algorithm [4]", ORB-SLAM2's last step).

The graph: every keyframe the loop closer knows (the first one held fixed), relative-pose edges (below), and every
point landmark that two or more of those keyframes observe, through gtsam's C++ stereo factor where the
observation has a lidar depth prior and the monocular projection factor otherwise (the back end's point factors,
`plvo.backend.factors`). It starts from the pose graph's solution, with the landmarks moved along with it.

Edges and weights: the back end's registration factors between consecutive keyframes, with their zeta and its
weights, where the back end ran (otherwise the pose graph's odometry edges, ~1e-4 of that); each loop edge as
strong as a registration factor (zeta 1). With the pose graph's 5 cm / 0.01 rad edges instead, the thousands of
point factors, which carry the depth priors' scale and the drift, overruled them: the adjustment undid the loop
at the loop keyframe (0.002 -> 0.27 m in the System loop test) and, without the registrations, pulled the
keyframes between towards the visual scale (0.09 -> 0.33 m). The map's landmarks are not fused across the loop
(ORB-SLAM2 fuses them), so the loop edge is the only constraint that closes it.

The result is applied only when it is a refinement (`implausible`): finite, a lower cost, and no keyframe moved
further from the pose graph's solution than a fraction of the pose graph's own correction.

Lines are not in this graph: gtsam has no 3D line type, and a Python factor per line made an 8-keyframe window
take seconds (factors.py); a map-wide graph of them would take minutes. Line landmarks move rigidly with the
keyframe that created them, as after the pose graph.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from plvo.backend.factors import optimize_gtsam
from plvo.backend.problem import BAProblem, BAResult, depth_prior_sigmas, relative_pose_information
from plvo.config import BackendConfig, LoopConfig
from plvo.geometry import se3
from plvo.geometry.camera import project
from plvo.tracking.map import Observations
from plvo.tracking.point_budget import budget_share, owner_ranks

log = logging.getLogger(__name__)


def build_problem(K: np.ndarray, poses: np.ndarray, edges: list[tuple[int, int, np.ndarray, float]],
                  obs: Observations, positions: np.ndarray, depth: np.ndarray, cfg: LoopConfig,
                  backend_cfg: BackendConfig, rotation_ratio: np.ndarray | None = None,
                  depth_rms: np.ndarray | None = None) -> tuple[BAProblem, np.ndarray]:
    """The global problem -> (BAProblem, landmark id of each problem point).

    poses (K,4,4) T_world_cam in the order of the closer's keyframes; edges (i, j, T_i_j, zeta) by index into
    poses: relative-pose factors with information zeta x the back end's (`edge_weights` says which zeta);
    obs: point observations whose `keyframe` is already an index into poses; positions (P,3) world positions of
    np.unique(obs.landmark); depth (len(obs),) z of each observation or NaN; rotation_ratio (len(edges),) each
    edge's rotation information against its translation's (GraphEdge.rotation_ratio; default 1); depth_rms
    (len(obs),) each prior's plane fit rms (m), which weighs it (backend.depth_prior_rms_factor).

    Observations further than cfg.global_ba_max_px from their landmark's projection are left out: the map holds
    some gross ones (where tracking was lost and re-initialised), and 0.1 px factors with a Huber kernel still
    let a few hundred 50-px residuals drag the keyframes of a turn by metres. Of the points two keyframes still
    see, at most cfg.global_ba_max_points are kept (`point_budget`): the cost of an iteration is then bounded by the
    keyframes and the budget, not by the map (81k points took 64 s at 1521 keyframes of the 4541-frame soak).
    """
    lm_ids, idx = np.unique(obs.landmark, return_inverse=True)
    positions = np.asarray(positions, float)
    keep = reprojection_errors(K, poses, positions[idx], obs.keyframe, obs.measurement) <= cfg.global_ba_max_px
    keep &= np.bincount(idx[keep], minlength=len(lm_ids))[idx] >= 2  # one view left: nothing to adjust
    keep &= np.isin(idx, point_budget(idx[keep], np.asarray(obs.keyframe, int)[keep], cfg.global_ba_max_points))
    used, pt_idx = np.unique(idx[keep], return_inverse=True)
    weight = relative_pose_information(backend_cfg.sigma_relative_pose, backend_cfg.sigma_relative_rotation_deg,
                                       rotation_ratio)
    sigma = depth_prior_sigmas(depth_rms, backend_cfg.depth_prior_rms_factor)
    log.debug("global BA: %d keyframes, %d edges, %d points, %d of %d observations kept", len(poses), len(edges),
              len(used), int(keep.sum()), len(keep))
    problem = BAProblem(
        K=np.asarray(K, float), T_world_cam=np.asarray(poses, float), fixed=np.arange(len(poses)) == 0,
        points=positions[used], pt_kf=np.asarray(obs.keyframe, int)[keep], pt_idx=pt_idx,
        pt_uv=np.asarray(obs.measurement, float)[keep], pt_depth=np.asarray(depth, float)[keep],
        rel_ij=np.array([(i, j) for i, j, _, _ in edges], int).reshape(-1, 2),
        rel_T=np.array([T for _, _, T, _ in edges], float).reshape(-1, 4, 4),
        rel_zeta=np.array([z for *_, z in edges], float), rel_weight=weight,
        pt_depth_sigma=None if sigma is None else sigma[keep],
    )
    return problem, lm_ids[used]


def point_budget(point: np.ndarray, keyframe: np.ndarray, max_points: int) -> np.ndarray:
    """Observations' point (n,) and keyframe (n,) -> the points to keep (ascending): all of them when there are
    at most max_points, else the same number for every keyframe (each point counted for the first keyframe that
    observes it, the most-viewed first), so the adjustment's cost stays bounded as the map grows while every
    keyframe keeps its share of the constraints."""
    point, keyframe = np.asarray(point, np.int64), np.asarray(keyframe, np.int64)
    points = np.unique(point)
    if max_points <= 0 or len(points) <= max_points:
        return points
    owner = np.full(point.max() + 1, np.iinfo(np.int64).max)
    np.minimum.at(owner, point, keyframe)
    views = np.bincount(point)
    rank = owner_ranks(owner[points], views[points], points)
    return points[rank < budget_share(rank, max_points)]


def pose_graph_zeta(cfg: LoopConfig, backend_cfg: BackendConfig) -> float:
    """Information scale of the pose graph's odometry edge against the back end's relative-pose factor (~1e-4)."""
    return (backend_cfg.sigma_relative_pose / cfg.odom_sigma_trans) ** 2


def reprojection_errors(K: np.ndarray, poses: np.ndarray, points: np.ndarray, kf: np.ndarray,
                        uv: np.ndarray) -> np.ndarray:
    """(K,4,4) T_world_cam, (N,3) world points, (N,) keyframe index, (N,2) px -> (N,) pixel errors (inf behind)."""
    T_cw = se3.inv_batch(np.asarray(poses, float))[np.asarray(kf, int)]
    proj, _ = project(np.asarray(K, float), np.einsum("nij,nj->ni", T_cw[:, :3, :3], points) + T_cw[:, :3, 3])
    err = np.linalg.norm(proj - uv, axis=1)
    return np.where(np.isfinite(err), err, np.inf)


def optimize(problem: BAProblem, backend_cfg: BackendConfig, loop_cfg: LoopConfig, use_depth_priors: bool,
             stereo_baseline_m: float) -> BAResult:
    """gtsam Levenberg-Marquardt over the global problem, at most loop_cfg.global_ba_iterations iterations."""
    cfg = dataclasses.replace(backend_cfg, iterations=int(loop_cfg.global_ba_iterations))
    res = optimize_gtsam(problem, cfg, use_depth_priors=use_depth_priors, use_lines=False,
                         stereo_baseline_m=stereo_baseline_m)
    log.info("global BA: %d keyframes, %d points, cost %.4g -> %.4g in %d iterations, %.2f s", problem.n_keyframes,
             int(res.point_used.sum()), res.initial_cost, res.final_cost, res.iterations, res.time_s)
    return res


def implausible(poses: np.ndarray, res: BAResult, cfg: LoopConfig, correction_m: float = 0.0) -> str:
    """Why a global BA result must not be applied, or "" when it may.

    poses (K,4,4): the pose graph's solution it started from; correction_m: how far the pose graph moved the
    keyframes (the largest move). The pose graph has made the large correction; the global adjustment refines
    it, by at most cfg.global_ba_max_move_m + cfg.global_ba_move_fraction x correction_m for any keyframe. A
    larger move means landmarks that disagree with the pose graph pulled the keyframes (seen where tracking was
    lost in a sharp turn and re-initialised: old and new landmarks there differ by metres).
    """
    if not (np.all(np.isfinite(res.T_world_cam)) and np.all(np.isfinite(res.points[res.point_used]))):
        return "non-finite values"
    if res.final_cost > res.initial_cost:
        return f"the cost rose from {res.initial_cost:.4g} to {res.final_cost:.4g}"
    move = np.linalg.norm(res.T_world_cam[:, :3, 3] - np.asarray(poses)[:, :3, 3], axis=1)
    limit = cfg.global_ba_max_move_m + cfg.global_ba_move_fraction * correction_m
    if move.max() > limit:
        return (f"it would move keyframe {int(move.argmax())} (in the closer's order) by {move.max():.2f} m "
                f"(at most {limit:.2f} m after a {correction_m:.2f} m pose-graph correction)")
    return ""
