"""Loop closing (paper II-F): BoW query, geometric verification, pose-graph correction.

`LoopCloser.on_keyframe(kf)` runs one keyframe through the whole chain and returns a `LoopOutcome`. It is
synchronous; the system runs it in its loop worker. After an accepted loop the closer optimises a pose graph
(gtsam Pose3: a prior on the first keyframe, BetweenFactors of consecutive keyframes as measured when each
keyframe arrived, every accepted loop edge) with Levenberg-Marquardt and keeps the result as its own estimate.
The system must apply the corrected poses to its map (and tracker) and tell the closer of later changes with
`update_poses`; the odometry edge of a new keyframe is measured against the closer's estimate of the previous
one. The global bundle adjustment that follows (plvo.loop.global_ba) needs the map's landmarks, so the loop
worker runs it, on the same edges (`pose_graph_edges`).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np

from plvo.config import LoopConfig, RegistrationConfig
from plvo.geometry import se3
from plvo.loop.database import Detection, LoopDetector
from plvo.loop.keyframe_store import FIELD_NAMES, KeyframeStore
from plvo.loop.scans import compact_scan
from plvo.loop.verification import LoopKeyframe, Verification, verify
from plvo.loop.vocabulary import Vocabulary, load_default

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class LoopEdge:
    """Accepted loop: T_match_query (4,4) maps camera `query_id` into camera `match_id` (older keyframe)."""

    query_id: int
    match_id: int
    T_match_query: np.ndarray
    n_inliers: int
    registered: bool


@dataclass(frozen=True)
class LoopOutcome:
    """One keyframe through the loop closer.

    detection: candidates and their scores; verifications: one per candidate checked; accepted: the new loop
    edge or None; rejections: "candidate <id>: <reason>" (or the detection's reason when nothing was checked);
    kf_ids (K,) with poses_before / poses_after (K,4,4) T_world_cam when a correction ran, else None;
    times in milliseconds: bow (transform), query (database), verify, correct (pose graph).
    """

    kf_id: int
    detection: Detection
    verifications: tuple[Verification, ...]
    accepted: LoopEdge | None
    rejections: tuple[str, ...]
    kf_ids: np.ndarray | None
    poses_before: np.ndarray | None
    poses_after: np.ndarray | None
    bow_ms: float
    query_ms: float
    verify_ms: float
    correct_ms: float


def compact_keyframe(kf: LoopKeyframe) -> LoopKeyframe:
    """What the database keeps of a keyframe once it was the query: as a candidate only its features with a
    depth prior can match (verify keeps only those), in float32."""
    p = np.flatnonzero(np.all(np.isfinite(kf.points_cam), axis=1))
    ln = np.flatnonzero(np.all(np.isfinite(kf.lines_cam), axis=(1, 2)))
    return dataclasses.replace(
        kf, keypoints=np.asarray(kf.keypoints, np.float32)[p], descriptors=np.ascontiguousarray(kf.descriptors[p]),
        points_cam=np.asarray(kf.points_cam, np.float32)[p], segments=np.asarray(kf.segments, np.float32)[ln],
        line_descriptors=np.ascontiguousarray(kf.line_descriptors[ln]), lines_cam=np.asarray(kf.lines_cam,
                                                                                              np.float32)[ln])


def optimize_pose_graph(poses: np.ndarray, odometry: list[tuple[int, int, np.ndarray]],
                        loops: list[tuple[int, int, np.ndarray]], cfg: LoopConfig) -> np.ndarray:
    """(K,4,4) initial T_world_cam, edges (i, j, T_i_j) by index into poses -> (K,4,4) optimised; pose 0 fixed."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    # gtsam's Pose3 tangent is (rotation, translation).
    odo = gtsam.noiseModel.Diagonal.Sigmas(np.r_[[cfg.odom_sigma_rot] * 3, [cfg.odom_sigma_trans] * 3])
    lp = gtsam.noiseModel.Diagonal.Sigmas(np.r_[[cfg.loop_sigma_rot] * 3, [cfg.loop_sigma_trans] * 3])
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(poses[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    for i, j, T in odometry:
        graph.add(gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(T), odo))
    for i, j, T in loops:
        graph.add(gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(T), lp))
    for k, T in enumerate(poses):
        values.insert(k, gtsam.Pose3(se3.orthonormalize(T)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.pgo_iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return np.stack([result.atPose3(k).matrix() for k in range(len(poses))])


class LoopCloser:
    """Keyframe-by-keyframe loop detection, verification and correction; K (3,3), T_cam_velo (4,4)."""

    def __init__(self, K: np.ndarray, orb_vocab: Vocabulary | None = None, lbd_vocab: Vocabulary | None = None,
                 cfg: LoopConfig | None = None, T_cam_velo: np.ndarray | None = None,
                 reg_cfg: RegistrationConfig | None = None) -> None:
        self.cfg = cfg or LoopConfig()
        self.K = np.asarray(K, float)
        self.T_cam_velo = None if T_cam_velo is None else np.asarray(T_cam_velo, float)
        self.reg_cfg = reg_cfg
        if orb_vocab is None or lbd_vocab is None:
            d = Path(self.cfg.vocab_dir) if self.cfg.vocab_dir else None
            orb_vocab = orb_vocab or (Vocabulary.load(d / "orb.npz") if d else load_default("orb"))
            lbd_vocab = lbd_vocab or (Vocabulary.load(d / "lbd.npz") if d else load_default("lbd"))
        self.orb_vocab, self.lbd_vocab = orb_vocab, lbd_vocab
        self.detector = LoopDetector(self.cfg)
        self._kfs = KeyframeStore()  # every keyframe, compact (compact_keyframe), on disk
        self._ids: list[int] = []
        self._poses: dict[int, np.ndarray] = {}
        self._odom: dict[int, np.ndarray] = {}  # kf id -> T_prev_kf measured when it arrived
        self._index: dict[int, int] = {}  # kf id -> arrival index
        self._driven: list[float] = []  # metres of odometry from the first keyframe to each, by arrival index
        self.edges: list[LoopEdge] = []
        self._last_loop_at = -10**9  # arrival index of the last accepted loop

    def keyframe(self, kf_id: int) -> LoopKeyframe:
        """What the database keeps of keyframe kf_id (read back from its store), scan included."""
        got = self._kfs.get(kf_id)
        if got is None:
            raise KeyError(f"loop closer: no keyframe {kf_id} in its database")
        arrays, frame_index = got
        return LoopKeyframe(kf_id, frame_index=frame_index, **arrays)

    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Keyframe ids (K,) and the closer's current T_world_cam estimates (K,4,4)."""
        return np.asarray(self._ids, np.int64), np.stack([self._poses[i] for i in self._ids])

    def pose_graph_edges(self) -> tuple[list[tuple[int, int, np.ndarray]], list[tuple[int, int, np.ndarray]]]:
        """Odometry and loop edges (i, j, T_i_j) by index into `poses()`, as the pose graph uses them."""
        index = {k: n for n, k in enumerate(self._ids)}
        odometry = [(n - 1, n, self._odom[self._ids[n]]) for n in range(1, len(self._ids))]
        loops = [(index[e.match_id], index[e.query_id], e.T_match_query) for e in self.edges]
        return odometry, loops

    def update_poses(self, ids: np.ndarray, poses: np.ndarray) -> None:
        """Tell the closer of refined T_world_cam (K,4,4) of keyframes ids (K,) (e.g. after bundle adjustment)."""
        for i, T in zip(np.asarray(ids).tolist(), np.asarray(poses)):
            if i in self._poses:
                self._poses[i] = np.array(T, float)

    def on_keyframe(self, kf: LoopKeyframe) -> LoopOutcome:
        """Query, (maybe) verify and correct with a new keyframe; it joins the database afterwards."""
        t0 = time.perf_counter()
        bp = self.orb_vocab.transform(kf.descriptors)
        bl = self.lbd_vocab.transform(kf.line_descriptors)
        t1 = time.perf_counter()
        det = self.detector.detect(kf.kf_id, bp, bl)
        t2 = time.perf_counter()
        query = self._store(kf)
        self.detector.add(kf.kf_id, bp, bl)
        checks, accepted, rejections = self._verify(query, det)
        stored = compact_keyframe(query)
        self._kfs.put(kf.kf_id, {f: getattr(stored, f) for f in FIELD_NAMES}, kf.frame_index)
        t3 = time.perf_counter()
        ids = before = after = None
        if accepted is not None:
            ids, before, after = self._correct(accepted)
        t4 = time.perf_counter()
        return LoopOutcome(kf.kf_id, det, checks, accepted, rejections, ids, before, after,
                          1e3 * (t1 - t0), 1e3 * (t2 - t1), 1e3 * (t3 - t2), 1e3 * (t4 - t3))

    def _store(self, kf: LoopKeyframe) -> LoopKeyframe:
        """Book the keyframe's arrival (pose, odometry, distance driven) -> it as the query, its scan compacted."""
        step = 0.0
        if self._ids:
            prev = self._ids[-1]
            self._odom[kf.kf_id] = se3.inv(self._poses[prev]) @ kf.T_world_cam
            step = float(np.linalg.norm(self._odom[kf.kf_id][:3, 3]))
        self._index[kf.kf_id] = len(self._ids)
        self._driven.append((self._driven[-1] if self._driven else 0.0) + step)
        scan = None if kf.scan is None or not self.cfg.use_registration else compact_scan(kf.scan, self.reg_cfg)
        self._ids.append(kf.kf_id)
        self._poses[kf.kf_id] = np.array(kf.T_world_cam, float)
        return LoopKeyframe(kf.kf_id, np.array(kf.T_world_cam, float), kf.keypoints, kf.descriptors, kf.points_cam,
                            kf.segments, kf.line_descriptors, kf.lines_cam, scan, kf.frame_index)

    def _verify(self, kf: LoopKeyframe, det: Detection):
        if not det.ready:
            return (), None, (det.reason,) if det.reason else ()
        since = len(self._ids) - 1 - self._last_loop_at
        if since <= self.cfg.loop_cooldown:
            why = f"{since} keyframes since the last loop (cooldown {self.cfg.loop_cooldown})"
            log.info("loop candidates %s for keyframe %d not verified: %s", list(map(int, det.to_verify)), kf.kf_id,
                     why)
            return (), None, (why,)
        checks, rejections = [], []
        for cid in det.to_verify:
            far = self._too_far(kf.kf_id, cid)
            if far:  # decided by the odometry alone: not worth a PnP/PnL and a registration
                log.info("loop candidate %d for keyframe %d rejected: %s", cid, kf.kf_id, far)
                checks.append(Verification(kf.kf_id, cid, False, np.eye(4), 0, 0, 0, 0, False, 0.0, far, 0.0))
                rejections.append(f"candidate {cid}: {far}")
                continue
            v = verify(kf, self.keyframe(cid), self.K, self.cfg, self.T_cam_velo, self.reg_cfg,
                       against_odometry=functools.partial(self._implausible, kf.kf_id, cid))
            checks.append(v)
            if v.accepted:
                edge = LoopEdge(kf.kf_id, cid, v.T_cand_query, v.n_point_inliers + v.n_line_inliers, v.registered)
                self.edges.append(edge)
                self._last_loop_at = len(self._ids) - 1
                return tuple(checks), edge, tuple(rejections)
            rejections.append(f"candidate {cid}: {v.reason}")
        return tuple(checks), None, tuple(rejections)

    def _drift_limit(self, query_id: int, match_id: int) -> tuple[float, float]:
        """(metres of odometry between the two keyframes, the drift they may have accumulated)."""
        driven = self._driven[self._index[query_id]] - self._driven[self._index[match_id]]
        return driven, self.cfg.max_drift_fraction * driven + self.cfg.max_drift_floor_m

    def _too_far(self, query_id: int, match_id: int) -> str:
        """Why the odometry alone rules the candidate out, or "": the keyframes are estimated further apart than the
        drift since then plus the distance at which two keyframes can still see one place (loop.max_view_m), so
        any measured loop edge would fail `_implausible` (triangle inequality; it also bounds the edge's length)."""
        if self.cfg.max_drift_fraction <= 0:
            return ""
        apart = float(np.linalg.norm(self._poses[query_id][:3, 3] - self._poses[match_id][:3, 3]))
        driven, limit = self._drift_limit(query_id, match_id)
        if apart <= limit + self.cfg.max_view_m:
            return ""
        return (f"{apart:.0f} m away by the odometry after {driven:.0f} m driven (at most {limit:.1f} m of drift "
                f"+ {self.cfg.max_view_m:.0f} m of view expected): a repeated place, not a revisit")

    def _implausible(self, query_id: int, match_id: int, T_match_query: np.ndarray) -> str:
        """Why a verified edge contradicts the odometry (a repeated place, not a revisit), or "" when it does not."""
        if self.cfg.max_drift_fraction <= 0:
            return ""
        length = float(np.linalg.norm(T_match_query[:3, 3]))
        if length > self.cfg.max_view_m:
            return (f"the loop edge is {length:.0f} m long (two views of one place are at most "
                    f"{self.cfg.max_view_m:.0f} m apart)")
        T_est = se3.inv(self._poses[match_id]) @ self._poses[query_id]
        jump = float(np.linalg.norm((se3.inv(T_est) @ T_match_query)[:3, 3]))
        driven, limit = self._drift_limit(query_id, match_id)
        if jump <= limit:
            return ""
        return (f"the loop would move the keyframe by {jump:.1f} m after {driven:.0f} m of odometry (at most "
                f"{limit:.1f} m of drift expected): a repeated place, not a revisit")

    def _correct(self, edge: LoopEdge) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ids, before = self.poses()
        odometry, loops = self.pose_graph_edges()
        after = optimize_pose_graph(before, odometry, loops, self.cfg)
        self.update_poses(ids, after)
        # Odometry edges stay as measured: they are the tracker's constraints, not the current estimate.
        log.info("loop %d -> %d: corrected %d keyframe poses, last moved by %.2f m", edge.query_id,
                 edge.match_id, len(ids), float(np.linalg.norm(after[-1, :3, 3] - before[-1, :3, 3])))
        return ids, before, after
