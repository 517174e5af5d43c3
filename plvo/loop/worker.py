"""The loop closer as the System runs it (paper II-F): one job a keyframe, a pure function of the jobs in order.

A `LoopJob` carries the keyframe as the closer keeps it (`LoopKeyframe`: features, depth priors as camera-frame 3D
points and lines, the scan) and every keyframe pose as the map had them when it was made. `LoopCore` runs it
through `LoopCloser` (BoW query, lidar place recognition, verification, on an accepted loop a pose-graph
correction) and returns a `LoopOutput`: the recorders' results and, for an accepted loop, a `MapCorrection` with
the loop edge. Each verified candidate becomes a `LoopResult` whose reason names the detector that proposed it
("bag of words" or "lidar place") and why it was accepted or refused. The System applies the output at a fixed
frame; then it submits a `GlobalBAJob` (every keyframe, graph edge and the points two keyframes see, read from the
map at that point), whose correction is applied at a later fixed frame. The core never touches the map.

The core's own estimate of the poses: the map's poses of the job, with the corrections this core made and the map
had not applied yet re-applied to them by the map's rule (plvo.tracking.corrections), so that a correction in
flight is neither lost nor applied twice. A correction's T_before is that estimate: when the map applies it, only
what moved since (the back end's refinements) is carried over.

The global bundle adjustment (plvo.loop.global_ba) refines every keyframe pose and every point landmark two
keyframes see, on the back end's registration edges (the pose graph's odometry where there are none) and the loop
edges plus the point factors; points it did not adjust and all lines move rigidly with the keyframe that created
them. Timings: loop_bow, loop_query, loop_lidar (the place recognition), loop_verify, loop_correct (pose graph),
loop_global_ba, loop (all), seconds, one entry a keyframe (the correction stages are 0 where no loop was
accepted).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from plvo.allocator import release_free_memory
from plvo.backend.problem import BAResult
from plvo.config import LoopSections
from plvo.loop import global_ba
from plvo.loop.closer import LoopCloser, LoopOutcome
from plvo.loop.verification import SOURCES, LoopKeyframe
from plvo.results import EdgeKind, LoopResult, MetricsResult
from plvo.tracking.corrections import GLOBAL_BA, LOOP, GlobalData, GraphEdge, MapCorrection, corrected_poses
from plvo.tracking.keyframes import KeyframeInfo
from plvo.tracking.map import Observations
from plvo.types import Calibration

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LoopJob:
    """One keyframe for the loop closer: the keyframe (its scan deskewed where the data needs it, plvo.runtime.system),
    every keyframe pose (K,4,4) by id as the map had them, how many of the loop closer's corrections the map had
    applied then."""

    kf_id: int
    frame_index: int
    keyframe: LoopKeyframe
    T_world_cam: np.ndarray
    corrections_applied: int

    def with_scan(self, scan: np.ndarray) -> LoopJob:
        """The job with its keyframe's scan replaced (by the deskewed one); a keyframe without a scan as it is."""
        if self.keyframe.scan is None:
            return self
        return dataclasses.replace(self, keyframe=dataclasses.replace(self.keyframe, scan=scan))


@dataclass(frozen=True)
class GlobalBAJob:
    """The global bundle adjustment after an applied loop correction: the map's data (GlobalData), how far the
    pose graph moved the keyframes (m), and how many of the closer's corrections the map had applied."""

    frame_index: int
    data: GlobalData
    correction_m: float
    corrections_applied: int


@dataclass(frozen=True)
class LoopOutput:
    """A job's answer: the correction for the map (None when none), the results for the recorders (LoopResult,
    MetricsResult), timings (seconds by stage), and for a global BA its result or why it was rejected."""

    frame_index: int
    correction: MapCorrection | None
    results: tuple = ()
    timings: dict[str, float] = field(default_factory=dict)
    outcome: LoopOutcome | None = None
    global_ba: BAResult | None = None
    rejected: str = ""

    @property
    def correction_m(self) -> float:
        """The largest keyframe move of a loop correction (m), 0 otherwise."""
        c = self.correction
        if c is None or c.source != LOOP:
            return 0.0
        return float(np.linalg.norm(c.T_after[:, :3, 3] - c.T_before[:, :3, 3], axis=1).max())


