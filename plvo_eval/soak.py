"""A whole-sequence soak of the deployed configuration (`plvo bench --soak`): does a KITTI-length run hold up?

The run is plvo-viz's: the config as given (the defaults: concurrent workers), frames read from disk one ahead, a
recording on (the recorder the caller hands in). Measured per window of `window` frames: frames a second, resident
memory of this process and of its worker processes, the recording's size on disk, and the error of the frames'
poses as the tracker reported them then (position, against the ground truth, no alignment). Per run: every loop
accepted and every candidate refused by the odometry check, with the true distance between their keyframes, the
loops' precision and recall against the ground truth's revisits, what
each applied correction moved and the error left after it, the global corrections and their times, the optimisations
discarded, the tracking losses, and the final trajectory's figures (ATE, devkit, short segments).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from plvo.config import SystemConfig
from plvo.geometry import se3
from plvo.recording import Recorder, RunInfo
from plvo.results import CorrectionEvent, KeyframeResult, LoopResult, TimingResult, TrackingResult
from plvo_eval import provenance

if TYPE_CHECKING:
    from plvo.data.dataset import Dataset
    from plvo.runtime.system import System
    from plvo.types import Frame

log = logging.getLogger(__name__)

SCHEMA = "plvo.soak/1"
REPEATED_PLACE = "repeated place"  # how the closer's drift check words a refusal (plvo.loop.closer)


def tree_rss_mb() -> tuple[float, float, float | None, list[float]]:
    """(this process's RSS, the RSS of it and all its children, their PSS, each child's RSS by pid) in MB.

    The RSS sum counts the pages the processes share (the libraries every worker maps, copy-on-write) once for
    each; the PSS sum (Linux) splits each shared page among its sharers, so it is what the tree takes of the
    machine's memory. None where /proc/PID/smaps_rollup cannot be read."""
    import psutil

    me = psutil.Process(os.getpid())
    procs = [me, *me.children(recursive=True)]
    own = me.memory_info().rss
    total, children = 0, []
    pss: int | None = 0
    for p in procs:
        try:
            rss = p.memory_info().rss
            total += rss
            if p is not me:
                children.append((p.pid, rss / 2**20))
            pss = None if pss is None else pss + p.memory_full_info().pss
        except (psutil.Error, AttributeError):
            pss = None if p is me else pss
    return own / 2**20, total / 2**20, None if pss is None else pss / 2**20, [round(r, 1) for _, r in sorted(children)]


@dataclass
class SoakTap:
    """A Recorder that passes every call on to `inner` and keeps what the soak reports."""

    inner: Recorder
    rrd: Path | None = None
    window: int = 100
    frames: list[int] = field(default_factory=list)
    step_end: list[float] = field(default_factory=list)  # perf_counter at each frame's end
    step_s: list[float] = field(default_factory=list)
    tracked: dict[int, np.ndarray] = field(default_factory=dict)  # frame -> T_world_cam as reported then
    lost: list[int] = field(default_factory=list)
    kf_frame: dict[int, int] = field(default_factory=dict)
    loops: list[LoopResult] = field(default_factory=list)
    samples: list[dict[str, Any]] = field(default_factory=list)
    map_bytes: Any = None  # a callable -> bytes the map holds now (run_soak sets it)

    def on_run_start(self, info: RunInfo) -> None:
        self.inner.on_run_start(info)

    def on_restart(self, info: RunInfo) -> None:
        # the frames of the run that counts; the memory samples go on (the process tree is what it is)
        for kept in (self.frames, self.step_end, self.step_s, self.lost, self.loops):
            kept.clear()
        self.tracked.clear()
        self.kf_frame.clear()
        self.inner.on_restart(info)

    def on_frame(self, frame: Frame) -> None:
        self.inner.on_frame(frame)

    def on_stage(self, frame_index: int, result: Any) -> None:
        self.inner.on_stage(frame_index, result)
        if isinstance(result, TrackingResult):
            self.tracked[frame_index] = np.asarray(result.T_world_cam, float)
            if not result.ok:
                self.lost.append(frame_index)
        elif isinstance(result, KeyframeResult):
            self.kf_frame[result.keyframe_id] = frame_index
        elif isinstance(result, LoopResult):
            self.loops.append(result)
        elif isinstance(result, TimingResult):
            self.frames.append(frame_index)
            self.step_end.append(time.perf_counter())
            self.step_s.append(float(result.seconds.get("total", 0.0)))
            if len(self.frames) % self.window == 0:
                self.sample()

    def sample(self) -> None:
        own, total, pss, children = tree_rss_mb()
        size = self.rrd.stat().st_size if self.rrd is not None and self.rrd.exists() else 0
        self.samples.append({"frames": len(self.frames), "rss_mb": round(own, 1), "rss_tree_mb": round(total, 1),
                             "pss_tree_mb": None if pss is None else round(pss, 1), "rrd_mb": round(size / 2**20, 2),
                             # the child processes by pid: multiprocessing's resource tracker, then the worker
                             # processes in the order they start (the back end, the loop closer)
                             "rss_workers_mb": children,
                             "map_mb": None if self.map_bytes is None else round(self.map_bytes() / 2**20, 2)})

    def close(self) -> None:
        self.inner.close()


