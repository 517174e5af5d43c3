"""Loop closing (paper II-F): BoW query, lidar place recognition, geometric verification, pose-graph correction.

`LoopCloser.on_keyframe(kf)` runs one keyframe through the whole chain and returns a `LoopOutcome`. It is
synchronous; the system runs it in its loop worker. Candidates come from two detectors: the bags of words of ORB
and LBD features (plvo.loop.database; verified by PnP/PnL on features with depth, then scan registration) and,
with `loop.lidar_place`, the lidar place recognition (plvo.loop.lidar_place: map_closures' density images of each
place's local map, which find a street driven back the other way), verified by registering the two keyframes'
local maps (plvo.loop.map_registration); a place node is the keyframe `loop.lidar_place_reach_m` behind the newest,
so its loop edge joins that keyframe. A bag-of-words candidate refused only for too few image matches with depth
or PnP/PnL inliers is registered the same way (`loop.scan_fallback`), from the odometry's relative pose. All go
through the same odometry checks (`_too_far`, `_implausible`) and the same cooldown; a registered edge joins
keyframes at most `loop.scan_max_edge_m` apart (a candidate further away hands it to its neighbour nearest the
query); the first candidate accepted makes the loop edge.

After an accepted loop the closer optimises a pose graph (gtsam Pose3: a prior on the first keyframe,
BetweenFactors of consecutive keyframes as the current estimates relate them, every accepted loop edge) with
Levenberg-Marquardt and keeps the result as its own estimate. The current estimates are the map's, refined by the
back end's lidar-constrained bundle adjustment (and bent by the loops before, whose edges stay in the graph), as
ORB-SLAM's essential graph takes them: the motions the tracker measured when each keyframe arrived are several times
worse in heading (plvo_eval.stage_drift). The newest keyframe's pose is still the tracker's (its back-end result comes
later), so the global bundle adjustment that follows, on the back end's registration edges, finishes the work.
The system must apply the corrected poses to its map (and tracker) and tell the closer of later changes with
`update_poses`; the distance a new keyframe adds to the drive (the odometry checks' measure) is taken from the
closer's estimate of the previous one. The global bundle adjustment that follows (plvo.loop.global_ba) needs
the map's landmarks, so the loop worker runs it, on the same edges (`pose_graph_edges`).
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
from plvo.loop.lidar_place import MAX_SIDE_KEYFRAMES, LocalMaps, PlaceCandidate, PlaceQuery, PlaceRecognizer
from plvo.loop.scans import compact_scan
from plvo.loop.verification import REGISTRATION, TOO_FAR, LoopKeyframe, Verification, verify, verify_by_registration
from plvo.loop.vocabulary import Vocabulary, load_default

log = logging.getLogger(__name__)

# A bag-of-words candidate is registered only when its images share this many matches with depth (KITTI 09's return
# to its start: 16-30): the bag of words alone proposes candidates at most keyframes of a repetitive street, and a
# registration costs 0.2-1 s.
FALLBACK_MIN_MATCHES = 10

@dataclass(frozen=True)
class LoopEdge:
    """Accepted loop: T_match_query (4,4) maps camera `query_id` into camera `match_id` (older keyframe);
    detector: "bow" or "lidar" (Verification.detector); n_inliers: PnP/PnL inliers, or the place recognition's."""

    query_id: int
    match_id: int
    T_match_query: np.ndarray
    n_inliers: int
    registered: bool
    detector: str = "bow"


