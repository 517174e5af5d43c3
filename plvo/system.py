"""The System: wires the stages together, one `step(frame)` a frame, and hands every result to the recorders.

Tracking runs in the caller's thread: features -> matching -> PnP/PnL -> keyframe decision; on a keyframe the
depth priors and new landmarks (all inside `plvo.tracking.frontend.Frontend`). Each keyframe then goes to the back
end (registration, scale correction, bundle adjustment; `plvo.backend.worker.Backend`, in its own thread when
`backend.concurrent`) and to the loop closer. Results of the workers are handed to the recorders from the
tracking thread, at the next step, so recorders are only ever called from one thread.

Poses: the back end moves keyframes after the tracker has passed them. Every frame's pose is kept relative to the
keyframe it was tracked from, and `poses` composes it with that keyframe's current pose, so the reported
trajectory carries every refinement (as ORB-SLAM2 reports its trajectory).

The System imports no viewer: recorders (Rerun, viser) are handed in from `plvo_app`.
"""

from __future__ import annotations

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
from plvo.recording import NullRecorder, Recorder, RunInfo
from plvo.results import KeyframeResult, TimingResult, TrackingResult
from plvo.types import Calibration, Frame

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

    def __init__(self, config: SystemConfig, recorder: Recorder | None = None):
        self.config = config
        self.recorder = recorder if recorder is not None else NullRecorder()
        self.timings: dict[str, list[float]] = defaultdict(list)  # stage -> seconds, one entry a time it ran
        self.frames_done = 0
        self.n_lost = 0
        self._frame_ref: dict[int, tuple[int, np.ndarray]] = {}  # frame -> (keyframe id, T_kf_cam)
        self._frontend = None
        self._backend = None
        self._loop = None
        self._calib: Calibration | None = None
        self._clock = _Clock()
        self._depth_debug: list[Any] = []
        self._ref_kf = -1

    @property
    def map(self):
        return None if self._frontend is None else self._frontend.map

    def start(self, info: RunInfo) -> None:
        self.recorder.on_run_start(info)

    def _build(self, calib: Calibration) -> None:
        from plvo.backend.worker import Backend
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
        self._backend = Backend(calib, self.config, self._frontend.map) if self.config.backend.enabled else None
        self._loop = None
        if self.config.loop.enabled:
            from plvo.loop.worker import LoopWorker

            self._loop = LoopWorker(calib, self.config, self._frontend.map)
            if self._backend is not None:
                self._backend.loop_edges = self._loop.loop_edges  # drawn in the keyframe graph
                self._loop.registration_edges = self._backend.registration_edges  # for the global BA

    def _emit(self, frame_index: int, results: Iterable[Any]) -> None:
        with self._clock.stage("recording"):
            for result in results:
                self.recorder.on_stage(frame_index, result)

    def step(self, frame: Frame) -> StepOutput:
        """Process one frame: track it, hand keyframes to the workers, stream every result, time it all."""
        if self._frontend is None:
            self._build(frame.calib)
        self._clock = _Clock()
        keyframe = None
        with self._clock.stage("total"):  # wall time of the step, recorders included ("recording" is their share)
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
            self._collect()
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
        if self._backend is not None:
            with self._clock.stage("backend_submit"):
                self._backend.submit(kf)
        if self._loop is not None:
            with self._clock.stage("loop_submit"):
                self._loop.submit(kf)
        return keyframe

    def _collect(self) -> None:
        """Hand the workers' finished results to the recorders (always from this thread)."""
        for worker in (self._backend, self._loop):
            if worker is None:
                continue
            for frame_index, result in worker.poll():
                self._emit(frame_index, [result])
            for name, values in worker.drain_timings().items():
                self.timings[name].extend(values)

    def finish(self) -> None:
        """Wait for the workers to process every keyframe and stream what they produced."""
        for worker in (self._backend, self._loop):
            if worker is not None:
                worker.flush()
        self._collect()
        if self._loop is not None and self._loop.n_corrections:
            log.info("loop closer corrected the map %d time(s)", self._loop.n_corrections)

    def run(self, frames: Iterable[Frame], info: RunInfo | None = None) -> None:
        """Start (when `info` is given), step through `frames`, finish; the caller closes."""
        if info is not None:
            self.start(info)
        for frame in frames:
            self.step(frame)
        self.finish()

    def close(self) -> None:
        for worker in (self._backend, self._loop):
            if worker is not None:
                worker.close()
        self.recorder.close()

    @property
    def poses(self) -> dict[int, np.ndarray]:
        """Frame index -> (4,4) T_world_cam of the tracked camera, with every back-end refinement applied."""
        if self.map is None:
            return {}
        with self.map.lock:
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
    system = System(config, recorder)
    try:
        for i in range(len(dataset)):
            system.step(dataset[i])
            if progress is not None:
                progress(1)
        system.finish()
        poses = system.poses_cam0(dataset.frame_indices)
    finally:
        system.close()
    return RunOutput(tuple(dataset.frame_indices), poses, dict(system.timings),
                     system.map.n_keyframes if system.map is not None else 0, system.n_lost)
