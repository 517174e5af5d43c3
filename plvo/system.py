"""The System: wires the stages together, one `step(frame)` a frame, and hands every result to the recorders.

A step runs, in order: features -> (matching) -> tracking -> on a keyframe: depth priors, the tracker's new
landmarks, the back end, the loop closer. Every stage is timed; every result goes to `recorder.on_stage`, and a
`TimingResult` closes each frame. Stages that are not built yet are None in `Stages` and simply skipped: until a
tracker exists there is no pose estimate, a keyframe is made every `tracking.keyframe_every` frames, and
`System.poses` stays empty (ground truth is never passed off as an estimate).

The System imports no viewer: recorders (Rerun, viser) are handed in from `plvo_app`.
"""

from __future__ import annotations

import importlib
import logging
import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from plvo.config import SystemConfig
from plvo.recording import NullRecorder, Recorder, RunInfo
from plvo.results import KeyframeResult, TimingResult, TrackingResult
from plvo.types import DepthPriors, FeatureSet, Frame

log = logging.getLogger(__name__)


class Tracker(Protocol):
    """The front end after feature extraction (built in plvo.tracking)."""

    def track(self, frame: Frame, features: FeatureSet) -> list[Any]:
        """Match, solve the pose, decide on a keyframe. Returns results; exactly one is a TrackingResult."""

    def add_keyframe(self, frame: Frame, features: FeatureSet, depth: DepthPriors | None) -> list[Any]:
        """Make new landmarks from a keyframe's depth priors. Returns results (e.g. a MapResult)."""


class KeyframeConsumer(Protocol):
    """The back end and the loop closer: called once a keyframe, may return results (GraphResult, LoopResult...)."""

    def on_keyframe(self, keyframe: KeyframeResult, frame: Frame, features: FeatureSet | None) -> list[Any]:
        ...


@dataclass
class Stages:
    """The stage functions and objects a System runs; None means not built yet and skipped.

    extract_features(image (H,W) uint8, OrbConfig, LineConfig) -> FeatureSet.
    extract_depth(scan (N,4) lidar frame, FeatureSet, Calibration, DepthConfig) -> DepthPriors, or an object with
    `.priors` (DepthPriors) and `.debug` (a debug result handed to the recorders only).
    """

    extract_features: Callable[..., FeatureSet] | None = None
    extract_depth: Callable[..., Any] | None = None
    tracker: Tracker | None = None
    backend: KeyframeConsumer | None = None
    loop_closer: KeyframeConsumer | None = None

    def names(self) -> list[str]:
        return [name for name, value in vars(self).items() if value is not None]


def _find(candidates: Iterable[tuple[str, str]]) -> Callable[..., Any] | None:
    """The first `module.attr` that exists; a module that is missing (not yet written) is skipped."""
    for module_name, attr in candidates:
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name is not None and module_name.startswith(exc.name):
                continue
            raise
        if hasattr(module, attr):
            return getattr(module, attr)
    return None


def default_stages() -> Stages:
    """The stages that exist in this checkout of plvo."""
    return Stages(
        extract_features=_find([("plvo.features", "extract_features"), ("plvo.features.extract", "extract_features")]),
        # extract_depth also returns the DepthDebug the viewers draw (projected scan, patches, planes)
        extract_depth=_find([("plvo.depth.extract", "extract_depth"), ("plvo.depth.extract", "extract_depth_priors")]),
    )


@dataclass(frozen=True)
class StepOutput:
    """What one step produced: the tracking result (None without a tracker), the keyframe made (or None)."""

    frame_index: int
    features: FeatureSet | None
    tracking: TrackingResult | None
    keyframe: KeyframeResult | None
    timing: TimingResult


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


