"""Geometric verification of a loop candidate (paper II-F): descriptor matching, PnP/PnL, scan registration.

Between the query keyframe Q (new) and the candidate C (old): ORB and LBD descriptors are matched (ratio test,
mutual), C's 3D points and lines (its depth priors, C's camera frame) against Q's keypoints and segments give
T_C_Q by PnP/PnL in RANSAC (poselib, through plvo.tracking.pnpl.solve_pnpl with C's camera as the world), which
needs LoopConfig.min_inliers inliers, of which LoopConfig.min_off_plane must lie off the plane that holds most
of them (on the synthetic town, every false loop that passed PnP was supported only by the tiled road texture:
at most 4 inliers off the road plane, against 12-84 for true revisits); then, when both keyframes carry a scan,
scan registration (plvo.lidar.registration.align) refines T_C_Q from the visual estimate and must converge.
Each rejection carries its reason and the stage that refused it (`Verification.stage`).

`verify_by_registration` verifies without image matches: the two keyframes' local maps are registered
(plvo.loop.map_registration) from a relative pose found otherwise, for the candidates of the lidar place
recognition (plvo.loop.lidar_place) and for bag-of-words candidates refused only for too few image matches with
depth or PnP/PnL inliers.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from plvo.config import LoopConfig, RegistrationConfig, TrackingConfig
from plvo.errors import PlvoError
from plvo.geometry import se3
from plvo.geometry.camera import backproject
from plvo.lidar.registration import align
from plvo.loop.map_registration import MapAlignment, align_maps
from plvo.loop.scans import scan_points
from plvo.tracking.pnpl import solve_pnpl
from plvo.types import DepthPriors, FeatureSet

log = logging.getLogger(__name__)

# The checks a verification can fail, in order (Verification.stage).
TOO_FAR, MATCHES, PNP, PLANE, REGISTRATION, ODOMETRY = "too far", "matches", "pnp", "plane", "registration", "odometry"
STAGES = (TOO_FAR, MATCHES, PNP, PLANE, REGISTRATION, ODOMETRY)
# The detectors that propose candidates (Verification.detector), in words as reasons and logs name them.
SOURCES = {"bow": "bag of words", "lidar": "lidar place"}


@dataclass(frozen=True)
class LoopKeyframe:
    """What the loop closer keeps of a keyframe.

    T_world_cam (4,4) the current estimate; keypoints (N,2) px, descriptors (N,32) uint8 ORB, points_cam (N,3)
    camera-frame 3D points from depth priors (NaN rows where none); segments (M,4) px, line_descriptors (M,32)
    uint8 LBD, lines_cam (M,2,3) camera-frame 3D endpoints (NaN where none); scan (P,3|4) lidar frame or None.
    """

    kf_id: int
    T_world_cam: np.ndarray
    keypoints: np.ndarray
    descriptors: np.ndarray
    points_cam: np.ndarray
    segments: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 4)))
    line_descriptors: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 32), np.uint8))
    lines_cam: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 2, 3)))
    scan: np.ndarray | None = None
    frame_index: int = -1

    @classmethod
    def from_features(cls, kf_id: int, T_world_cam: np.ndarray, features: FeatureSet, priors: DepthPriors,
                      K: np.ndarray, scan: np.ndarray | None = None, frame_index: int = -1) -> LoopKeyframe:
        """Build from a keyframe's FeatureSet and DepthPriors (camera frame, (3,3) K) and its lidar-frame scan."""
        pts = backproject(K, features.keypoints, priors.point_depth)
        pts[~priors.point_valid] = np.nan
        lines = np.array(priors.line_endpoints, dtype=float).reshape(-1, 2, 3)
        lines[~priors.line_valid] = np.nan
        return cls(kf_id, np.asarray(T_world_cam, float), features.keypoints, features.descriptors, pts,
                   features.segments, features.line_descriptors, lines, scan, frame_index)


@dataclass(frozen=True)
class Verification:
    """Outcome of verifying candidate C for query Q.

    accepted; T_cand_query (4,4) camera Q -> camera C (the loop edge; identity when rejected); counts of
    descriptor matches usable for PnP/PnL and of their inliers; registered: scan registration refined the pose;
    reg_fitness; reason: why rejected, or a summary when accepted; time_s. detector: who proposed the candidate
    ("bow": the bags of words, "lidar": the lidar place recognition); stage: the check that refused it (one of
    STAGES, "" when accepted); place_inliers: the place recognition's density-map inliers (0 for the bags of
    words'); alignment: the local maps' registration when one ran (verify_by_registration).
    """

    query_id: int
    cand_id: int
    accepted: bool
    T_cand_query: np.ndarray
    n_point_matches: int
    n_line_matches: int
    n_point_inliers: int
    n_line_inliers: int
    registered: bool
    reg_fitness: float
    reason: str
    time_s: float
    detector: str = "bow"
    stage: str = ""
    place_inliers: int = 0
    alignment: MapAlignment | None = None

    @property
    def source(self) -> str:
        """The detector in words, as reasons and logs name it."""
        return SOURCES[self.detector]

    @property
    def support(self) -> int:
        """The candidate's inliers: the place recognition's density-map inliers for a lidar place, else PnP/PnL's."""
        return self.place_inliers if self.detector == "lidar" else self.n_point_inliers + self.n_line_inliers

    @property
    def for_lack_of_matches(self) -> bool:
        """Refused only because the images gave too few matches with depth or PnP/PnL inliers."""
        return not self.accepted and self.stage in (MATCHES, PNP)


