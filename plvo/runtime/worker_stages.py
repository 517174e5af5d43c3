"""The System's side of each worker: the job it makes from a keyframe, and what it does with the output.

`BackendStage` (registration, scale correction, bundle adjustment of the window) and `LoopStage` (loop detection,
pose-graph correction, global bundle adjustment) each own their channel of the run's `plvo.runtime.scheduler.Scheduler`.
They write the map only through `LandmarkMap.apply`, in the tracking thread, when the scheduler says a result is
due; everything they produce for the recorders goes through `emit`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from plvo.allocator import release_free_memory
from plvo.config import SystemConfig
from plvo.results import CorrectionEvent, EdgeKind, GraphResult, MapResult, MetricsResult, StageSteps
from plvo.runtime.scheduler import Channel, Lags, Scheduler
from plvo.runtime.workers import OrderedWorker
from plvo.tracking.corrections import GLOBAL_BA, LOOP, MapCorrection
from plvo.tracking.frontend import Frontend
from plvo.tracking.keyframes import KeyframeInfo
from plvo.tracking.map import LandmarkMap

log = logging.getLogger(__name__)

Emit = Callable[[int, Iterable[Any]], None]  # (frame index, results for the recorders)


@dataclass
class LoopStats:
    """What the workers' results did over a run (the soak reports it): loop corrections and global BAs applied,
    global BAs rejected or superseded, back-end optimisations discarded, keyframes solved again on a refined map."""

    corrections: int = 0
    global_ba: int = 0
    global_ba_rejected: int = 0
    global_ba_superseded: int = 0
    backend_discarded: int = 0
    relocalised: int = 0


@dataclass
class RunRecord:
    """What the stages tell the run: per-stage seconds (one entry a time a stage ran), the counts, one entry an
    applied loop or global BA correction, one an applied back-end result's stage record."""

    timings: dict[str, list[float]]
    stats: LoopStats = field(default_factory=LoopStats)
    corrections: list[CorrectionEvent] = field(default_factory=list)
    stage_steps: list[StageSteps] = field(default_factory=list)

    def add_timings(self, seconds: dict[str, float]) -> None:
        for name, value in seconds.items():
            self.timings[name].append(value)


class GraphView:
    """The keyframe graph as the map has it now (poses, odometry and loop edges, zeta), for the recorders. The map
    only appends edges: their arrays grow by what is new instead of being rebuilt each keyframe."""

    def __init__(self, map_: LandmarkMap):
        self._map = map_
        self._rows = (np.zeros((0, 2), int), np.zeros(0, int), np.zeros(0))

    def result(self, frame_index: int, scale: float = 1.0) -> GraphResult:
        poses, new = self._map.poses(), self._map.edges[len(self._rows[0]):]
        pairs, kinds, zeta = self._rows
        if new:
            pairs = np.r_[pairs, np.array([(e.i, e.j) for e in new], int).reshape(-1, 2)]
            kinds = np.r_[kinds, np.array([e.kind for e in new], int)]
            zeta = np.r_[zeta, np.array([np.nan if e.kind == EdgeKind.LOOP else e.zeta for e in new], float)]
            self._rows = (pairs, kinds, zeta)
        return GraphResult(frame_index, np.arange(len(poses)), poses, pairs, kinds, zeta, scale)


class BackendStage:
    """Each keyframe's window to the back end; its correction to the map when due."""

    def __init__(self, worker: OrderedWorker, scheduler: Scheduler, lags: Lags, frontend: Frontend,
                 config: SystemConfig, graph: GraphView, record: RunRecord, emit: Emit):
        self.channel: Channel = scheduler.channel("backend", worker, self.apply, lags.backend)
        self._scheduler, self._frontend, self._map = scheduler, frontend, frontend.map
        self._uses_lines, self._config = frontend.uses_lines, config
        self._graph, self._record, self._emit = graph, record, emit

    def catch_up(self, frame_index: int) -> None:
        """Before a keyframe's window is read: apply every earlier result still in flight. The keyframe was then
        tracked on the map before them, and is solved again on the map they refined (Frontend.relocalise_keyframe),
        so that it starts its window where inline it would."""
        if not self._scheduler.drain(self.channel):
            return
        correction = self._frontend.relocalise_keyframe()
        if correction is None:
            return
        self._map.apply(correction)
        self._record.stats.relocalised += 1
        moved = float(np.linalg.norm(correction.T_after[0][:3, 3] - correction.T_before[0][:3, 3]))
        log.debug("keyframe %d solved again on the refined map: moved %.3f m", correction.keyframe_ids[0], moved)
        self._emit(frame_index, [MetricsResult(frame_index, {"relocalised_m": moved})])

    def job(self, kf: KeyframeInfo) -> Any:
        from plvo.backend.worker import BackendJob  # with the back end's module: open3d and gtsam

        n = max(2, self._config.backend.window_keyframes)
        ids = np.arange(max(0, kf.kf_id - n + 1), kf.kf_id + 1)
        scan = kf.registration_scan if self._config.backend.registration else None
        return BackendJob(kf.kf_id, kf.frame_index, scan, self._map.window_data(ids, self._uses_lines))

    def apply(self, out: Any) -> None:
        if out.correction is not None:
            self._map.apply(out.correction)
        if out.step.ba is None and "bundle_adjustment" in out.step.seconds:
            self._record.stats.backend_discarded += 1
        self._record_stages(out)
        self._record.add_timings(out.step.seconds)
        self._emit(out.frame_index, [self._graph.result(out.frame_index, out.step.scale),
                                     MapResult(out.frame_index, out.points, out.lines),
                                     MetricsResult(out.frame_index, out.metrics)])


    def _record_stages(self, out: Any) -> None:
        if not out.stage_poses or len(out.stage_kf_ids) != 2:
            return
        prev, new = (int(k) for k in out.stage_kf_ids)
        steps = {stage: np.linalg.inv(T[0]) @ T[1] for stage, T in out.stage_poses.items()}
        self._record.stage_steps.append(StageSteps((self._map.keyframe_frame(prev), self._map.keyframe_frame(new)),
                                                   steps))