class LoopCore:
    """Detect and close loops; a pure function of its jobs in order (see the module doc)."""

    def __init__(self, calib: Calibration, config: LoopSections):
        self.cfg = config
        self.K = np.asarray(calib.K, dtype=float)
        self.closer = LoopCloser(self.K, cfg=config.loop, T_cam_velo=np.asarray(calib.T_cam_velo, float),
                                 reg_cfg=config.registration)
        self._made: list[MapCorrection] = []  # every correction this core returned, in order
        self._skipped = 0  # global BAs skipped since the last one that ran (superseded by a later loop)

    def process(self, job: LoopJob | GlobalBAJob) -> LoopOutput:
        if isinstance(job, GlobalBAJob):
            return self._global_ba(job)
        return self._keyframe(job)

    def _estimate(self, poses: np.ndarray, applied: int) -> np.ndarray:
        """The map's poses with this core's corrections the map had not applied yet."""
        for c in self._made[applied:]:
            poses = corrected_poses(c, poses)[0]
        return poses

    def _keyframe(self, job: LoopJob) -> LoopOutput:
        t0 = time.perf_counter()
        poses = self._estimate(np.asarray(job.T_world_cam, float), job.corrections_applied)
        if job.kf_id:
            self.closer.update_poses(np.arange(job.kf_id), poses[: job.kf_id])
        lk = dataclasses.replace(job.keyframe, T_world_cam=poses[job.kf_id])
        outcome = self.closer.on_keyframe(lk)
        correction = None
        if outcome.accepted is not None and outcome.poses_before is not None and outcome.poses_after is not None:
            e = outcome.accepted
            correction = MapCorrection(LOOP, np.asarray(outcome.kf_ids, np.int64), outcome.poses_before,
                                       outcome.poses_after,
                                       edges=(GraphEdge(e.match_id, e.query_id, e.T_match_query, 1.0, EdgeKind.LOOP),))
            self._made.append(correction)
        corrected = correction is not None
        timings = {"loop_bow": 1e-3 * outcome.bow_ms, "loop_query": 1e-3 * outcome.query_ms,
                   "loop_lidar": 1e-3 * outcome.lidar_ms, "loop_verify": 1e-3 * outcome.verify_ms,
                   "loop_correct": 1e-3 * outcome.correct_ms if corrected else 0.0,
                   "loop": time.perf_counter() - t0}
        return LoopOutput(job.frame_index, correction, tuple(_results(job.frame_index, outcome)), timings, outcome)

    def _global_ba(self, job: GlobalBAJob) -> LoopOutput:
        """Bundle-adjust all keyframes and the points two of them see -> a correction (or why it was rejected)."""
        t0 = time.perf_counter()
        d = job.data
        if len(self._made) > job.corrections_applied:
            # A later loop was closed after this job's data was read (the loop jobs queued before it ran first):
            # its landmarks lack that correction, and the System submits another global BA once it is applied.
            log.info("global BA after the loop at frame %d skipped: a later loop correction supersedes it",
                     job.frame_index)
            self._skipped += 1
            return LoopOutput(job.frame_index, None, rejected="superseded by a later loop correction")
        poses = np.asarray(d.T_world_cam, float)
        ids = np.asarray(d.kf_ids, np.int64)
        if not len(d.landmark):
            return LoopOutput(job.frame_index, None, timings={"loop_global_ba": time.perf_counter() - t0})
        depth = d.depth if self.cfg.tracking.use_depth_priors else np.full(len(d.landmark), np.nan)
        obs = Observations(d.landmark, np.searchsorted(ids, d.keyframe), np.zeros(len(d.landmark), np.int64),
                           d.measurement)
        edges, rotation_ratio = self._edges(ids, d.edges)
        problem, pt_ids = global_ba.build_problem(self.K, poses, edges, obs, d.positions, depth, self.cfg.loop,
                                                   self.cfg.backend, rotation_ratio, d.depth_rms)
        # It does the work of the one it superseded too: twice the iterations (not more, so that its cost stays
        # bounded when several loops close in a row).
        iterations = self.cfg.loop.global_ba_iterations * (1 + min(self._skipped, 1))
        loop_cfg = dataclasses.replace(self.cfg.loop, global_ba_iterations=iterations)
        self._skipped = 0
        res = global_ba.optimize(problem, self.cfg.backend, loop_cfg, self.cfg.tracking.use_depth_priors,
                                 self.cfg.backend.stereo_baseline_m)
        del problem
        release_free_memory()  # the adjustment's peak is freed but kept by the C heap otherwise (plvo.allocator)
        timings = {"loop_global_ba": time.perf_counter() - t0}
        why = global_ba.implausible(poses, res, self.cfg.loop, job.correction_m)
        if why:
            log.warning("global BA rejected, the pose graph's result is kept: %s", why)
            return LoopOutput(job.frame_index, None, timings=timings, global_ba=res, rejected=why)
        used = res.point_used
        correction = MapCorrection(GLOBAL_BA, ids, poses, res.T_world_cam, point_ids=pt_ids[used],
                                   point_positions=res.points[used], base_version=d.version)
        self._made.append(correction)
        return LoopOutput(job.frame_index, correction, timings=timings, global_ba=res)

    def _edges(self, ids: np.ndarray, graph: tuple[GraphEdge, ...]
               ) -> tuple[list[tuple[int, int, np.ndarray, float]], np.ndarray]:
        """Relative-pose edges (i, j, T_i_j, zeta) by index into ids for the global BA: the back end's
        registrations where it provides them, else the pose graph's odometry; every loop edge with zeta 1; and
        each edge's rotation information against its translation's (a registration's as the back end weighed it)."""
        odometry, _ = self.closer.pose_graph_edges()
        row = {int(k): n for n, k in enumerate(ids)}
        weak = global_ba.pose_graph_zeta(self.cfg.loop, self.cfg.backend)
        odometry_edges = [e for e in graph if e.kind == EdgeKind.ODOMETRY and e.i in row and e.j in row and e.zeta > 0]
        registered = [(row[e.i], row[e.j], e.T_i_j, e.information) for e in odometry_edges]
        have = {(i, j) for i, j, _, _ in registered}
        closer_ids = self.closer.poses()[0]
        fallback = [(row[int(closer_ids[i])], row[int(closer_ids[j])], T, weak) for i, j, T in odometry
                    if int(closer_ids[i]) in row and int(closer_ids[j]) in row]
        loops = [(row[e.i], row[e.j], e.T_i_j, 1.0) for e in graph
                 if e.kind == EdgeKind.LOOP and e.i in row and e.j in row]
        rest = [e for e in fallback if (e[0], e[1]) not in have] + loops
        ratio = np.r_[[e.rotation_ratio for e in odometry_edges], np.ones(len(rest))]
        return registered + rest, ratio