@dataclass(frozen=True)
class LoopOutcome:
    """One keyframe through the loop closer.

    detection: candidates and their scores; verifications: one per candidate checked; accepted: the new loop
    edge or None; rejections: "candidate <id>: <reason>" (or the detection's reason when nothing was checked);
    kf_ids (K,) with poses_before / poses_after (K,4,4) T_world_cam when a correction ran, else None;
    times in milliseconds: bow (transform), query (database), verify, correct (pose graph), lidar (the place
    recognition's local maps and queries); places: the place nodes queried at this keyframe (keyframes
    lidar_place_reach_m behind it; usually none or one).
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
    lidar_ms: float = 0.0
    places: tuple[PlaceQuery, ...] = ()


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


def _refused(v: Verification, reason: str) -> Verification:
    """A registration's verification (its log said "registered") refused after all, for reason: logged as every
    other refusal (at DEBUG: a run's log under -vv says what became of each candidate)."""
    log.debug("loop candidate %d (%s) for keyframe %d rejected: %s", v.cand_id, v.detector, v.query_id, reason)
    return dataclasses.replace(v, accepted=False, T_cand_query=np.eye(4), stage=REGISTRATION, reason=reason)


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
        self._index: dict[int, int] = {}  # kf id -> arrival index
        self._driven: list[float] = []  # metres of odometry from the first keyframe to each, by arrival index
        self.edges: list[LoopEdge] = []
        self._last_loop_at = -10**9  # arrival index of the last accepted loop
        self._maps = LocalMaps(self.cfg, self.T_cam_velo, self._stored_scan)
        self._built: dict[int, np.ndarray] = {}  # local maps built for the keyframe in hand (poses may change after)
        on = self.cfg.lidar_place and self.cfg.use_registration
        self._places = PlaceRecognizer(self.cfg) if on else None

    def _stored_scan(self, kf_id: int) -> np.ndarray | None:
        got = self._kfs.get(kf_id)
        return None if got is None else got[0]["scan"]

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
        P = self._poses
        odometry = [(n - 1, n, se3.inv(P[self._ids[n - 1]]) @ P[self._ids[n]]) for n in range(1, len(self._ids))]
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
        self._maps.remember(kf.kf_id, query.scan)
        tp = time.perf_counter()
        places = self._place()
        t3 = time.perf_counter()
        checks, accepted, rejections = self._verify(query, det, places)
        self._built.clear()
        stored = compact_keyframe(query)
        self._kfs.put(kf.kf_id, {f: getattr(stored, f) for f in FIELD_NAMES}, kf.frame_index)
        t4 = time.perf_counter()
        ids = before = after = None
        if accepted is not None:
            ids, before, after = self._correct(accepted)
        t5 = time.perf_counter()
        return LoopOutcome(kf.kf_id, det, checks, accepted, rejections, ids, before, after, 1e3 * (t1 - t0),
                           1e3 * (t2 - t1), 1e3 * (t4 - t3 + tp - t2), 1e3 * (t5 - t4), 1e3 * (t3 - tp), places)

    def _store(self, kf: LoopKeyframe) -> LoopKeyframe:
        """Book the keyframe's arrival (pose, odometry, distance driven) -> it as the query, its scan compacted."""
        step = 0.0
        if self._ids:
            step = float(np.linalg.norm((se3.inv(self._poses[self._ids[-1]]) @ kf.T_world_cam)[:3, 3]))
        self._index[kf.kf_id] = len(self._ids)
        self._driven.append((self._driven[-1] if self._driven else 0.0) + step)
        scan = None if kf.scan is None or not self.cfg.use_registration else compact_scan(kf.scan, self.reg_cfg)
        self._ids.append(kf.kf_id)
        self._poses[kf.kf_id] = np.array(kf.T_world_cam, float)
        return LoopKeyframe(kf.kf_id, np.array(kf.T_world_cam, float), kf.keypoints, kf.descriptors, kf.points_cam,
                            kf.segments, kf.line_descriptors, kf.lines_cam, scan, kf.frame_index)

    def _local_map(self, kf_id: int) -> np.ndarray:
        """Keyframe kf_id's local map (plvo.loop.lidar_place.LocalMaps) with the current poses, built once a
        keyframe."""
        if kf_id not in self._built:
            self._built[kf_id] = self._maps.build(self._index[kf_id], self._ids, self._poses)
        return self._built[kf_id]

    def _place(self) -> tuple[PlaceQuery, ...]:
        """The lidar place recognition's nodes due at this keyframe, queried (none when it is off)."""
        if self._places is None:
            return ()
        out = []
        for at in self._places.due(self._driven):
            kf_id = self._ids[at]
            out.append(self._places.query(kf_id, functools.partial(self._local_map, kf_id),
                                          functools.partial(self._old_enough, at)))
        return tuple(out)

    def _old_enough(self, at: int, cid: int) -> bool:
        """Is keyframe cid more than min_keyframe_gap keyframes older than the keyframe of arrival index at?"""
        return self._index[cid] < at - self.cfg.min_keyframe_gap

    def _verify(self, kf: LoopKeyframe, det: Detection, places: tuple[PlaceQuery, ...]
                ) -> tuple[tuple[Verification, ...], LoopEdge | None, tuple[str, ...]]:
        lidar = [(p.kf_id, c) for p in places for c in p.candidates]
        if not det.ready and not lidar:
            return (), None, (det.reason,) if det.reason else ()
        since = len(self._ids) - 1 - self._last_loop_at
        if since <= self.cfg.loop_cooldown:
            why = f"{since} keyframes since the last loop (cooldown {self.cfg.loop_cooldown})"
            log.debug("loop candidates %s for keyframe %d not verified: %s",
                      list(map(int, det.to_verify)) + [c.kf_id for _, c in lidar], kf.kf_id, why)
            return (), None, (why,)
        checks: list[Verification] = []
        rejections: list[str] = []
        lacking: list[int] = []  # positions in checks of bag-of-words candidates refused for lack of image matches
        for cid in det.to_verify:
            v = self._check_bow(kf, cid)
            if self._take(v, checks, rejections):
                return tuple(checks), self.edges[-1], tuple(rejections)
            if v.for_lack_of_matches:
                lacking.append(len(checks) - 1)
        for node, c in lidar:
            v = self._check_place(node, c)
            if self._take(v, checks, rejections):
                return tuple(checks), self.edges[-1], tuple(rejections)
        placed = {c.kf_id for _, c in lidar}
        lacking = [k for k in lacking if checks[k].cand_id not in placed  # registered from its own pose already
                   and checks[k].n_point_matches + checks[k].n_line_matches >= FALLBACK_MIN_MATCHES]
        if lacking and self.cfg.scan_fallback and kf.scan is not None:
            # the best such candidate only: a registration costs 0.2-0.7 s; it takes the place of the refusal
            k = lacking[0]
            v = self._fallback(kf, checks[k])
            del checks[k], rejections[k]
            if self._take(v, checks, rejections):
                return tuple(checks), self.edges[-1], tuple(rejections)
        return tuple(checks), None, tuple(rejections)

    def _take(self, v: Verification, checks: list[Verification], rejections: list[str]) -> bool:
        """Book a verification (checks and rejections stay parallel until one is accepted); an accepted one makes
        the loop edge (True)."""
        checks.append(v)
        rejections.append(f"candidate {v.cand_id} ({v.source}): {v.reason}")
        if not v.accepted:
            return False
        rejections.pop()
        if v.alignment is not None:
            log.info("loop %d -> %d accepted (%s): %s", v.query_id, v.cand_id, v.detector, v.reason)
        self.edges.append(LoopEdge(v.query_id, v.cand_id, v.T_cand_query, v.support, v.registered, v.detector))
        self._last_loop_at = len(self._ids) - 1
        return True

    def _far(self, query_id: int, cid: int, detector: str, place_inliers: int = 0) -> Verification | None:
        far = self._too_far(query_id, cid)
        if not far:  # decided by the odometry alone: not worth a PnP/PnL or a registration
            return None
        log.debug("loop candidate %d for keyframe %d rejected: %s", cid, query_id, far)
        return Verification(query_id, cid, False, np.eye(4), 0, 0, 0, 0, False, 0.0, far, 0.0, detector, TOO_FAR,
                            place_inliers)

    def _check_bow(self, kf: LoopKeyframe, cid: int) -> Verification:
        """A bag-of-words candidate: PnP/PnL on the features with depth, then scan registration."""
        far = self._far(kf.kf_id, cid, "bow")
        if far is not None:
            return far
        return verify(kf, self.keyframe(cid), self.K, self.cfg, self.T_cam_velo, self.reg_cfg,
                      against_odometry=functools.partial(self._implausible, kf.kf_id, cid))

    def _fallback(self, kf: LoopKeyframe, v: Verification) -> Verification:
        """A bag-of-words candidate refused for lack of image matches (v): its local maps registered from the
        odometry's relative pose (one the place recognition proposed was registered from its own pose)."""
        cid = v.cand_id
        T_init = se3.inv(self._poses[cid]) @ self._poses[kf.kf_id]
        counts = (v.n_point_matches, v.n_line_matches, v.n_point_inliers, v.n_line_inliers)
        return self._register(kf.kf_id, cid, T_init, "bow", 0, counts, f"{v.reason}; registered from the odometry: ")

    def _check_place(self, query_id: int, c: PlaceCandidate) -> Verification:
        """A lidar place candidate for place node query_id: the local maps registered from the place recognition's
        relative pose."""
        far = self._far(query_id, c.kf_id, "lidar", c.inliers)
        if far is not None:
            return far
        return self._register(query_id, c.kf_id, self._camera(c.T_cand_query), "lidar", c.inliers,
                              prefix=f"{c.inliers} density-map inliers; ")

    def _register(self, query_id: int, cid: int, T_init: np.ndarray, detector: str, place_inliers: int,
                  counts: tuple[int, int, int, int] = (0, 0, 0, 0), prefix: str = "") -> Verification:
        """Verify candidate cid for keyframe query_id by registering their local maps from T_init (T_cand_query,
        cameras). The loop edge
        must join keyframes at most loop.scan_max_edge_m apart: a candidate further away (a place node up to
        half a node spacing off, a bag-of-words neighbour) hands the edge to its neighbour nearest the query,
        registered again from the first registration's pose."""
        def register(c: int, T: np.ndarray, text: str, view_bound: bool = True) -> Verification:
            return verify_by_registration(query_id, c, self._local_map(query_id), self._local_map(c), T, self.cfg,
                                          self.T_cam_velo, functools.partial(self._implausible, query_id, c,
                                                                             view_bound=view_bound),
                                          detector, place_inliers, counts, text)

        # The first registration is held to the odometry's drift alone: an edge beyond the view bound (loop.max_view_m)
        # is handed on below, and the edge that is kept is at most scan_max_edge_m long. Held to the view bound here,
        # a revisit seen from 41-60 m (a bag-of-words neighbour of the place) was refused though a keyframe near the
        # candidate saw it from a few metres (twin 08 at LSD 0.35: 628 -> 45, 1323 -> 868).
        v = register(cid, T_init, prefix, view_bound=False)
        apart = float(np.linalg.norm(v.T_cand_query[:3, 3]))
        if not v.accepted or apart <= self.cfg.scan_max_edge_m:
            return v
        nearest, T_n = self._nearest_neighbour(query_id, cid, v.T_cand_query)
        if nearest is None:
            return _refused(v, f"{v.reason}; but the keyframes are {apart:.1f} m apart and no keyframe near the "
                               f"candidate is within {self.cfg.scan_max_edge_m:.0f} m of the query (a loop edge joins "
                               f"two views of one place)")
        first = v.alignment.summary() if v.alignment is not None else ""
        w = register(nearest, T_n, f"{prefix}registered {apart:.1f} m away ({first}), handed to its neighbour "
                                   f"{nearest}: ")
        handed = float(np.linalg.norm(w.T_cand_query[:3, 3]))
        if w.accepted and handed > self.cfg.scan_max_edge_m:
            return _refused(w, f"{w.reason}; but it is {handed:.1f} m away (at most {self.cfg.scan_max_edge_m:.0f} m)")
        return w

    def _nearest_neighbour(self, query_id: int, cid: int, T_cand_query: np.ndarray
                           ) -> tuple[int | None, np.ndarray]:
        """The keyframe near candidate cid (within its local map's window, old enough to be a candidate) whose
        camera is nearest the query's by the registered pose and the closer's poses about the candidate, within
        loop.scan_max_edge_m -> (its id, T_it_query), or (None, identity)."""
        at, q_at = self._index[cid], self._index[query_id]
        last = q_at - self.cfg.min_keyframe_gap - 1
        best, best_d, best_T = None, self.cfg.scan_max_edge_m, np.eye(4)
        for j in range(max(0, at - MAX_SIDE_KEYFRAMES), min(last, at + MAX_SIDE_KEYFRAMES) + 1):
            n = self._ids[j]
            T = se3.inv(self._poses[n]) @ self._poses[cid] @ T_cand_query
            d = float(np.linalg.norm(T[:3, 3]))
            if d <= best_d:
                best, best_d, best_T = n, d, T
        return best, best_T

    def _camera(self, T_lidar: np.ndarray) -> np.ndarray:
        """A relative pose between lidar frames -> the same between the keyframes' cameras."""
        return T_lidar if self.T_cam_velo is None else se3.conjugate(self.T_cam_velo, T_lidar)

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

    def _implausible(self, query_id: int, match_id: int, T_match_query: np.ndarray, view_bound: bool = True) -> str:
        """Why a verified edge contradicts the odometry (a repeated place, not a revisit), or "" when it does not;
        without view_bound an edge may be longer than loop.max_view_m (one that is to be handed on)."""
        if self.cfg.max_drift_fraction <= 0:
            return ""
        length = float(np.linalg.norm(T_match_query[:3, 3]))
        if view_bound and length > self.cfg.max_view_m:
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
        log.info("loop %d -> %d: corrected %d keyframe poses, last moved by %.2f m", edge.query_id,
                 edge.match_id, len(ids), float(np.linalg.norm(after[-1, :3, 3] - before[-1, :3, 3])))
        return ids, before, after