def run_soak(dataset: Dataset, config: SystemConfig, recorder: Recorder, info: RunInfo, rrd: Path | None = None,
             window: int = 100, progress: Callable[[int], object] | None = None) -> dict:
    """Run the System over the dataset as plvo-viz does, through a SoakTap -> the soak report (schema SCHEMA)."""
    from plvo.runtime.system import System

    prov = provenance.start()
    tap = SoakTap(recorder, rrd, window)
    system = System(config, tap, calib=dataset.calib)  # as plvo-viz: the workers start while the recorder does
    system.start(info)
    tap.map_bytes = lambda: system.map.nbytes() if system.map is not None else 0
    t0 = time.perf_counter()
    try:
        for frame in system.read_ahead(dataset):
            system.step(frame)
            if progress is not None:
                progress(1)
        t_frames = time.perf_counter()
        system.finish()
        wall = time.perf_counter() - t0
        tap.sample()
        poses = system.poses_cam0(dataset.frame_indices)
        report = _report(dataset, system, tap, poses, t0, wall, time.perf_counter() - t_frames, window)
    finally:
        system.close()
    rrd_size = rrd.stat().st_size if rrd is not None and rrd.exists() else None
    report["recording"] = {"bytes": rrd_size, "bytes_per_frame": None if rrd_size is None else
                           round(rrd_size / max(len(dataset), 1))}
    report["provenance"] = provenance.finish(prov)
    return report


