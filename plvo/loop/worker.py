"""The loop closer as the System runs it (paper II-F): one keyframe at a time, inline or in its own thread.

Each keyframe is turned into a `LoopKeyframe` (features, depth priors as camera-frame 3D points and lines, the
thinned scan) and run through `LoopCloser`: BoW query, verification, and on an accepted loop a pose-graph
correction. The corrected keyframe poses are written into the shared map; every landmark moves rigidly with the
keyframe that created it, and keyframes the tracker made meanwhile move with the newest corrected one. The
tracker follows through its re-anchoring on the last keyframe. After a correction a GraphResult with the corrected
keyframe trajectory, its odometry chain and the loop edges goes to the recorders; timings: loop_bow, loop_query,
loop_verify, loop_correct (pose graph), loop_apply (map update), loop_global_ba, loop (all), seconds, one entry a
keyframe (the three correction stages are 0 where no loop was accepted).

After the pose graph, a global bundle adjustment (plvo.loop.global_ba) refines every keyframe pose and every
point landmark two keyframes see, on the back end's registration factors (`registration_edges`, set by the
System; the pose graph's odometry where there are none) and the loop edges plus the point factors; points it did
not adjust and all lines move rigidly with the keyframe that created them. It holds the GIL while gtsam builds and
solves the graph (0.5-2 s a loop at 150-290 keyframes), so a concurrent tracker slows meanwhile.
`loop.global_ba = false` stops after the pose graph.

With `backend.concurrent` the back end may be optimising a window read before the correction and write it back
afterwards; it rebases that window on its first keyframe's corrected pose, so the correction survives, but the
window's relative poses are the pre-correction ones. Inline workers (what the evaluation and the tests use) do
not have this race.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from plvo.config import SystemConfig
from plvo.geometry import se3
from plvo.loop import global_ba
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
        self.last_global_ba = None  # BAResult of the latest global bundle adjustment
        self.global_ba_rejected = 0
        # () -> [(kf i, kf j, T_i_j, zeta)]: the back end's registration factors (set by the System), or None
        self.registration_edges = None
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
        t_gba = 0.0
        corrected = outcome.accepted is not None and outcome.poses_after is not None
        if corrected:
            self._apply(outcome)
            t2 = time.perf_counter()
            if self.cfg.loop.global_ba:
                moved = np.linalg.norm(outcome.poses_after[:, :3, 3] - outcome.poses_before[:, :3, 3], axis=1)
                self._global_ba(float(moved.max()))
            t_gba = time.perf_counter() - t2
        # loop_correct: the closer's pose graph; loop_apply: writing it into the map (under the map lock).
        # The correction stages are exactly 0 where no loop was accepted (bench reports them over corrections).
        self.add_timing({"loop_bow": 1e-3 * outcome.bow_ms, "loop_query": 1e-3 * outcome.query_ms,
                         "loop_verify": 1e-3 * outcome.verify_ms,
                         "loop_correct": 1e-3 * outcome.correct_ms if corrected else 0.0,
                         "loop_apply": time.perf_counter() - t1 - t_gba if corrected else 0.0,
                         "loop_global_ba": t_gba, "loop": time.perf_counter() - t0})
        self.emit(kf.frame_index, *self._results(kf.frame_index, outcome))
        return outcome

    def _loop_keyframe(self, kf: KeyframeInfo, T_world_cam: np.ndarray) -> LoopKeyframe:
        priors = kf.depth_priors
        scan = kf.registration_scan  # for the verification's registration
        if priors is None:  # no-depth-priors ablation: nothing metric to verify against
            f = kf.features
            return LoopKeyframe(kf.kf_id, T_world_cam, f.keypoints, f.descriptors,
                                np.full((f.n_points, 3), np.nan), f.segments, f.line_descriptors,
                                np.full((f.n_lines, 2, 3), np.nan), scan, kf.frame_index)
        return LoopKeyframe.from_features(kf.kf_id, T_world_cam, kf.features, priors, self.K, scan, kf.frame_index)

    def _apply(self, outcome: LoopOutcome) -> None:
        """Write the pose graph's poses into the map; move landmarks and newer keyframes rigidly along."""
        n = self._write(np.asarray(outcome.kf_ids), np.asarray(outcome.poses_after))
        self.n_corrections += 1
        e = outcome.accepted
        self.loop_edges.append((e.match_id, e.query_id))
        log.info("loop %d -> %d closed: %d keyframes corrected", e.query_id, e.match_id, n)

    def _global_ba(self, correction_m: float) -> None:
        """Bundle-adjust all keyframes and the points two of them see (global_ba.py), write the result back."""
        ids, _ = self.closer.poses()
        poses = np.stack([self.map.keyframe_pose(int(k)) for k in ids])  # with the landmarks' current frame
        edges = self._edges(ids)
        obs = self.map.point_observations()
        keep = np.isin(obs.keyframe, ids)
        counts = np.bincount(obs.landmark[keep], minlength=int(obs.landmark.max(initial=-1)) + 1)
        keep &= counts[obs.landmark] >= 2  # a landmark one keyframe sees tells the poses nothing
        obs = dataclasses.replace(obs, landmark=obs.landmark[keep], keyframe=obs.keyframe[keep],
                                  feature=obs.feature[keep], measurement=obs.measurement[keep])
        if not len(obs.landmark):
            return
        depth = np.full(len(obs.feature), np.nan)
        if self.cfg.tracking.use_depth_priors:
            for k in np.unique(obs.keyframe):
                sel = obs.keyframe == k
                depth[sel] = self.closer.point_depth(int(k), obs.feature[sel])
        row = np.searchsorted(ids, obs.keyframe)
        obs = dataclasses.replace(obs, keyframe=row)
        positions = self.map.point_positions(np.unique(obs.landmark))
        problem, pt_ids = global_ba.build_problem(self.K, poses, edges, obs, positions, depth, self.cfg.loop,
                                                   self.cfg.backend)
        res = global_ba.optimize(problem, self.cfg.backend, self.cfg.loop, self.cfg.tracking.use_depth_priors,
                                 self.cfg.backend.stereo_baseline_m)
        used = res.point_used
        why = global_ba.implausible(poses, res, self.cfg.loop, correction_m)
        if why:
            log.warning("global BA rejected, the pose graph's result is kept: %s", why)
            self.global_ba_rejected += 1
            return
        self._write(ids, res.T_world_cam, pt_ids[used], res.points[used])
        self.closer.update_poses(ids, res.T_world_cam)
        self.last_global_ba = res

    def _edges(self, ids: np.ndarray) -> list[tuple[int, int, np.ndarray, float]]:
        """Relative-pose edges (i, j, T_i_j, zeta) by index into ids for the global BA: the back end's
        registrations where it provides them, else the pose graph's odometry; every loop edge with zeta 1."""
        odometry, loops = self.closer.pose_graph_edges()
        weak = global_ba.pose_graph_zeta(self.cfg.loop, self.cfg.backend)
        edges = [(i, j, T, weak) for i, j, T in odometry]
        if self.registration_edges is not None:
            row = {int(k): n for n, k in enumerate(ids)}
            registered = [(row[i], row[j], T, z) for i, j, T, z in self.registration_edges()
                          if i in row and j in row and z > 0]
            have = {(i, j) for i, j, _, _ in registered}
            edges = registered + [e for e in edges if (e[0], e[1]) not in have]
        return edges + [(i, j, T, 1.0) for i, j, T in loops]

    def _write(self, ids: np.ndarray, after: np.ndarray, point_ids: np.ndarray | None = None,
               point_positions: np.ndarray | None = None) -> int:
        """Set keyframes ids to poses after (K,4,4); keyframes made since move with the last of them; landmarks
        move rigidly with the keyframe that created them, except point_ids, set to point_positions. Returns the
        number of keyframes moved."""
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
            if point_ids is not None and len(point_ids):
                pts[np.searchsorted(pt_ids, point_ids)] = point_positions
            lns = _move(self.map.line_endpoints(ln_ids).reshape(-1, 3), np.repeat(ln_kf, 2), all_corr, row)
            self.map.apply_update(pt_ids, pts, ln_ids, lns.reshape(-1, 2, 3), all_ids, poses)
        return len(all_ids)

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