def loop_keyframe(kf: KeyframeInfo, K: np.ndarray) -> LoopKeyframe:
    """A tracker KeyframeInfo -> the LoopKeyframe the closer keeps (camera-frame 3D from its depth priors)."""
    priors = kf.depth_priors
    scan = kf.registration_scan  # for the verification's registration
    if priors is None:  # no-depth-priors ablation: nothing metric to verify against
        f = kf.features
        return LoopKeyframe(kf.kf_id, np.asarray(kf.T_world_cam, float), f.keypoints, f.descriptors,
                            np.full((f.n_points, 3), np.nan), f.segments, f.line_descriptors,
                            np.full((f.n_lines, 2, 3), np.nan), scan, kf.frame_index)
    return LoopKeyframe.from_features(kf.kf_id, kf.T_world_cam, kf.features, priors, K, scan, kf.frame_index)


def _results(frame_index: int, outcome: LoopOutcome) -> list[object]:
    """One LoopResult a verified candidate (or for the best candidate of each detector when none was verified),
    and the counts. The reason begins with the detector that proposed the candidate; n_inliers is the PnP/PnL
    inliers of a bag-of-words candidate, the density-map inliers of a lidar place's; query_keyframe is the keyframe
    whose place was matched (for a lidar place, a node lidar_place_reach_m behind the job's keyframe)."""
    det = outcome.detection
    score = {int(c): float(s) for c, s in zip(det.candidates, det.normalised)}
    out: list[object] = []
    for v in outcome.verifications:
        out.append(LoopResult(
            frame_index, int(v.query_id), int(v.cand_id), bool(v.accepted), score.get(int(v.cand_id), np.nan),
            int(v.support), v.T_cand_query if v.accepted else None, f"{v.source}: {v.reason}"))
    if not outcome.verifications:
        why = "; ".join(outcome.rejections)
        if len(det.candidates):
            out.append(LoopResult(frame_index, outcome.kf_id, int(det.candidates[0]), False,
                                  float(det.normalised[0]), 0, None, f"{SOURCES['bow']}: {why}"))
        for p in outcome.places:
            if p.candidates:
                c = p.candidates[0]
                out.append(LoopResult(frame_index, p.kf_id, c.kf_id, False, np.nan, c.inliers, None,
                                      f"{SOURCES['lidar']}: {why}"))
    n_place = sum(len(p.candidates) for p in outcome.places)
    out.append(MetricsResult(frame_index, {"loop_candidates": float(len(det.candidates)),
                                           "loop_place_candidates": float(n_place),
                                           "loop_verified": float(len(outcome.verifications)),
                                           "loop_closed": float(outcome.accepted is not None)}))
    return out