def _report(dataset: Dataset, system: System, tap: SoakTap, poses: np.ndarray, t0: float, wall: float, finish_s: float,
            window: int) -> dict:
    assert system.map is not None  # run_soak read the poses from it (System.poses_cam0) before this
    gt = dataset.gt_T_world_cam  # of the camera the run used, by position in the selection
    index = {f: n for n, f in enumerate(dataset.frame_indices)}
    windows = _windows(tap, t0, gt, index, window)
    fps = np.array([w["fps"] for w in windows]) if windows else np.zeros(0)
    step = np.asarray(tap.step_s)
    n = min(500, len(step) // 2)
    out: dict[str, Any] = {
        "schema": SCHEMA, "frames": len(dataset), "wall_s": round(wall, 2), "finish_s": round(finish_s, 2),
        "fps": round(len(dataset) / max(wall, 1e-9), 3), "window_frames": window, "windows": windows,
        "fps_window_median": round(float(np.median(fps)), 3) if len(fps) else None,
        "fps_window_worst": round(float(fps.min()), 3) if len(fps) else None,
        "worst_over_median": round(float(fps.min() / np.median(fps)), 3) if len(fps) else None,
        "step_ms_first_500": round(1e3 * float(step[:n].mean()), 2) if n else None,
        "step_ms_last_500": round(1e3 * float(step[-n:].mean()), 2) if n else None,
        "rss_mb_at": _rss_at(tap.samples, tuple(f for f in (1000, 2000, 3000, 4000) if f < len(dataset))
                             + (len(dataset),)),
        "tracking_losses": tap.lost, "n_keyframes": system.map.n_keyframes,
        "corrections": [_with_errors(c, tap, gt, index) for c in system.corrections],
        "loop_stats": dataclasses.asdict(system.loop_stats),
        "loops": _loops(tap, gt, index) if gt is not None else None,
        "loop_detection": _detection(tap, gt, index, system.config) if gt is not None else None,
        "timings": system.timing_summary(),
    }
    if gt is not None:
        from plvo_eval.kitti_metric import evaluate_sequence, evaluation_json

        T_cam0 = np.asarray(dataset.calib.T_cam0_cam, float)
        gt0 = gt @ se3.inv(T_cam0)
        out["final"] = evaluation_json(evaluate_sequence(gt0, poses))
        err = np.linalg.norm(poses[:, :3, 3] - gt0[:, :3, 3], axis=1)
        out["final"]["last_frame_error_m"] = float(err[-1])
        out["final"]["max_error_m"] = float(err.max())
    return out


def _windows(tap: SoakTap, t0: float, gt: np.ndarray | None, index: dict[int, int], window: int) -> list[dict]:
    out = []
    ends = [t0] + tap.step_end
    samples = {s["frames"]: s for s in tap.samples}
    for a in range(0, len(tap.frames) - window + 1, window):
        b = a + window
        w: dict[str, Any] = {"first_frame": tap.frames[a], "last_frame": tap.frames[b - 1],
             "fps": round(window / max(ends[b] - ends[a], 1e-9), 3)}
        w.update({k: v for k, v in samples.get(b, {}).items() if k != "frames"})
        if gt is not None:
            errs = [np.linalg.norm(tap.tracked[f][:3, 3] - gt[index[f]][:3, 3]) for f in tap.frames[a:b]
                    if f in tap.tracked]
            w["error_m_median"] = round(float(np.median(errs)), 3) if errs else None
            w["error_m_max"] = round(float(np.max(errs)), 3) if errs else None
        out.append(w)
    return out


def _with_errors(correction: CorrectionEvent, tap: SoakTap, gt: np.ndarray | None, index: dict[int, int]) -> dict:
    """A correction event (as the soak's JSON holds it) with the tracked error of the frame before it was applied
    and of the frame after."""
    event = correction.as_dict()
    if gt is None:
        return event
    for key, f in (("error_before_m", event["applied_at_frame"] - 1), ("error_after_m", event["applied_at_frame"])):
        if f in tap.tracked and f in index:
            event[key] = round(float(np.linalg.norm(tap.tracked[f][:3, 3] - gt[index[f]][:3, 3])), 3)
    return event


def _rss_at(samples: list[dict], frames: tuple[int, ...]) -> dict[str, dict]:
    out = {}
    for f in frames:
        near = [s for s in samples if s["frames"] <= f]
        if near:
            out[str(f)] = {"rss_mb": near[-1]["rss_mb"], "rss_tree_mb": near[-1]["rss_tree_mb"],
                           "pss_tree_mb": near[-1].get("pss_tree_mb"), "map_mb": near[-1].get("map_mb"),
                           "rss_workers_mb": near[-1].get("rss_workers_mb"), "at_frames": near[-1]["frames"]}
    return out


def _loops(tap: SoakTap, gt: np.ndarray, index: dict[int, int]) -> list[dict]:
    """Every loop accepted and every candidate refused by the odometry check (before or after the geometric
    checks: "repeated place"), with the true distance between their keyframes."""
    out = []
    for r in tap.loops:
        refused = (not r.accepted) and REPEATED_PLACE in (r.reason or "")
        if not (r.accepted or refused):
            continue
        fq, fm = tap.kf_frame.get(r.query_keyframe), tap.kf_frame.get(r.match_keyframe)
        d = None
        if fq in index and fm in index:
            d = float(np.linalg.norm(gt[index[fq]][:3, 3] - gt[index[fm]][:3, 3]))
        out.append({"query_keyframe": r.query_keyframe, "match_keyframe": r.match_keyframe, "query_frame": fq,
                    "match_frame": fm, "accepted": bool(r.accepted), "true_distance_m": d,
                    "n_inliers": r.n_inliers, "reason": r.reason})
    return out


def _detection(tap: SoakTap, gt: np.ndarray, index: dict[int, int], config: SystemConfig) -> dict:
    """Precision and recall of the accepted loops against the ground truth's revisits (plvo_eval.revisits)."""
    from plvo_eval.revisits import detection_stats

    kf_frame = {k: index[f] for k, f in tap.kf_frame.items() if f in index}
    loops = [r for r in tap.loops if r.accepted]
    # a loop joining no same-direction revisit (a street driven back) is true when its edge is (plvo_eval.revisits)
    stats: dict[str, Any] = dict(detection_stats(
        gt, kf_frame, [(r.query_keyframe, r.match_keyframe) for r in loops], config.loop.min_keyframe_gap,
        config.loop.loop_cooldown, edges=[r.T_match_query for r in loops]))
    refused = [r for r in tap.loops if not r.accepted and REPEATED_PLACE in (r.reason or "")]
    stats["n_refused_by_odometry"] = len(refused)
    stats["n_refused_after_geometry"] = sum(1 for r in refused if r.n_inliers > 0)
    stats["precision"] = round(stats["n_true"] / stats["n_accepted"], 3) if stats["n_accepted"] else None
    stats["recall_passages"] = (round(stats["n_passages_found"] / stats["n_passages"], 3) if stats["n_passages"]
                                else None)
    return stats