class System:
    """Runs the pipeline frame by frame and streams each stage's result to `recorder`."""

    def __init__(self, config: SystemConfig, recorder: Recorder | None = None, stages: Stages | None = None):
        self.config = config
        self.recorder = recorder if recorder is not None else NullRecorder()
        self.stages = stages if stages is not None else default_stages()
        self.poses: dict[int, np.ndarray] = {}  # frame index -> estimated (4,4) T_world_cam
        self.timings: dict[str, list[float]] = defaultdict(list)  # stage -> seconds, one entry a time it ran
        self.frames_done = 0
        self._n_keyframes = 0
        self._clock = _Clock()
        log.info("stages: %s", ", ".join(self.stages.names()) or "none")

    @property
    def has_odometry(self) -> bool:
        return self.stages.tracker is not None

    def start(self, info: RunInfo) -> None:
        self.recorder.on_run_start(info)

    def _emit(self, frame_index: int, results: Iterable[Any]) -> None:
        with self._clock.stage("recording"):
            for result in results:
                self.recorder.on_stage(frame_index, result)

    def step(self, frame: Frame) -> StepOutput:
        """Process one frame: run every built stage, hand the results to the recorders, time it all."""
        self._clock = _Clock()
        with self._clock.stage("total"):  # wall time of the step, recorders included ("recording" is their share)
            with self._clock.stage("recording"):
                self.recorder.on_frame(frame)
            features = self._features(frame)
            tracking = self._track(frame, features)
            keyframe = self._keyframe(frame, features, tracking)
        seconds = dict(self._clock.seconds)
        for name, value in seconds.items():
            self.timings[name].append(value)
        timing = TimingResult(frame.index, seconds)
        self.recorder.on_stage(frame.index, timing)
        self.frames_done += 1
        return StepOutput(frame.index, features, tracking, keyframe, timing)

    def _features(self, frame: Frame) -> FeatureSet | None:
        fn = self.stages.extract_features
        if fn is None:
            return None
        with self._clock.stage("features"):
            features = fn(frame.image, self.config.orb, self.config.lines)
        self._emit(frame.index, [features])
        return features

    def _track(self, frame: Frame, features: FeatureSet | None) -> TrackingResult | None:
        tracker = self.stages.tracker
        if tracker is None or features is None:
            return None
        with self._clock.stage("tracking"):
            results = list(tracker.track(frame, features))
        self._emit(frame.index, results)
        tracking = next(r for r in results if isinstance(r, TrackingResult))
        self.poses[frame.index] = np.asarray(tracking.T_world_cam, dtype=float)
        return tracking

    def _is_keyframe(self, tracking: TrackingResult | None) -> tuple[bool, str]:
        if tracking is not None:
            return tracking.is_keyframe, tracking.message
        every = max(1, self.config.tracking.keyframe_every)
        return self.frames_done % every == 0, f"every {every} frames (no tracker yet)"

    def _keyframe(self, frame: Frame, features: FeatureSet | None, tracking: TrackingResult | None):
        is_kf, reason = self._is_keyframe(tracking)
        if not is_kf:
            return None
        pose = None if tracking is None else tracking.T_world_cam
        keyframe = KeyframeResult(frame.index, self._n_keyframes, pose, reason)
        self._n_keyframes += 1
        self._emit(frame.index, [keyframe])
        depth = self._depth(frame, features)
        if self.stages.tracker is not None and features is not None:
            with self._clock.stage("landmarks"):
                results = list(self.stages.tracker.add_keyframe(frame, features, depth))
            self._emit(frame.index, results)
        for name in ("backend", "loop_closer"):
            consumer = getattr(self.stages, name)
            if consumer is not None:
                with self._clock.stage(name):
                    results = list(consumer.on_keyframe(keyframe, frame, features))
                self._emit(frame.index, results)
        return keyframe

    def _depth(self, frame: Frame, features: FeatureSet | None) -> DepthPriors | None:
        fn = self.stages.extract_depth
        if fn is None or features is None:
            return None
        with self._clock.stage("depth"):
            out = fn(frame.scan, features, frame.calib, self.config.depth)
        priors = getattr(out, "priors", out)
        self._emit(frame.index, [priors] + ([out.debug] if hasattr(out, "debug") else []))
        return priors

    def run(self, frames: Iterable[Frame], info: RunInfo | None = None) -> None:
        """Start (when `info` is given), step through `frames`; the caller closes."""
        if info is not None:
            self.start(info)
        for frame in frames:
            self.step(frame)

    def close(self) -> None:
        self.recorder.close()

    def timing_summary(self) -> dict[str, dict[str, float]]:
        """Per stage: runs, mean, median and max milliseconds, total seconds."""
        out = {}
        for name, values in self.timings.items():
            v = np.asarray(values)
            out[name] = {
                "runs": int(v.size),
                "mean_ms": float(v.mean() * 1e3),
                "median_ms": float(np.median(v) * 1e3),
                "max_ms": float(v.max() * 1e3),
                "total_s": float(v.sum()),
            }
        return out