class LoopStage:
    """Each keyframe to the loop closer; its corrections to the map when due, and after a loop correction the
    global bundle adjustment, submitted on the same channel."""

    def __init__(self, worker: OrderedWorker, scheduler: Scheduler, lags: Lags, map_: LandmarkMap, K: np.ndarray,
                 config: SystemConfig, graph: GraphView, record: RunRecord, emit: Emit, now: Callable[[], int]):
        self.channel: Channel = scheduler.channel("loop", worker, self.apply, lags.loop)
        self._scheduler, self._lags, self._map, self._K = scheduler, lags, map_, np.asarray(K, float)
        self._config, self._graph, self._record, self._emit, self._now = config, graph, record, emit, now
        # The largest pose-graph move of the loops since the last applied global BA: a global BA that supersedes
        # skipped ones refines all of their corrections, and is judged against the largest (global_ba.implausible).
        self._pose_graph_move_m = 0.0

    def job(self, kf: KeyframeInfo) -> Any:
        from plvo.loop.worker import LoopJob, loop_keyframe

        return LoopJob(kf.kf_id, kf.frame_index, loop_keyframe(kf, self._K), self._map.poses(),
                       self._scheduler.loop_corrections_applied)

    def apply(self, out: Any) -> None:
        t0 = time.perf_counter()
        c = out.correction
        if c is not None:
            before = self._map.poses()
            self._map.apply(c)
            self._scheduler.loop_corrections_applied += 1
            self._record.corrections.append(self._event(c, before, out))
        stats = self._record.stats
        if out.rejected.startswith("superseded"):
            stats.global_ba_superseded += 1
        elif out.rejected:
            stats.global_ba_rejected += 1
        results = list(out.results)
        if c is not None and c.source == LOOP:
            stats.corrections += 1
            e = c.edges[0]
            log.info("loop %d -> %d closed: %d keyframes corrected", e.j, e.i, self._map.n_keyframes)
            if self._config.loop.global_ba:
                self._submit_global_ba(out)
        if c is not None:
            if c.source == GLOBAL_BA:
                stats.global_ba += 1
                self._pose_graph_move_m = 0.0
            results.append(self._graph.result(out.frame_index))
        timings = dict(out.timings)
        if c is not None:
            timings["loop_apply"] = time.perf_counter() - t0
        self._record.add_timings(timings)
        self._emit(out.frame_index, results)
        if c is not None:  # a correction of the whole map: its temporaries were the size of the map (plvo.allocator)
            release_free_memory()
        if c is not None and c.source == LOOP and self._lags.global_ba == 0:
            self._scheduler.drain(self.channel)

    def _submit_global_ba(self, out: Any) -> None:
        from plvo.loop.worker import GlobalBAJob

        self._pose_graph_move_m = max(self._pose_graph_move_m, out.correction_m)
        job = GlobalBAJob(out.frame_index, self._map.global_data(), self._pose_graph_move_m,
                          self._scheduler.loop_corrections_applied)
        self._scheduler.submit(self.channel, job, self._now(), lag=self._lags.global_ba)

    def _event(self, c: MapCorrection, before: np.ndarray, out: Any) -> CorrectionEvent:
        """What an applied loop-closer correction did: source, frames, keyframes, how far it moved them."""
        after = self._map.poses()
        moved = np.linalg.norm(after[:, :3, 3] - before[:, :3, 3], axis=1)
        loop = c.edges[0] if c.source == LOOP else None
        return CorrectionEvent(
            c.source, int(out.frame_index), int(self._now()), int(len(after)), float(moved.max(initial=0.0)),
            float(moved[-1]) if len(moved) else 0.0,
            float(sum(out.timings.values()) if c.source == GLOBAL_BA else out.timings.get("loop_correct", 0.0)),
            None if loop is None else int(loop.j), None if loop is None else int(loop.i))
