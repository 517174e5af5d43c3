"""The loop closer as the System runs it (paper II-F): one keyframe at a time, inline or in its own thread.

Each keyframe is turned into a `LoopKeyframe` (features, depth priors as camera-frame 3D points and lines, the
thinned scan) and run through `LoopCloser`: BoW query, verification, and on an accepted loop a pose-graph
correction. The corrected keyframe poses are written into the shared map; every landmark moves rigidly with the
keyframe that created it, and keyframes the tracker made meanwhile move with the newest corrected one. The
tracker follows through its re-anchoring on the last keyframe. After a correction a GraphResult with the corrected
keyframe trajectory, its odometry chain and the loop edges goes to the recorders; timings: loop_bow, loop_query,
loop_verify, loop_correct (pose graph), loop_apply (map update), loop (all), seconds, one entry a keyframe.

With `backend.concurrent` the back end may be optimising a window read before the correction and write it back
afterwards (absolute poses), undoing the correction on that window; inline workers (what the evaluation
and the tests use) do not have this race.

A global bundle adjustment after the pose graph (ORB-SLAM2's last step) is not run: the pose graph plus the
rigid landmark update already makes the map consistent, and the local bundle adjustment refines it as the
vehicle goes on. This is a deliberate simplification, stated in the README.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from plvo.config import SystemConfig
from plvo.geometry import se3
from plvo.loop.closer import LoopCloser, LoopOutcome
from plvo.loop.verification import LoopKeyframe
from plvo.results import EDGE_LOOP, EDGE_ODOMETRY, GraphResult, LoopResult, MetricsResult
from plvo.tracking.keyframes import KeyframeInfo
from plvo.tracking.map import LandmarkMap
from plvo.types import Calibration
from plvo.workers import KeyframeWorker

log = logging.getLogger(__name__)


class LoopWorker(KeyframeWorker):
    """Detect and close loops against the shared map."""

    name = "loop closer"

    def __init__(self, calib: Calibration, config: SystemConfig, landmark_map: LandmarkMap):
        self.cfg = config
        self.map = landmark_map
        self.K = np.asarray(calib.K, dtype=float)
        self.closer = LoopCloser(self.K, cfg=config.loop, T_cam_velo=np.asarray(calib.T_cam_velo, float),
                                 reg_cfg=config.registration)
        self.n_corrections = 0
        self.loop_edges: list[tuple[int, int]] = []  # (match, query) keyframe ids of accepted loops
        super().__init__(threaded=config.backend.concurrent)

    def process(self, kf: KeyframeInfo) -> LoopOutcome | None:
        t0 = time.perf_counter()
        snap = self.map.snapshot()
        known = snap.keyframe_ids[: kf.kf_id]
        if len(known):
            self.closer.update_poses(known, snap.keyframe_T_world_cam[: kf.kf_id])
        lk = self._loop_keyframe(kf, snap.keyframe_T_world_cam[kf.kf_id])
        outcome = self.closer.on_keyframe(lk)
        t1 = time.perf_counter()
        if outcome.accepted is not None and outcome.poses_after is not None:
            self._apply(outcome)
        # loop_correct: the closer's pose graph; loop_apply: writing it into the map (under the map lock).
        self.add_timing({"loop_bow": 1e-3 * outcome.bow_ms, "loop_query": 1e-3 * outcome.query_ms,
                         "loop_verify": 1e-3 * outcome.verify_ms, "loop_correct": 1e-3 * outcome.correct_ms,
                         "loop_apply": time.perf_counter() - t1, "loop": time.perf_counter() - t0})
        self.emit(kf.frame_index, *self._results(kf.frame_index, outcome))
        return outcome

    def _loop_keyframe(self, kf: KeyframeInfo, T_world_cam: np.ndarray) -> LoopKeyframe:
        priors = kf.depth_priors
        if priors is None:  # no-depth-priors ablation: nothing metric to verify against
            f = kf.features
            return LoopKeyframe(kf.kf_id, T_world_cam, f.keypoints, f.descriptors,
                                np.full((f.n_points, 3), np.nan), f.segments, f.line_descriptors,
                                np.full((f.n_lines, 2, 3), np.nan), kf.frame.scan, kf.frame_index)
        return LoopKeyframe.from_features(kf.kf_id, T_world_cam, kf.features, priors, self.K, kf.frame.scan,
                                          kf.frame_index)

    def _apply(self, outcome: LoopOutcome) -> None:
        """Write the corrected poses into the map; move landmarks and newer keyframes rigidly along."""
        ids, after = np.asarray(outcome.kf_ids), np.asarray(outcome.poses_after)
        with self.map.lock:
            current = np.stack([self.map.keyframe_pose(int(k)) for k in ids])
            corr = after @ np.stack([se3.inv(T) for T in current])  # per keyframe: T_new T_old^-1
            later = np.arange(int(ids.max()) + 1, self.map.n_keyframes)
            all_ids = np.r_[ids, later]
            all_corr = np.concatenate([corr, np.repeat(corr[-1:], len(later), axis=0)])
            poses = np.stack([c @ self.map.keyframe_pose(int(k)) for c, k in zip(all_corr, all_ids)])
            row = {int(k): n for n, k in enumerate(all_ids)}
            pt_ids, pt_kf = self.map.point_ids_and_first_keyframes()
            ln_ids, ln_kf = self.map.line_ids_and_first_keyframes()
            pts = _move(self.map.point_positions(pt_ids), pt_kf, all_corr, row)
            lns = _move(self.map.line_endpoints(ln_ids).reshape(-1, 3), np.repeat(ln_kf, 2), all_corr, row)
            self.map.apply_update(pt_ids, pts, ln_ids, lns.reshape(-1, 2, 3), all_ids, poses)
        self.n_corrections += 1
        e = outcome.accepted
        self.loop_edges.append((e.match_id, e.query_id))
        log.info("loop %d -> %d closed: %d keyframes corrected", e.query_id, e.match_id, len(all_ids))

    def _results(self, frame_index: int, outcome: LoopOutcome) -> list[object]:
        """One LoopResult a verified candidate (or for the best candidate when none was verified)."""
        det = outcome.detection
        score = {int(c): float(s) for c, s in zip(det.candidates, det.normalised)}
        out: list[object] = []
        for v in outcome.verifications:
            out.append(LoopResult(
                frame_index, outcome.kf_id, int(v.cand_id), bool(v.accepted), score.get(int(v.cand_id), np.nan),
                int(v.n_point_inliers + v.n_line_inliers), v.T_cand_query if v.accepted else None, v.reason))
        if not outcome.verifications and len(det.candidates):
            out.append(LoopResult(frame_index, outcome.kf_id, int(det.candidates[0]), False,
                                  float(det.normalised[0]), 0, None, "; ".join(outcome.rejections)))
        if outcome.accepted is not None:
            out.append(self._graph(frame_index))
        out.append(MetricsResult(frame_index, {"loop_candidates": float(len(det.candidates)),
                                               "loop_verified": float(len(outcome.verifications)),
                                               "loop_closed": float(outcome.accepted is not None)}))
        return out

    def _graph(self, frame_index: int) -> GraphResult:
        """The corrected keyframe trajectory with its odometry chain and every loop edge (for the viewers)."""
        snap = self.map.snapshot()
        n = len(snap.keyframe_ids)
        chain = np.c_[np.arange(n - 1), np.arange(1, n)]
        loops = np.array(self.loop_edges, int).reshape(-1, 2)
        kinds = np.r_[np.full(len(chain), EDGE_ODOMETRY), np.full(len(loops), EDGE_LOOP)].astype(int)
        return GraphResult(frame_index, snap.keyframe_ids, snap.keyframe_T_world_cam, np.r_[chain, loops],
                           kinds, np.full(len(kinds), np.nan))


def _move(points: np.ndarray, first_kf: np.ndarray, corr: np.ndarray, row: dict[int, int]) -> np.ndarray:
    """(N,3) world points, (N,) keyframe that created each -> points moved by that keyframe's correction."""
    out = points.copy()
    idx = np.array([row.get(int(k), -1) for k in first_kf], int)
    ok = idx >= 0
    C = corr[idx[ok]]
    out[ok] = np.einsum("nij,nj->ni", C[:, :3, :3], points[ok]) + C[:, :3, 3]
    return out
