"""The System: wires the stages together, one `step(frame)` a frame, and hands every result to the recorders.

Tracking runs in the caller's thread: features -> matching -> PnP/PnL -> keyframe decision; on a keyframe the
depth priors and new landmarks (all inside `plvo.tracking.frontend.Frontend`). Each keyframe then goes, as a job
read from the map at that moment, to the back end (registration, scale correction, bundle adjustment;
`plvo.backend.worker.BackendCore`) and to the loop closer (`plvo.loop.worker.LoopCore`), each run by a
`plvo.workers.OrderedWorker` inline, in a thread or in a worker process.

The map has one owner and one writer: this thread. Workers return typed corrections, which the System applies
(`LandmarkMap.apply`) at fixed points of the run, waiting there for a worker that is late:
- a keyframe's back-end result at the start of frame (its frame + backend.max_lag_frames), or before the next
  keyframe's window is read, whichever comes first; in the latter case the next keyframe was tracked on the map
  before that result, and is solved again on the refined one (`Frontend.relocalise_keyframe`) before its window
  is read;
- a keyframe's loop result at the start of frame (its frame + loop.max_lag_frames); after an applied loop
  correction the global bundle adjustment is submitted, its result applied loop.global_ba_lag_frames later.
So the tracker runs ahead of the workers by a bounded lag and the trajectory does not depend on the machine's load
or the workers' speed: a slower worker costs frames a second, never accuracy. Inline (`backend.concurrent =
false`) every lag is 0: each keyframe is fully processed before the next frame.

Poses: the back end moves keyframes after the tracker has passed them. Every frame's pose is kept relative to the
keyframe it was tracked from, and `poses` composes it with that keyframe's current pose, so the reported
trajectory carries every refinement (as ORB-SLAM2 reports its trajectory).

The System imports no viewer: recorders (Rerun, viser) are handed in from `plvo_app`.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import time
from collections import defaultdict
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from plvo.config import SystemConfig
from plvo.geometry import se3
from plvo.heap import release_free_memory
from plvo.priority import LOOKAHEAD_NICENESS
from plvo.recording import NullRecorder, Recorder, RunInfo
from plvo.results import EDGE_LOOP, GraphResult, KeyframeResult, MapResult, MetricsResult, TimingResult, TrackingResult
from plvo.tracking.corrections import GLOBAL_BA, LOOP
from plvo.types import Calibration, Frame
from plvo.workers import OrderedWorker

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StepOutput:
    """What one step produced: the tracking result and the keyframe made (or None)."""

    frame_index: int
    tracking: TrackingResult
    keyframe: KeyframeResult | None
    timing: TimingResult


@dataclass(frozen=True)
class RunOutput:
    """A whole run: poses (N,4,4) T_world_cam0 of the frames in order, per-stage timings (seconds per run)."""

    frame_indices: tuple[int, ...]
    poses: np.ndarray
    timings: dict[str, list[float]]
    n_keyframes: int
    n_lost: int
    finished_at: float = 0.0  # time.perf_counter() once the workers' last results were applied (before closing)


@dataclass
class _Clock:
    seconds: dict[str, float] = field(default_factory=dict)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds


class System:
    """Runs the pipeline frame by frame and streams each stage's result to `recorder`."""

    def __init__(self, config: SystemConfig, recorder: Recorder | None = None, calib: Calibration | None = None):
        """calib: the sequence's calibration, when known before the first frame: the stages and the worker
        processes are then made at once, so that the workers start up (~1-2 s of imports on two cores) while the
        caller sets up its recorders and viewer, instead of while the first frames are tracked."""
        self.config = config
        self.recorder = recorder if recorder is not None else NullRecorder()
        self.timings: dict[str, list[float]] = defaultdict(list)  # stage -> seconds, one entry a time it ran
        self.frames_done = 0
        self.n_lost = 0
        self._frame_ref: dict[int, tuple[int, np.ndarray]] = {}  # frame -> (keyframe id, T_kf_cam)
        self._frontend = None
        self._backend: OrderedWorker | None = None
        self._loop: OrderedWorker | None = None
        self._features: OrderedWorker | None = None  # the features process (deployed mode: plvo.features.worker)
        self._due: dict[str, collections.deque] = {"backend": collections.deque(), "loop": collections.deque()}
        self.loop_stats = {"corrections": 0, "global_ba": 0, "global_ba_rejected": 0, "backend_discarded": 0,
                           "relocalised": 0}
        # One entry an applied loop or global BA correction: what it moved, when (for the soak and the log).
        self.corrections: list[dict[str, Any]] = []
        self._calib: Calibration | None = None
        self._clock = _Clock()
        self._depth_debug: list[Any] = []
        self._ref_kf = -1
        self._frame_now = 0
        # The largest pose-graph move of the loops since the last applied global BA: a global BA that supersedes
        # skipped ones refines all of their corrections, and is judged against the largest (global_ba.implausible).
        self._pose_graph_move_m = 0.0
        self._edge_rows = (np.zeros((0, 2), int), np.zeros(0, int), np.zeros(0))  # the graph's edges so far (_graph)
        if calib is not None:
            self._build(calib)

    @property
    def map(self):
        return None if self._frontend is None else self._frontend.map

    def start(self, info: RunInfo) -> None:
        """Start the recorders, then wait for the workers to be ready (see `wait_ready`)."""
        self.recorder.on_run_start(info)
        self.wait_ready()

    def prepare(self, frame: Frame) -> Frame:
        """The frame with the tracker's features extracted (`Frame.features`): the prefetching thread calls it, so
        that extraction overlaps tracking the frames before and waiting for the workers. Features depend on the
        image and the config alone, so the trajectory is the same. Before the stages are built (no calib given to
        the System), the frame is returned as it is and the tracker extracts them itself."""
        frontend = self._frontend
        if frontend is None or frame.features is not None:
            return frame
        t0 = time.perf_counter()
        features = frontend.features(frame.image)
        return dataclasses.replace(frame, features=features, features_s=time.perf_counter() - t0)

    def read_ahead(self, dataset) -> Iterator[Frame]:
        """The dataset's frames as the System is meant to take them: read, and prepared (`prepare`), up to two
        ahead in a thread at the look-ahead's priority (plvo.priority), while the frames before are tracked; in the
        deployed mode their features are extracted in the features process, one more frame ahead."""
        from plvo.data.prefetch import prefetched

        # A frame's wait includes its features' (bounded by the workers' timeout): the read gets a minute more
        timeout_s = self.config.backend.worker_timeout_s + 60.0
        if self._features is None:
            return prefetched(dataset, prepare=self.prepare, niceness=LOOKAHEAD_NICENESS, timeout_s=timeout_s)
        return prefetched(dataset, prepare=self._start_features, finish=self._take_features,
                          niceness=LOOKAHEAD_NICENESS, timeout_s=timeout_s)

    def _start_features(self, frame: Frame) -> bool:
        """Queue the frame's image in the features process -> whether it was (not when it has its features)."""
        from plvo.features.worker import FeaturesJob

        if frame.features is not None:
            return False
        self._features.submit(FeaturesJob(frame.index, frame.image))
        return True

    def _take_features(self, frame: Frame, started: bool) -> Frame:
        if not started:
            return frame
        features, seconds = self._features.take()
        return dataclasses.replace(frame, features=features, features_s=seconds)

    def wait_ready(self) -> None:
        """Wait until the worker processes have made their cores (their imports: ~1-2 s on two cores, which the
        recorders' and viewer's start-up hides in part), so that the first frames are not timed waiting for them;
        the wait is timed as `workers_ready` (seconds, once). A worker that cannot start raises WorkerError here."""
        if "workers_ready" in self.timings or self._frontend is None:
            return
        t0 = time.perf_counter()
        for worker in self._workers:
            worker.wait_ready()
        self.timings["workers_ready"].append(time.perf_counter() - t0)

    @property
    def _workers(self) -> list[OrderedWorker]:
        return [w for w in (self._backend, self._loop, self._features) if w is not None]

    @property
    def worker_pids(self) -> list[int]:
        """The worker processes' ids (back end, loop closer, features, those made; none inline or in threads)."""
        return [w.pid for w in self._workers if w.pid is not None]

    def _build(self, calib: Calibration) -> None:
        from plvo.backend.worker import BackendCore
        from plvo.depth.extract import extract_depth
        from plvo.features.extract import extract_features
        from plvo.features.matching import match_lines, match_points
        from plvo.tracking.frontend import Frontend

        def depth(scan, features, calib_, cfg):
            # the tracker wants the priors; the viewers also want what the extraction saw (DepthDebug)
            t0 = time.perf_counter()
            out = extract_depth(scan, features, calib_, cfg)
            self._clock.add("depth", time.perf_counter() - t0)
            self._depth_debug = [out.priors, out.debug]
            return out.priors

        self._calib = calib
        self._frontend = Frontend(calib, self.config, stages=(extract_features, match_points, match_lines, depth))
        b = self.config.backend
        mode = b.executor if b.concurrent else "inline"
        if b.enabled:
            self._backend = OrderedWorker("back end", BackendCore, (calib, self.config), mode,
                                          timeout_s=b.worker_timeout_s)
        if self.config.loop.enabled:
            from plvo.loop.worker import LoopCore

            self._loop = OrderedWorker("loop closer", LoopCore, (calib, self.config), mode,
                                       niceness=LOOKAHEAD_NICENESS, timeout_s=b.worker_timeout_s)
        if b.concurrent and mode == "process":
            # Off the tracker's process: there ORB and LSD shared the GIL with the tracker (plvo.features.worker)
            from plvo.features.worker import FeaturesCore

            self._features = OrderedWorker("features", FeaturesCore, self._frontend.feature_settings, mode,
                                           niceness=LOOKAHEAD_NICENESS, timeout_s=b.worker_timeout_s)

    @property
    def _lags(self) -> tuple[int, int, int]:
        """Frames from submission to application: back end, loop result, global BA (all 0 inline)."""
        if not self.config.backend.concurrent:
            return 0, 0, 0
        return (max(0, self.config.backend.max_lag_frames), max(0, self.config.loop.max_lag_frames),
                max(0, self.config.loop.global_ba_lag_frames))

    def _emit(self, frame_index: int, results: Iterable[Any]) -> None:
        with self._clock.stage("recording"):
            for result in results:
                self.recorder.on_stage(frame_index, result)

    def step(self, frame: Frame) -> StepOutput:
        """Process one frame: track it, hand keyframes to the workers, stream every result, time it all."""
        if self._frontend is None:
            self._build(frame.calib)
        self._frame_now = frame.index
        self._clock = _Clock()
        for worker in self._workers:  # a worker process that died fails the run here, not frames later
            worker.check_alive(f"frame {frame.index}")
        keyframe = None
        with self._clock.stage("total"):  # wall time of the step, recorders included ("recording" is their share)
            with self._clock.stage("apply"):  # waiting for and applying the results due at this frame
                self._apply_due(frame.index)
            with self._clock.stage("recording"):
                self.recorder.on_frame(frame)
            with self._clock.stage("tracking"):
                res = self._frontend.track(frame)
            for name, seconds in res.timings.items():
                if name != "total":
                    self._clock.add(name, seconds)
            self.n_lost += int(not res.ok)
            self._emit(frame.index, [r for r in (res.features, res) if r is not None])
            # The frame's pose relative to its reference keyframe, taken before inline workers move that keyframe
            # (a keyframe frame is its own reference).
            T = np.asarray(res.T_world_cam, float)
            if res.keyframe is not None:
                self._ref_kf = res.keyframe.kf_id
                T_ref = np.asarray(res.keyframe.T_world_cam, float)
            else:
                T_ref = self.map.keyframe_pose(self._ref_kf)
            self._frame_ref[frame.index] = (self._ref_kf, se3.inv(T_ref) @ T)
            if res.keyframe is not None:
                keyframe = self._on_keyframe(frame, res)
        seconds = dict(self._clock.seconds)
        for name, value in seconds.items():
            self.timings[name].append(value)
        timing = TimingResult(frame.index, seconds)
        self.recorder.on_stage(frame.index, timing)
        self.frames_done += 1
        return StepOutput(frame.index, res, keyframe, timing)

    def _on_keyframe(self, frame: Frame, res) -> KeyframeResult:
        kf = res.keyframe
        keyframe = KeyframeResult(frame.index, kf.kf_id, np.asarray(kf.T_world_cam), res.keyframe_reason)
        self._emit(frame.index, [keyframe, *self._depth_debug])
        self._depth_debug = []
        lag_b, lag_l, _ = self._lags
        if self._backend is not None:
            with self._clock.stage("apply"):
                if self._apply_all("backend"):  # the window read next includes every earlier result
                    self._relocalise()
            with self._clock.stage("backend_submit"):
                self._submit("backend", self._backend_job(kf), frame.index + lag_b)
            if lag_b == 0:
                self._apply_all("backend")
        if self._loop is not None:
            with self._clock.stage("loop_submit"):
                self._submit("loop", self._loop_job(kf), frame.index + lag_l)
            if lag_l == 0:
                self._apply_all("loop")
        every = self.config.tracking.drop_unreachable_every
        if every and kf.kf_id % every == 0:
            with self._clock.stage("map_drop"):
                loop = self.config.loop
                budget = loop.global_ba_max_points if loop.enabled and loop.global_ba else None
                self.map.drop_unreachable(frame.index, self._oldest_reachable_keyframe(kf.kf_id),
                                          global_ba_points=budget)
        return keyframe

    def _oldest_reachable_keyframe(self, kf_id: int) -> int:
        """The oldest keyframe whose landmarks anything may still read: the window of the back-end job in flight
        (one at a time: the next keyframe's job waits for it) and of the next, the tracker's recent keyframes."""
        reach = max(2, self.config.backend.window_keyframes, self.config.tracking.search_keyframes)
        return kf_id - reach

    def _backend_job(self, kf):
        from plvo.backend.worker import BackendJob

        n = max(2, self.config.backend.window_keyframes)
        ids = np.arange(max(0, kf.kf_id - n + 1), kf.kf_id + 1)
        use_lines = self._frontend.uses_lines
        scan = kf.registration_scan if self.config.backend.registration else None
        return BackendJob(kf.kf_id, kf.frame_index, scan, self.map.window_data(ids, use_lines))

    def _loop_job(self, kf):
        from plvo.loop.worker import LoopJob, loop_keyframe

        lk = loop_keyframe(kf, np.asarray(self._calib.K, float))
        return LoopJob(kf.kf_id, kf.frame_index, lk, self.map.poses(), self._loop_applied())

    def _loop_applied(self) -> int:
        return sum(self.map.applied.get(s, 0) for s in (LOOP, GLOBAL_BA))

    # ---- results of the workers, applied at fixed frames ------------------------------------------------
    def _submit(self, which: str, job, due_frame: int) -> None:
        worker = self._backend if which == "backend" else self._loop
        worker.submit(job)
        self._due[which].append(due_frame)

    def _apply_due(self, frame_index: int) -> None:
        """Wait for and apply every worker result due at or before frame_index, back end first."""
        for which in ("backend", "loop"):
            due = self._due[which]
            while due and due[0] <= frame_index:
                self._apply_next(which)

    def _apply_all(self, which: str) -> int:
        """Wait for and apply every pending result of `which` -> how many."""
        n = 0
        while self._due[which]:
            self._apply_next(which)
            n += 1
        return n

    def _relocalise(self) -> None:
        """The keyframe just made was tracked before the back-end results just applied: solve it again on the map
        they refined (Frontend.relocalise_keyframe), so that it starts its window where inline it would."""
        correction = self._frontend.relocalise_keyframe()
        if correction is None:
            return
        self.map.apply(correction)
        self.loop_stats["relocalised"] += 1
        moved = float(np.linalg.norm(correction.T_after[0][:3, 3] - correction.T_before[0][:3, 3]))
        log.debug("keyframe %d solved again on the refined map: moved %.3f m", correction.keyframe_ids[0], moved)
        self._emit(self._frame_now, [MetricsResult(self._frame_now, {"relocalised_m": moved})])

    def _apply_next(self, which: str) -> None:
        self._due[which].popleft()
        if which == "backend":
            t0 = time.perf_counter()
            out = self._backend.take()
            self._clock.add("backend_wait", time.perf_counter() - t0)
            self._apply_backend(out)
        else:
            t0 = time.perf_counter()
            out = self._loop.take()
            self._clock.add("loop_wait", time.perf_counter() - t0)
            self._apply_loop(out)

    def _apply_backend(self, out) -> None:
        if out.correction is not None:
            self.map.apply(out.correction)
        if out.step.ba is None and "bundle_adjustment" in out.step.seconds:
            self.loop_stats["backend_discarded"] += 1
        for name, value in out.step.seconds.items():
            self.timings[name].append(value)
        self._emit(out.frame_index, [self._graph(out.frame_index, out.step.scale),
                                     MapResult(out.frame_index, out.points, out.lines),
                                     MetricsResult(out.frame_index, out.metrics)])

    def _apply_loop(self, out) -> None:
        from plvo.loop.worker import GlobalBAJob

        t0 = time.perf_counter()
        c = out.correction
        if c is not None:
            before = self.map.poses()
            self.map.apply(c)
            self.corrections.append(self._correction_event(c, before, out))
        if out.rejected:
            key = "global_ba_superseded" if out.rejected.startswith("superseded") else "global_ba_rejected"
            self.loop_stats[key] = self.loop_stats.get(key, 0) + 1
        results = list(out.results)
        if c is not None and c.source == LOOP:
            self.loop_stats["corrections"] += 1
            e = c.edges[0]
            log.info("loop %d -> %d closed: %d keyframes corrected", e.j, e.i, self.map.n_keyframes)
            if self.config.loop.global_ba:
                _, _, lag_g = self._lags
                self._pose_graph_move_m = max(self._pose_graph_move_m, out.correction_m)
                job = GlobalBAJob(out.frame_index, self.map.global_data(), self._pose_graph_move_m,
                                  self._loop_applied())
                self._submit("loop", job, self._frame_now + lag_g)
        if c is not None:
            if c.source == GLOBAL_BA:
                self.loop_stats["global_ba"] += 1
                self._pose_graph_move_m = 0.0
            results.append(self._graph(out.frame_index))
        timings = dict(out.timings)
        if c is not None:
            timings["loop_apply"] = time.perf_counter() - t0
        for name, value in timings.items():
            self.timings[name].append(value)
        self._emit(out.frame_index, results)
        if c is not None:  # a correction of the whole map: its temporaries were the size of the map (plvo.heap)
            release_free_memory()
        if c is not None and c.source == LOOP and self._lags[2] == 0:
            self._apply_all("loop")

    def _correction_event(self, c, before: np.ndarray, out) -> dict[str, Any]:
        """What an applied loop-closer correction did: source, frames, keyframes, how far it moved them."""
        after = self.map.poses()
        moved = np.linalg.norm(after[:, :3, 3] - before[:, :3, 3], axis=1)
        event = {"source": c.source, "keyframe_frame": int(out.frame_index), "applied_at_frame": int(self._frame_now),
                 "keyframes": int(len(after)), "max_move_m": float(moved.max(initial=0.0)),
                 "newest_move_m": float(moved[-1]) if len(moved) else 0.0,
                 "seconds": float(sum(out.timings.values()) if c.source == GLOBAL_BA else
                                  out.timings.get("loop_correct", 0.0))}
        if c.source == LOOP:
            e = c.edges[0]
            event.update(query_keyframe=int(e.j), match_keyframe=int(e.i))
        return event

    def _graph(self, frame_index: int, scale: float = 1.0) -> GraphResult:
        """The keyframe graph as the map has it now: poses, odometry (registration) and loop edges, zeta."""
        poses, new = self.map.poses(), self.map.edges[len(self._edge_rows[0]):]
        # The map only appends edges: their arrays grow by what is new instead of being rebuilt each keyframe.
        pairs, kinds, zeta = self._edge_rows
        if new:
            pairs = np.r_[pairs, np.array([(e.i, e.j) for e in new], int).reshape(-1, 2)]
            kinds = np.r_[kinds, np.array([e.kind for e in new], int)]
            zeta = np.r_[zeta, np.array([np.nan if e.kind == EDGE_LOOP else e.zeta for e in new], float)]
            self._edge_rows = (pairs, kinds, zeta)
        return GraphResult(frame_index, np.arange(len(poses)), poses, pairs, kinds, zeta, scale)

    def finish(self) -> None:
        """Wait for the workers to process every keyframe, apply and stream what they produced."""
        for which in ("backend", "loop"):
            self._apply_all(which)
        self._apply_all("backend")
        if self.loop_stats["corrections"]:
            log.info("loop closer corrected the map %d time(s)", self.loop_stats["corrections"])

    def run(self, frames: Iterable[Frame], info: RunInfo | None = None) -> None:
        """Start (when `info` is given), step through `frames`, finish; the caller closes."""
        if info is not None:
            self.start(info)
        for frame in frames:
            self.step(frame)
        self.finish()

    def close(self) -> None:
        for worker in self._workers:
            worker.close()
        self.recorder.close()

    @property
    def poses(self) -> dict[int, np.ndarray]:
        """Frame index -> (4,4) T_world_cam of the tracked camera, with every back-end refinement applied."""
        if self.map is None:
            return {}
        return {f: self.map.keyframe_pose(k) @ T_kf_cam for f, (k, T_kf_cam) in self._frame_ref.items()}

    def poses_cam0(self, frame_indices: Iterable[int]) -> np.ndarray:
        """(N,4,4) T_world_cam0 of the given frames (what KITTI pose files hold)."""
        T_cam_cam0 = se3.inv(np.asarray(self._calib.T_cam0_cam, dtype=float))
        poses = self.poses
        return np.stack([poses[f] @ T_cam_cam0 for f in frame_indices])

    def timing_summary(self) -> dict[str, dict[str, float]]:
        """Per stage: runs, mean, median, 90th percentile and max milliseconds, total seconds."""
        out = {}
        for name, values in self.timings.items():
            v = np.asarray(values)
            out[name] = {
                "runs": int(v.size),
                "mean_ms": float(v.mean() * 1e3),
                "median_ms": float(np.median(v) * 1e3),
                "p90_ms": float(np.percentile(v, 90) * 1e3),
                "max_ms": float(v.max() * 1e3),
                "total_s": float(v.sum()),
            }
        return out


def run_dataset(dataset, config: SystemConfig, recorder: Recorder | None = None, progress=None) -> RunOutput:
    """Run the whole pipeline over a Dataset -> RunOutput with cam0 poses of every frame (KITTI convention).

    progress: an optional callable taking the number of frames done (e.g. a tqdm bar's update).
    """
    return run_system(System(config, recorder, calib=dataset.calib), dataset, progress)


def run_system(system: System, dataset, progress=None) -> RunOutput:
    """Step `system` (made for this dataset, not yet stepped) through every frame, each read while the one before
    is tracked, let its workers finish, and close it -> RunOutput."""
    try:
        for frame in system.read_ahead(dataset):
            system.step(frame)
            if progress is not None:
                progress(1)
        system.finish()
        finished_at = time.perf_counter()
        poses = system.poses_cam0(dataset.frame_indices)
    finally:
        system.close()
    return RunOutput(tuple(dataset.frame_indices), poses, dict(system.timings),
                     system.map.n_keyframes if system.map is not None else 0, system.n_lost, finished_at)