def match_binary(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float, max_dist: int) -> np.ndarray:
    """(N,32),(M,32) uint8 -> (K,2) int index pairs (a, b): ratio test, distance bound, mutual best match."""
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2), np.int64)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    knn = bf.knnMatch(np.ascontiguousarray(desc_a), np.ascontiguousarray(desc_b), k=2)
    back = {m.queryIdx: m.trainIdx for m in bf.match(np.ascontiguousarray(desc_b), np.ascontiguousarray(desc_a))}
    pairs = [(m[0].queryIdx, m[0].trainIdx) for m in knn
             if len(m) == 2 and m[0].distance <= max_dist and m[0].distance < ratio * m[1].distance
             and back.get(m[0].trainIdx) == m[0].queryIdx]
    return np.asarray(pairs, dtype=np.int64).reshape(-1, 2)


def off_plane_count(P: np.ndarray, tol: float, iterations: int = 200, seed: int = 0) -> int:
    """(N,3) points -> how many lie farther than tol from the plane (RANSAC) that holds most of them."""
    if len(P) < 4:
        return 0
    rng = np.random.default_rng(seed)
    best = 0
    for _ in range(iterations):
        a, b, c = P[rng.choice(len(P), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        best = max(best, int((np.abs((P - a) @ (n / norm)) < tol).sum()))
    return len(P) - best


def _pnp_config(cfg: LoopConfig) -> TrackingConfig:
    return TrackingConfig(min_pnp_inliers=cfg.min_inliers, ransac_reproj_px=cfg.ransac_px,
                          ransac_line_px=cfg.ransac_px, outlier_reproj_px=cfg.ransac_px, ransac_iterations=1000)


def _reject(q: LoopKeyframe, c: LoopKeyframe, t0: float, reason: str, stage: str,
            counts: tuple[int, int, int, int] = (0, 0, 0, 0)) -> Verification:
    log.debug("loop candidate %d for keyframe %d rejected: %s", c.kf_id, q.kf_id, reason)
    return Verification(q.kf_id, c.kf_id, False, np.eye(4), *counts, False, 0.0, reason, time.perf_counter() - t0,
                        stage=stage)


def verify(query: LoopKeyframe, cand: LoopKeyframe, K: np.ndarray, cfg: LoopConfig | None = None,
           T_cam_velo: np.ndarray | None = None, reg_cfg: RegistrationConfig | None = None,
           against_odometry: Callable[[np.ndarray], str] | None = None) -> Verification:
    """Check candidate `cand` for `query` with (3,3) K; the accepted edge is T_cand_query (camera Q -> camera C).
    against_odometry: the last check, T_cand_query -> why it contradicts the odometry, or "" (the loop closer's)."""
    cfg = cfg or LoopConfig()
    t0 = time.perf_counter()
    pm = match_binary(query.descriptors, cand.descriptors, cfg.ratio, cfg.point_max_hamming)
    pm = pm[np.all(np.isfinite(cand.points_cam[pm[:, 1]]), axis=1)] if len(pm) else pm
    lm = match_binary(query.line_descriptors, cand.line_descriptors, cfg.ratio, cfg.line_max_hamming)
    lm = lm[np.all(np.isfinite(cand.lines_cam[lm[:, 1]]), axis=(1, 2))] if len(lm) else lm
    n_pm, n_lm = len(pm), len(lm)
    if n_pm + n_lm < cfg.min_inliers:
        return _reject(query, cand, t0, f"only {n_pm} point + {n_lm} line matches with depth "
                       f"(need {cfg.min_inliers})", MATCHES, (n_pm, n_lm, 0, 0))
    res = solve_pnpl(K, cand.points_cam[pm[:, 1]], query.keypoints[pm[:, 0]], cand.lines_cam[lm[:, 1]],
                     query.segments[lm[:, 0]], None, _pnp_config(cfg))
    n_pi, n_li = int(res.point_inliers.sum()), int(res.line_inliers.sum())
    counts = (n_pm, n_lm, n_pi, n_li)
    if not res.success:
        return _reject(query, cand, t0, f"PnP/PnL: {res.message}", PNP, counts)
    T = res.T_world_cam  # world = candidate's camera: T_cand_query
    P_in = np.concatenate([cand.points_cam[pm[res.point_inliers, 1]],
                           cand.lines_cam[lm[res.line_inliers, 1]].reshape(-1, 3)])
    n_off = off_plane_count(P_in, cfg.plane_tolerance_m)
    if n_off < cfg.min_off_plane:
        return _reject(query, cand, t0, f"PnP/PnL inliers lie on one plane ({n_off} off it, need "
                       f"{cfg.min_off_plane}): a repeated texture, not a place", PLANE, counts)
    registered, fitness = False, 0.0
    if cfg.use_registration and query.scan is not None and cand.scan is not None:
        T, fitness, err = _register(query.scan, cand.scan, T, T_cam_velo, reg_cfg)
        if err:
            return _reject(query, cand, t0, err, REGISTRATION, counts)
        registered = True
    why = against_odometry(T) if against_odometry is not None else ""
    if why:
        return _reject(query, cand, t0, why, ODOMETRY, counts)
    msg = f"{n_pi}/{n_pm} point and {n_li}/{n_lm} line inliers" + (f", scan fitness {fitness:.2f}" if registered
                                                                    else ", no scan registration")
    log.info("loop %d -> %d accepted: %s", query.kf_id, cand.kf_id, msg)
    return Verification(query.kf_id, cand.kf_id, True, T, *counts, registered, fitness, msg,
                        time.perf_counter() - t0)


def verify_by_registration(query_id: int, cand_id: int, query_map: np.ndarray, cand_map: np.ndarray,
                           T_init: np.ndarray, cfg: LoopConfig, T_cam_velo: np.ndarray | None = None,
                           against_odometry: Callable[[np.ndarray], str] | None = None, detector: str = "lidar",
                           place_inliers: int = 0, counts: tuple[int, int, int, int] = (0, 0, 0, 0),
                           prefix: str = "") -> Verification:
    """Verify candidate cand_id for keyframe query_id by registering their local maps ((N,3), (M,3), each in its
    keyframe's lidar frame, plvo.loop.lidar_place.LocalMaps) from T_init (4,4) T_cand_query in camera frames;
    against_odometry as for `verify`. counts carry a failed image verification's matches; prefix its reason."""
    t0 = time.perf_counter()
    T_cv = np.eye(4) if T_cam_velo is None else np.asarray(T_cam_velo, float)
    a = align_maps(query_map, cand_map, se3.inv(T_cv) @ np.asarray(T_init, float) @ T_cv, cfg, cfg.lidar_place_voxel_m)

    def done(accepted: bool, T: np.ndarray, reason: str, stage: str) -> Verification:
        reason = prefix + reason
        # a registered candidate is news (INFO); a rejected one is DEBUG, as every rejection (a run has dozens)
        log.log(logging.INFO if accepted else logging.DEBUG, "loop candidate %d (%s) for keyframe %d %s: %s",
                cand_id, detector, query_id, "registered" if accepted else "rejected", reason)
        return Verification(query_id, cand_id, accepted, T, *counts, True, a.overlap, reason,
                            time.perf_counter() - t0, detector, stage, place_inliers, a)

    if not a.accepted:
        return done(False, np.eye(4), f"scan registration: {a.reason}", REGISTRATION)
    T = np.round(se3.conjugate(T_cv, a.T_dst_src), 9)
    why = against_odometry(T) if against_odometry is not None else ""
    if why:
        return done(False, np.eye(4), f"scan registration ({a.summary()}), but {why}", ODOMETRY)
    return done(True, T, f"scan registration: {a.summary()}", "")


def _register(query_scan: np.ndarray, cand_scan: np.ndarray, T_cand_query: np.ndarray, T_cam_velo: np.ndarray | None,
              reg_cfg: RegistrationConfig | None) -> tuple[np.ndarray, float, str]:
    """Refine T_cand_query by registering Q's scan onto C's -> (T, fitness, error message or "")."""
    T_cv = np.eye(4) if T_cam_velo is None else np.asarray(T_cam_velo, float)
    init = se3.inv(T_cv) @ T_cand_query @ T_cv
    try:
        r = align(scan_points(query_scan), scan_points(cand_scan), init, reg_cfg, T_cv)
    except (PlvoError, RuntimeError) as exc:  # a scan too sparse to register is a rejection, not a crash
        return T_cand_query, 0.0, f"scan registration raised: {exc}"
    if not r.converged:
        return T_cand_query, r.fitness, f"scan registration did not converge ({r.method}, fitness {r.fitness:.2f})"
    return r.T_camdst_camsrc, r.fitness, ""
