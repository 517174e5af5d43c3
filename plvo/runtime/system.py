"""The System: wires the stages together, one `step(frame)` a frame, and hands every result to the recorders.

Tracking runs in the caller's thread: features -> matching -> PnP/PnL -> keyframe decision; on a keyframe the
depth priors and new landmarks (all inside `plvo.tracking.frontend.Frontend`). Each keyframe then goes, as a job
read from the map at that moment, to the back end (`plvo.runtime.worker_stages.BackendStage`) and to the loop closer
(`LoopStage`), each run by a `plvo.runtime.workers.OrderedWorker` inline, in a thread or in a worker process.

The map has one owner and one writer: this thread. Workers return typed corrections, which are applied
(`LandmarkMap.apply`) at fixed frames of the run that `plvo.runtime.scheduler` sets, waiting there for a worker that is
late, so the trajectory does not depend on the machine's load or the workers' speed. When a back-end result is
applied before the next keyframe's window is read, that keyframe was tracked on the map before the result, and is
solved again on the refined one (`Frontend.relocalise_keyframe`). docs/architecture.md draws the whole.

Poses: the back end moves keyframes after the tracker has passed them. Every frame's pose is kept relative to the
keyframe it was tracked from, and `poses` composes it with that keyframe's current pose, so the reported
trajectory carries every refinement (as ORB-SLAM2 reports its trajectory).

The System imports no viewer: recorders (Rerun, viser) are handed in from `plvo_app`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import defaultdict
from collections.abc import Callable, Generator, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial.transform import Rotation

from plvo.config import (
    BackendSections,
    LoopSections,
    SystemConfig,
    TrackerSections,
    config_to_dict,
    config_to_toml,
)
from plvo.depth.extract import extract_depth
from plvo.features.extract import extract_features
from plvo.features.matching import match_lines, match_points
from plvo.features.worker import FeaturesCore
from plvo.priority import LOOKAHEAD_NICENESS
from plvo.recording import NullRecorder, Recorder, RunInfo
from plvo.results import CorrectionEvent, KeyframeResult, TimingResult, TrackingResult
from plvo.runtime.frame_poses import FramePoses
from plvo.runtime.lookahead import Lookahead
from plvo.runtime.prefetch import prefetched
from plvo.runtime.scheduler import Lags, Scheduler, drop_unreachable
from plvo.runtime.timing import StageClock, timing_summary
from plvo.runtime.worker_stages import BackendStage, GraphView, LoopStage, LoopStats, RunRecord
from plvo.runtime.workers import START_TIMEOUT_S, OrderedWorker, libraries_single_threaded
from plvo.tracking.extrinsic import corrected
from plvo.tracking.frontend import Frontend, FrontendResult, Stages
from plvo.tracking.keyframes import KeyframeInfo
from plvo.tracking.map import LandmarkMap
from plvo.types import Calibration, Frame

if TYPE_CHECKING:
    from plvo.config import DepthConfig
    from plvo.data.dataset import Dataset
    from plvo.types import DepthPriors, FeatureSet

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StepOutput:
    """What one step produced: the tracking result and the keyframe made (or None)."""

    frame_index: int
    tracking: TrackingResult
    keyframe: KeyframeResult | None
    timing: TimingResult


def _nothing() -> None:
    pass


class System:
    """Runs the pipeline frame by frame and streams each stage's result to `recorder`."""

    def __init__(self, config: SystemConfig, recorder: Recorder | None = None, calib: Calibration | None = None):
        """calib: the sequence's calibration, when known before the first frame: the stages and the worker
        processes are then made at once, so that the workers start up (~1-2 s of imports on two cores) while the
        caller sets up its recorders and viewer, instead of while the first frames are tracked."""
        self.recorder = recorder if recorder is not None else NullRecorder()
        self.restarts: list[dict[str, Any]] = []  # each restart from the first frame: why, at which frame (restart())
        self._info: RunInfo | None = None  # what the recorders were told at start()
        self._fresh(config)
        if calib is not None:
            self._build(calib)

    def _fresh(self, config: SystemConfig) -> None:
        """The state of a run not yet stepped (no stages built)."""
        self.config = config
        self.record = RunRecord(defaultdict(list))
        self.timings = self.record.timings  # stage -> seconds, one entry a time it ran
        self.frames_done = 0
        self.n_lost = 0
        self._frame_poses = FramePoses()
        self._frontend: Frontend | None = None
        self._backend: BackendStage | None = None
        self._loop: LoopStage | None = None
        self._features: OrderedWorker | None = None  # the features process (deployed mode: plvo.features.worker)
        self._lookahead: Lookahead | None = None
        self._workers: list[OrderedWorker] = []
        self._clock = StageClock()
        self._scheduler = Scheduler(self._clock_add)
        self._calib: Calibration | None = None
        self._depth_debug: list[Any] = []
        self._frame_now = 0
        # the last keyframe's back-end and loop jobs, read from the map at its frame and submitted at the next
        # frame, once the motion to that frame completes its scan's deskewing (plvo.lidar.deskew.Sweep)
        self._pending: tuple[KeyframeInfo, Any, Any] | None = None
        self._threads_back: Callable[[], None] = _nothing  # the libraries' threads as they were (close())

    @property
    def map(self) -> LandmarkMap | None:
        return None if self._frontend is None else self._frontend.map

    @property
    def loop_stats(self) -> LoopStats:
        return self.record.stats

    @property
    def corrections(self) -> list[CorrectionEvent]:
        """One entry an applied loop or global BA correction: what it moved, when (for the soak and the log)."""
        return self.record.corrections

    @property
    def workers(self) -> tuple[OrderedWorker, ...]:
        """The workers made: back end, loop closer, features process (those enabled, in that order)."""
        return tuple(self._workers)

    @property
    def worker_pids(self) -> list[int]:
        """The worker processes' ids (back end, loop closer, features, those made; none inline or in threads)."""
        return [w.pid for w in self._workers if w.pid is not None]

    def start(self, info: RunInfo) -> None:
        """Start the recorders, then wait for the workers to be ready (see `wait_ready`)."""
        self._info = info
        self.recorder.on_run_start(info)
        self.wait_ready()

    # ---- a run started again (plvo.runtime.run.step_through) -------------------------------------------------------
    @property
    def restart_wanted(self) -> SystemConfig | None:
        """The config to run again with from the first frame, when the frames so far found that the run's own is
        wrong in a way a restart mends: a camera-lidar time offset found while none (or another) was stated
        (crosscheck.restart_on_offset), a gross extrinsic error (crosscheck.restart_on_extrinsic; composed with the
        correction this run was told); at most one restart a run. None: go on."""
        frontend = self._frontend
        cc = self.config.crosscheck
        if frontend is None or self.restarts:
            return None
        offset = frontend.offset_found if cc.restart_on_offset else None
        extrinsic = frontend.extrinsic_found if cc.restart_on_extrinsic else None
        if offset is None and extrinsic is None:
            return None
        mended = cc
        if offset is not None:
            mended = dataclasses.replace(mended, time_offset_s=float(offset.offset_s))
        if extrinsic is not None:  # found against the corrected extrinsic this run used: composed with its correction
            both = Rotation.from_rotvec(extrinsic.correction_deg, degrees=True) * \
                Rotation.from_rotvec(cc.extrinsic_correction_deg, degrees=True)
            mended = dataclasses.replace(mended, extrinsic_correction_deg=tuple(
                round(float(v), 4) for v in both.as_rotvec(degrees=True)))
        return dataclasses.replace(self.config, crosscheck=mended)

    def restart(self, config: SystemConfig) -> None:
        """Start the run again from its first frame with `config`: the workers closed and made anew, the map, the
        trajectory and the timings of the frames so far dropped; the recorders told (Recorder.on_restart) with the
        run's info carrying the new config and why. The caller then steps every frame again from the first."""
        frontend, calib = self._frontend, self._calib
        assert frontend is not None and calib is not None, "restart() of a System never stepped"
        frontend.checks.flush()  # the episodes open at this frame (the offset's own) are warned now
        found = frontend.offset_found if config.crosscheck.time_offset_s != self.config.crosscheck.time_offset_s \
            else None
        turned = config.crosscheck.extrinsic_correction_deg != self.config.crosscheck.extrinsic_correction_deg
        reasons = [r for r, yes in (("camera-lidar time offset", found is not None),
                                    ("camera-lidar extrinsic", turned)) if yes]
        why = {"at_frame": self._frame_now, "frames_before": self.frames_done, "reason": " and ".join(reasons),
               "time_offset_s": round(config.crosscheck.time_offset_s, 4),
               "sigma_s": None if found is None else round(float(found.sigma_s), 4),
               "extrinsic_correction_deg": list(config.crosscheck.extrinsic_correction_deg)}
        for worker in self._workers:
            worker.close()
        self._threads_back()
        self.restarts.append(why)
        self._fresh(config)
        self._build(calib)
        if self._info is not None:
            self._info = dataclasses.replace(self._info, config=config_to_dict(config), extra={
                **self._info.extra, "config_toml": config_to_toml(config), "restart": why})
            self.recorder.on_restart(self._info)
        # after the recorders' restart: the warning is in the recording of the run that counts
        if found is not None:
            log.warning("frame %d: starting again from the first frame with the scans moved %.3f s to the images' "
                        "instants (crosscheck.time_offset_s: the offset found there)", why["at_frame"],
                        why["time_offset_s"])
        if turned:
            log.warning("frame %d: starting again from the first frame with the extrinsic turned by [%s] deg "
                        "(crosscheck.extrinsic_correction_deg: the correction found there)", why["at_frame"],
                        ", ".join(f"{v:+.3f}" for v in config.crosscheck.extrinsic_correction_deg))
        self.wait_ready()

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

    # ---- frames read ahead (plvo.runtime.lookahead) ---------------------------------------------------------------
    def prepare(self, frame: Frame) -> Frame:
        """The frame with the tracker's features extracted (`Frame.features`), as the reading thread prepares it;
        before the stages are built (no calib given to the System) the frame as it is."""
        return frame if self._lookahead is None else self._lookahead.prepare(frame)

    def read_ahead(self, dataset: Dataset) -> Generator[Frame, None, None]:
        """The dataset's frames as the System is meant to take them: read and prepared ahead
        (plvo.runtime.lookahead)."""
        if self._lookahead is None:  # the stages are built at the first step: prepared from then on
            return prefetched(dataset, prepare=self.prepare, niceness=LOOKAHEAD_NICENESS,
                              timeout_s=self._read_timeout_s)
        return self._lookahead.frames(dataset)

    # ---- wiring --------------------------------------------------------------------------------------------
    def _build(self, calib: Calibration) -> None:
        def depth(scan: np.ndarray, features: FeatureSet, calib_: Calibration, cfg: DepthConfig) -> DepthPriors:
            # the tracker wants the priors; the viewers also want what the extraction saw (DepthDebug)
            t0 = time.perf_counter()
            out = extract_depth(scan, features, calib_, cfg)
            self._clock.add("depth", time.perf_counter() - t0)
            self._depth_debug = [out.priors, out.debug]
            return out.priors

        self._calib = calib  # as given: a restart turns it anew from the restart's config
        turn = self.config.crosscheck.extrinsic_correction_deg
        if any(turn):
            calib = dataclasses.replace(calib, T_cam_velo=corrected(calib.T_cam_velo, turn))
        frontend = self._frontend = Frontend(calib, self.config.sections(TrackerSections),
                                             stages=Stages(extract_features, match_points, match_lines, depth))
        b, lags = self.config.backend, Lags.of(self.config)
        mode = b.executor if b.concurrent else "inline"
        graph = GraphView(frontend.map)
        if b.enabled:
            from plvo.backend.worker import BackendCore  # open3d and gtsam: loaded when a back end is made

            worker = OrderedWorker("back end", BackendCore, (calib, self.config.sections(BackendSections)), mode,
                                   timeout_s=b.worker_timeout_s)
            self._backend = BackendStage(worker, self._scheduler, lags, frontend, self.config, graph, self.record,
                                         self._emit)
            self._workers.append(worker)
        if self.config.loop.enabled:
            from plvo.loop.worker import LoopCore

            worker = OrderedWorker("loop closer", LoopCore, (calib, self.config.sections(LoopSections)), mode,
                                   niceness=LOOKAHEAD_NICENESS, timeout_s=b.worker_timeout_s)
            self._loop = LoopStage(worker, self._scheduler, lags, frontend.map, calib.K, self.config, graph,
                                   self.record, self._emit, lambda: self._frame_now)
            self._workers.append(worker)
        if b.concurrent and mode == "process":
            # Off the tracker's process: there ORB and LSD shared the GIL with the tracker (plvo.features.worker)
            self._features = OrderedWorker("features", FeaturesCore, frontend.feature_settings, mode,
                                           niceness=LOOKAHEAD_NICENESS, timeout_s=b.worker_timeout_s)
            self._workers.append(self._features)
        if b.concurrent and mode == "process":
            # this process shares the cores with its workers as they share them with each other: single-threaded
            # libraries here too (the lidar check's open3d, the tracker's OpenCV), until close() gives them back
            self._threads_back = libraries_single_threaded()
        self._lookahead = Lookahead(frontend, self._features, self._read_timeout_s)

    @property
    def _read_timeout_s(self) -> float:
        """A frame's wait includes its features' (bounded by the workers' timeout, and the first one by the features
        process's start): the read gets a minute more."""
        return max(self.config.backend.worker_timeout_s, START_TIMEOUT_S) + 60.0

    def _clock_add(self, stage: str, seconds: float) -> None:
        self._clock.add(stage, seconds)

    def _emit(self, frame_index: int, results: Iterable[Any]) -> None:
        with self._clock.stage("recording"):
            for result in results:
                self.recorder.on_stage(frame_index, result)

    # ---- one frame -----------------------------------------------------------------------------------------
    def step(self, frame: Frame) -> StepOutput:
        """Process one frame: track it, hand keyframes to the workers, stream every result, time it all."""
        if self._frontend is None:
            self._build(frame.calib)
        frontend = self._frontend
        assert frontend is not None
        self._frame_now = frame.index
        self._clock = StageClock()
        for worker in self._workers:  # a worker process that died fails the run here, not frames later
            worker.check_alive(f"frame {frame.index}")
        keyframe = None
        with self._clock.stage("total"):  # wall time of the step, recorders included ("recording" is their share)
            with self._clock.stage("apply"):  # waiting for and applying the results due at this frame
                self._scheduler.apply_due(frame.index)
            with self._clock.stage("recording"):
                self.recorder.on_frame(frame)
            with self._clock.stage("tracking"):
                res = frontend.track(frame)
            for name, seconds in res.timings.items():
                if name != "total":
                    self._clock.add(name, seconds)
            self.n_lost += int(not res.ok)
            self._emit(frame.index, [r for r in (res.features, res) if r is not None])
            self._frame_poses.add(frame.index, res, frontend.map)
            if self._pending is not None:
                self._submit_pending(frame, res.T_world_cam)
            if res.keyframe is not None:
                keyframe = self._on_keyframe(frame, res)
        stages = dict(self._clock.seconds)
        self.record.add_timings(stages)
        timing = TimingResult(frame.index, stages)
        self.recorder.on_stage(frame.index, timing)
        self.frames_done += 1
        return StepOutput(frame.index, res, keyframe, timing)

    def _on_keyframe(self, frame: Frame, res: FrontendResult) -> KeyframeResult:
        kf = res.keyframe
        assert kf is not None and self._frontend is not None
        keyframe = KeyframeResult(frame.index, kf.kf_id, np.asarray(kf.T_world_cam), res.keyframe_reason)
        self._emit(frame.index, [keyframe, *self._depth_debug])
        self._depth_debug = []
        backend_job = loop_job = None
        if self._backend is not None:
            with self._clock.stage("apply"):
                self._backend.catch_up(self._frame_now)
            with self._clock.stage("backend_submit"):
                backend_job = self._backend.job(kf)
        if self._loop is not None:
            with self._clock.stage("loop_submit"):
                loop_job = self._loop.job(kf)
        if backend_job is not None or loop_job is not None:
            self._pending = (kf, backend_job, loop_job)
            if kf.sweep is None and self._results_lag():
                # nothing to deskew, so nothing to wait a frame for: the workers start a frame earlier, and their
                # results are applied at the same frames as ever (inline, lag 0, they would be applied at once, before
                # the next frame is tracked instead of after: there the job still waits)
                self._submit_pending(None, None)
        every = self.config.tracking.drop_unreachable_every
        if every and kf.kf_id % every == 0:
            with self._clock.stage("map_drop"):
                drop_unreachable(self._frontend.map, kf.kf_id, frame.index, self.config)
        return keyframe

    def _results_lag(self) -> bool:
        """Whether every worker's results are applied at a later frame than their job's submission (not inline)."""
        return all(stage.channel.lag > 0 for stage in (self._backend, self._loop) if stage is not None)

    def _submit_pending(self, frame: Frame | None, T_world_cam: np.ndarray | None) -> None:
        """Submit the last keyframe's back-end and loop jobs, their scan deskewed with the motion to `frame`
        (tracked at T_world_cam; None at the end of the run, or at the keyframe itself when its scan is not
        deskewed), due as if submitted at the keyframe's own frame."""
        assert self._pending is not None and self._frontend is not None
        kf, backend_job, loop_job = self._pending
        self._pending = None
        sweep = kf.sweep
        if frame is not None and T_world_cam is not None and sweep is not None:
            sweep = self._frontend.sweep_after(kf, frame, T_world_cam)
        scan = None
        if sweep is not None:
            # once, here, for both workers: the back end and the loop closer register the same deskewed scan, which
            # costs 15-25 ms for a 120k-point scan
            with self._clock.stage("deskew"):
                scan = sweep.apply(kf.registration_scan)
        for stage, job, name in ((self._backend, backend_job, "backend_submit"), (self._loop, loop_job, "loop_submit")):
            if stage is None or job is None:
                continue
            with self._clock.stage(name):
                self._scheduler.submit(stage.channel, job if scan is None else job.with_scan(scan), kf.frame_index)
            self._scheduler.settle(stage.channel)

    def finish(self) -> None:
        """Wait for the workers to process every keyframe, apply and stream what they produced."""
        if self._frontend is not None:
            self._frontend.checks.flush()  # the cross-check's episodes still open are warned now
        if self._pending is not None:
            self._submit_pending(None, None)
        self._scheduler.finish()
        if self.record.stats.corrections:
            log.info("loop closer corrected the map %d time(s)", self.record.stats.corrections)

    def close(self) -> None:
        for worker in self._workers:
            worker.close()
        self.recorder.close()
        self._threads_back()
        self._threads_back = _nothing

    # ---- the trajectory (plvo.runtime.frame_poses) ---------------------------------------------------------------
    @property
    def poses(self) -> dict[int, np.ndarray]:
        """Frame index -> (4,4) T_world_cam of the tracked camera, with every back-end refinement applied."""
        return {} if self.map is None else self._frame_poses.world(self.map)

    def poses_cam0(self, frame_indices: Iterable[int]) -> np.ndarray:
        """(N,4,4) T_world_cam0 of the given frames (what KITTI pose files hold)."""
        assert self.map is not None and self._calib is not None
        return self._frame_poses.cam0(self.map, self._calib, frame_indices)

    def trust_summary(self) -> dict:
        """How far to trust the trajectory: frames by where their pose came from (the camera; the camera matched
        again from the lidar's motion; the lidar alone; the motion model after a loss), the cross-check's findings
        and their episodes (plvo.tracking.lidar_check.CheckLog)."""
        if self._frontend is None:
            return {}
        out = self._frontend.checks.summary()
        if self.restarts:
            out["restarts"] = list(self.restarts)
        offset = self._frontend.offset
        est = None if offset is None else offset.estimate()
        out["time_offset"] = {"stated_s": self.config.crosscheck.time_offset_s,
                              "estimate": None if est is None else est.as_dict(),
                              "found": None if self._frontend.offset_found is None
                              else self._frontend.offset_found.as_dict()}
        ext = self._frontend.extrinsic
        ext_est = None if ext is None else ext.estimate()
        out["extrinsic"] = {"correction_stated_deg": list(self.config.crosscheck.extrinsic_correction_deg),
                            "estimate": None if ext_est is None else ext_est.as_dict(),
                            "found": None if self._frontend.extrinsic_found is None
                            else self._frontend.extrinsic_found.as_dict()}
        return out

    def timing_summary(self) -> dict[str, dict[str, float]]:
        """Per stage: runs, mean, median, 90th percentile and max milliseconds, total seconds."""
        return timing_summary(self.timings)
