"""Speed and memory of plvo (`plvo bench`): per-stage timings, whole-system frames a second, peak memory.

Every stage entry says where its numbers come from ("source"):
- "isolated": the stage called on its own over the frames held in memory: features and its sub-stages (ORB,
  LSD, repair, LBD, timed one after another, whereas `features` runs the line pipeline in a thread beside ORB),
  features on the frames resized to the budget's 1241x376, matching of consecutive frames (no motion prediction),
  depth priors of every `keyframe_every`-th frame, registration between those frames seeded by ground truth;
- "system": what the System itself records in a full run over the frames held in memory (preloaded), with the
  config given (the defaults: concurrent workers), recording off and on (PnP/PnL, matching + PnP/PnL a frame,
  scale correction, bundle adjustment, the loop closer).
"deployed" is the figure a user gets from plvo-viz: frames read from disk as plvo-viz reads them, recording on,
the config given, and KISS-ICP's frames a second over the same scans (read alone) in the same bench run beside it,
both clocked alike from the first frame read to the last result, their set-up (imports, workers, pipeline) apart;
from `plvo bench` each of these runs is made in a fresh process, before anything is loaded for the other figures.
The machine may be shared: the result carries its provenance (plvo_eval.provenance: revision, machine, load at start and
end, command), the load average of every run, the CPU time used and the thread settings so a reader can judge the
figures. Budgets are the design's ("Performance budget"); `within_budget` compares the median.
"""

from __future__ import annotations

import logging
import os
import resource
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from plvo.config import SystemConfig, config_to_dict
from plvo.errors import ConfigError
from plvo.recording import NullRecorder, Recorder, RunInfo
from plvo.results import TimingResult
from plvo.types import Calibration, FeatureSet, Frame
from plvo_eval import provenance

if TYPE_CHECKING:
    from plvo.data.dataset import Dataset

log = logging.getLogger(__name__)

SCHEMA = "plvo.bench/1"
STAGE_GROUPS = ("features", "matching", "depth", "registration", "backend", "loop", "system")
SYSTEM_GROUPS = frozenset({"backend", "loop", "system"})  # these need whole-system runs
BUDGET_MS = {"features": 50.0, "features_1241x376": 50.0, "matching_pnpl": 15.0, "depth": 30.0,
             "registration": 150.0, "scale_correction_ba": 150.0}
FPS_BUDGET = 10.0
RECORDING_OVERHEAD_BUDGET_PCT = 25.0
BUDGET_IMAGE_SIZE = (1241, 376)  # width, height of the design's budget table (the shared frames are 1226x370)


def parse_stages(text: str) -> frozenset[str]:
    """'all' or a comma list of STAGE_GROUPS -> the set; unknown names raise ConfigError naming them."""
    names = {s.strip() for s in str(text).split(",") if s.strip()}
    if "all" in names:
        return frozenset(STAGE_GROUPS)
    bad = sorted(names - set(STAGE_GROUPS))
    if bad or not names:
        raise ConfigError(f"--stages: unknown stage(s) {', '.join(bad) or repr(text)} "
                          f"(choose all or a comma list of {','.join(STAGE_GROUPS)})")
    return frozenset(names)


def stage_stats(seconds: Sequence[float], budget_ms: float | None = None, source: str = "isolated") -> dict:
    """n, median/p90/mean/max milliseconds of per-call `seconds`, the budget and whether the median is within."""
    v = np.asarray(list(seconds), dtype=float) * 1e3
    out: dict[str, Any] = {"source": source, "n": int(v.size)}
    for key, fn in (("median_ms", np.median), ("p90_ms", lambda x: np.percentile(x, 90)),
                    ("mean_ms", np.mean), ("max_ms", np.max)):
        out[key] = round(float(fn(v)), 3) if v.size else None
    out["budget_ms"] = budget_ms
    out["within_budget"] = None if budget_ms is None or not v.size else bool(out["median_ms"] <= budget_ms)
    return out


# ---- input held in memory -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class FrameList:
    """A Dataset held in memory, so that the system runs are timed without disk reads and image decoding."""

    frames: tuple[Frame, ...]
    sequence: str
    calib: Calibration
    gt_T_world_cam: np.ndarray | None
    name: str = "memory"

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> Frame:
        return self.frames[i]

    @property
    def frame_indices(self) -> tuple[int, ...]:
        return tuple(f.index for f in self.frames)

    @property
    def times(self) -> np.ndarray:
        return np.array([f.time for f in self.frames])

    @property
    def nbytes(self) -> int:
        return sum(f.image.nbytes + f.scan.nbytes for f in self.frames)


def load_frames(dataset: Dataset) -> tuple[FrameList, list[float]]:
    """Read every frame of a Dataset into memory -> (FrameList, seconds to load each frame)."""
    frames, seconds = [], []
    for i in range(len(dataset)):
        t0 = time.perf_counter()
        frames.append(dataset[i])
        seconds.append(time.perf_counter() - t0)
    return FrameList(tuple(frames), dataset.sequence, dataset.calib, dataset.gt_T_world_cam,
                     getattr(dataset, "name", "dataset")), seconds


# ---- memory ---------------------------------------------------------------------------------------------------
class RssSampler:
    """Samples this process's resident set size (psutil) every `interval_s` in a daemon thread; a context manager."""

    def __init__(self, interval_s: float = 0.05):
        import psutil

        self._proc = psutil.Process()
        self._interval = interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, name="plvo-bench-rss", daemon=True)
        self.samples: list[int] = []

    def _sample(self) -> None:
        while True:
            self.samples.append(self._proc.memory_info().rss)
            if self._stop.wait(self._interval):
                return

    def __enter__(self) -> RssSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.samples.append(self._proc.memory_info().rss)

    def summary(self) -> dict:
        mb = np.asarray(self.samples, dtype=float) / 2**20
        return {"peak_mb": round(float(mb.max()), 1), "mean_mb": round(float(mb.mean()), 1), "samples": int(mb.size)}


def max_rss_mb() -> float:
    """Peak resident set size of this process so far (getrusage; kilobytes on Linux)."""
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)


# ---- isolated stages ------------------------------------------------------------------------------------------
def _timed(fn: Callable, *args: Any) -> tuple[float, Any]:
    t0 = time.perf_counter()
    out = fn(*args)
    return time.perf_counter() - t0, out


def bench_features(images: Sequence[np.ndarray], cfg: SystemConfig, repeat: int = 1
                   ) -> tuple[dict[str, list[float]], list[FeatureSet]]:
    """Seconds of features and its sub-stages on (H,W) uint8 images (and resized to 1241x376) -> timings, sets."""
    import cv2

    from plvo.features.extract import extract_features
    from plvo.features.lbd import compute_lbd
    from plvo.features.lines import detect_lsd, repair_segments
    from plvo.features.points import detect_orb

    po = cfg.tracking.points_only
    extract_features(images[0], cfg.orb, cfg.lines, po)  # warm-up: thread pool, OpenCV's first-call costs
    out: dict[str, list[float]] = defaultdict(list)
    sets = []
    for img in images:
        big = cv2.resize(img, BUDGET_IMAGE_SIZE, interpolation=cv2.INTER_LINEAR)
        for _ in range(repeat):
            t, fs = _timed(extract_features, img, cfg.orb, cfg.lines, po)
            out["features"].append(t)
            out["features_1241x376"].append(_timed(extract_features, big, cfg.orb, cfg.lines, po)[0])
            out["features_orb"].append(_timed(detect_orb, img, cfg.orb)[0])
            if not po:
                t, raw = _timed(detect_lsd, img, cfg.lines)
                out["features_lsd"].append(t)
                t, lines = _timed(repair_segments, raw, cfg.lines)
                out["features_repair"].append(t)
                out["features_lbd"].append(_timed(compute_lbd, img, lines.segments)[0])
        sets.append(fs)
    return dict(out), sets


def bench_matching(sets: Sequence[FeatureSet], cfg: SystemConfig, repeat: int = 1) -> list[float]:
    """Seconds of match_features between consecutive FeatureSets (no motion prediction)."""
    from plvo.features.matching import match_features

    return [_timed(match_features, prev, cur, cfg.matching)[0]
            for prev, cur in zip(sets[:-1], sets[1:]) for _ in range(repeat)]


def keyframe_positions(n: int, every: int) -> list[int]:
    """Positions 0, every, 2 every... < n: the stand-in keyframes of the isolated depth and registration stages."""
    return list(range(0, n, max(1, int(every))))


def bench_depth(frames: Sequence[Frame], sets: Sequence[FeatureSet], cfg: SystemConfig, repeat: int = 1
                ) -> list[float]:
    """Seconds of extract_depth on the stand-in keyframes (scan + that frame's features)."""
    from plvo.depth.extract import extract_depth

    return [_timed(extract_depth, frames[p].scan, sets[p], frames[p].calib, cfg.depth)[0]
            for p in keyframe_positions(len(frames), cfg.tracking.keyframe_every) for _ in range(repeat)]


def _registration_init(a: Frame, b: Frame, T_cam_velo: np.ndarray) -> tuple[np.ndarray, str]:
    """T_va_vb (lidar of a <- lidar of b) from ground truth when both frames have it, else identity."""
    from plvo.geometry import se3

    if a.gt_T_world_cam is None or b.gt_T_world_cam is None:
        return np.eye(4), "identity"
    T_ca_cb = se3.inv(a.gt_T_world_cam) @ b.gt_T_world_cam
    return se3.inv(T_cam_velo) @ T_ca_cb @ T_cam_velo, "ground truth"


def bench_registration(frames: Sequence[Frame], cfg: SystemConfig, repeat: int = 1
                       ) -> tuple[list[float], dict]:
    """Seconds of align between consecutive stand-in keyframes (newer onto older, as the back end does)."""
    from plvo.lidar.registration import align
    from plvo.lidar.scan import registration_scan as scan

    seconds, converged, inits = [], 0, set()
    pos = keyframe_positions(len(frames), cfg.tracking.keyframe_every)
    for a, b in zip(pos[:-1], pos[1:]):
        T_cv = np.asarray(frames[a].calib.T_cam_velo, dtype=float)
        init, how = _registration_init(frames[a], frames[b], T_cv)
        inits.add(how)
        for _ in range(repeat):
            t, res = _timed(lambda a=a, b=b, init=init, T_cv=T_cv: align(scan(frames[b]), scan(frames[a]), init,
                                                                          cfg.registration, T_cv))
            seconds.append(t)
            converged += int(res.converged)
    return seconds, {"init": ",".join(sorted(inits)), "converged": converged, "runs": len(seconds)}


# ---- whole system ---------------------------------------------------------------------------------------------
class TimingTap:
    """A Recorder that hands every call to `inner` and keeps each frame's stage seconds (the TimingResults)."""

    def __init__(self, inner: Recorder):
        self.inner = inner
        self.per_frame: list[dict[str, float]] = []

    def on_run_start(self, info: RunInfo) -> None:
        self.inner.on_run_start(info)

    def on_restart(self, info: RunInfo) -> None:
        self.per_frame.clear()  # the frames of the run that counts, as the System's own timings
        self.inner.on_restart(info)

    def on_frame(self, frame: Frame) -> None:
        self.inner.on_frame(frame)

    def on_stage(self, frame_index: int, result: Any) -> None:
        if isinstance(result, TimingResult):
            self.per_frame.append(dict(result.seconds))
        self.inner.on_stage(frame_index, result)

    def close(self) -> None:
        self.inner.close()


@dataclass
class SystemRun:
    """One whole-system run: wall and CPU seconds, per-frame and per-stage timings, memory, load."""

    recording: bool
    frames: int
    wall_s: float
    cpu_s: float
    n_keyframes: int
    n_lost: int
    load_start: tuple[float, ...]
    load_end: tuple[float, ...]
    rss: dict
    per_frame: list[dict[str, float]]
    timings: dict[str, list[float]]
    rrd_bytes: int | None = None
    workers_cpu_s: float | None = None  # the worker processes' CPU during the run (their start-up excluded)
    setup_s: float | None = None  # before the clock: imports, opening the input, the System, its workers' start-up

    @property
    def fps(self) -> float:
        return self.frames / max(self.wall_s, 1e-9)

    def summary(self) -> dict:
        step = [f.get("total", 0.0) for f in self.per_frame]
        rec = [f.get("recording", 0.0) for f in self.per_frame]
        out = {"recording": self.recording, "frames": self.frames, "wall_s": round(self.wall_s, 3),
               "fps": round(self.fps, 3), "setup_s": None if self.setup_s is None else round(self.setup_s, 3),
               "cpu_s": round(self.cpu_s, 3),
               "cpu_ms_per_frame": round(1e3 * self.cpu_s / max(self.frames, 1), 2),
               "cpu_share": round(self.cpu_s / max(self.wall_s, 1e-9), 3),  # cores kept busy; 2.0 = both
               "tracking_thread_fps": round(len(step) / max(sum(step), 1e-9), 3),
               # the wait for the worker processes' start-up before the first frame (their imports), outside wall_s
               "workers_ready_s": round(sum(self.timings.get("workers_ready", [0.0])), 3),
               "tracking_thread_fps_from_frame_10": (round((len(step) - 10) / max(sum(step[10:]), 1e-9), 3)
                                                     if len(step) > 10 else None),
               "first_step_ms": round(1e3 * step[0], 1) if step else None,
               "recording_ms_per_frame": stage_stats(rec, source="system")["median_ms"],
               # the recorders' share of the tracking thread's time: less sensitive to a shared machine's load
               "recording_pct_of_step": round(100 * sum(rec) / max(sum(step) - sum(rec), 1e-9), 2),
               "n_keyframes": self.n_keyframes, "n_lost": self.n_lost,
               "load_start": [round(x, 2) for x in self.load_start],
               "load_end": [round(x, 2) for x in self.load_end], "rss": self.rss}
        if self.workers_cpu_s is not None:  # the worker processes' share, and all processes together
            out["workers_cpu_ms_per_frame"] = round(1e3 * self.workers_cpu_s / max(self.frames, 1), 2)
            total = self.cpu_s + self.workers_cpu_s
            out["all_processes_cpu_ms_per_frame"] = round(1e3 * total / max(self.frames, 1), 2)
            out["all_processes_cpu_share"] = round(total / max(self.wall_s, 1e-9), 3)
        if self.rrd_bytes is not None:
            out["rrd_bytes"] = self.rrd_bytes
            out["rrd_bytes_per_frame"] = round(self.rrd_bytes / max(self.frames, 1))
        return out


def bench_system(frames: FrameList | Dataset, cfg: SystemConfig, recorder: Recorder | None = None,
                 info: RunInfo | None = None, rrd: Path | None = None, setup_started: float | None = None
                 ) -> SystemRun:
    """Run the System over `frames` as plvo-viz does, timing it; `rrd`: the recording file to measure.

    As in plvo-viz, the System (and so its worker processes) is made before the recorders start, and the clock runs
    from the first frame read to the workers' last result: what plvo-viz's timings.json reports. Everything before
    it, from `setup_started` (time.perf_counter(); default: this call) on, is the run's setup_s."""
    setup_started = time.perf_counter() if setup_started is None else setup_started
    from plvo.runtime.run import run_system
    from plvo.runtime.system import System

    tap = TimingTap(recorder if recorder is not None else NullRecorder())
    children0 = _cpu_s(resource.RUSAGE_CHILDREN)  # worker processes are counted here once they are reaped
    system = System(cfg, tap, calib=frames.calib)
    if info is not None:
        tap.on_run_start(info)  # the recording needs calib and config
    system.wait_ready()  # as plvo-viz's System.start: the workers' start-up is timed apart (workers_ready)
    startup = _processes_cpu_s(system.worker_pids)  # their imports, before the clock starts
    load0 = os.getloadavg()
    cpu0 = _cpu_s(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    with RssSampler() as rss:
        out = run_system(system, frames)  # closes the System: its worker processes are joined
    # to the workers' last result, as plvo-viz's frames a second: closing (the workers' exit) is not part of it
    wall = out.finished_at - t0
    cpu = _cpu_s(resource.RUSAGE_SELF) - cpu0
    workers = _cpu_s(resource.RUSAGE_CHILDREN) - children0 - startup if startup is not None else None
    size = rrd.stat().st_size if rrd is not None and rrd.exists() else None
    return SystemRun(recorder is not None, len(frames), wall, cpu, out.n_keyframes, out.n_lost, load0,
                     os.getloadavg(), rss.summary(), tap.per_frame, out.timings, size, workers, t0 - setup_started)


def _cpu_s(who: int) -> float:
    ru = resource.getrusage(who)
    return ru.ru_utime + ru.ru_stime


def _processes_cpu_s(pids: Sequence[int]) -> float | None:
    """CPU seconds the processes have used so far (None when one cannot be read)."""
    import psutil

    total = 0.0
    for pid in pids:
        try:
            t = psutil.Process(pid).cpu_times()
        except psutil.Error:
            return None
        total += t.user + t.system
    return total


def _pool(runs: Sequence[SystemRun]) -> dict[str, list[float]]:
    pooled: dict[str, list[float]] = defaultdict(list)
    for run in runs:
        for name, values in run.timings.items():
            pooled[name].extend(values)
    return pooled


def system_stages(runs: Sequence[SystemRun]) -> dict[str, dict]:
    """The stages only a whole run measures (pooled over `runs`): pnpl, matching_pnpl, the back end, the loop."""
    pooled = _pool(runs)
    for run in runs:
        pooled["matching_pnpl"].extend(f["matching"] + f.get("pnpl", 0.0) for f in run.per_frame if "matching" in f)
    names = ("pnpl", "matching_pnpl", "scale_correction", "bundle_adjustment", "scale_correction_ba", "backend",
             "loop_query", "loop_verify", "loop_correct", "loop_apply", "loop_global_ba", "loop")
    for n in CORRECTION_STAGES:  # timed every keyframe, but they only work after an accepted loop
        pooled[n] = [v for v in pooled.get(n, []) if v > 0]
    return {n: stage_stats(pooled.get(n, []), BUDGET_MS.get(n), "system") for n in names}


# Per-keyframe loop timings that are zero unless a loop was accepted: their figures are over the corrections only
# (none on a sequence without a revisit: `plvo bench --root R --seq S --stages loop` on one with a loop).
CORRECTION_STAGES = ("loop_correct", "loop_apply", "loop_global_ba")


def system_figures(off: Sequence[SystemRun], on: Sequence[SystemRun]) -> dict:
    """Frames a second with recording off and on (medians over runs), the recording overhead against budgets."""
    out: dict[str, Any] = {"backend_concurrent": None}
    fps_off = float(np.median([r.fps for r in off])) if off else None
    out["recording_off"] = {"fps": None if fps_off is None else round(fps_off, 3), "fps_budget": FPS_BUDGET,
                            "within_budget": None if fps_off is None else fps_off >= FPS_BUDGET,
                            "runs": [r.summary() for r in off]}
    if on:
        fps_on = float(np.median([r.fps for r in on]))
        sizes = [r.rrd_bytes / r.frames for r in on if r.rrd_bytes]
        out["recording_on"] = {"fps": round(fps_on, 3), "rrd_bytes_per_frame": round(float(np.median(sizes)))
                               if sizes else None, "runs": [r.summary() for r in on]}
        if fps_off:
            pct = 100.0 * (fps_off / fps_on - 1.0)  # how much longer a frame takes with recording on
            out["recording_overhead_pct"] = round(pct, 2)
            out["recording_overhead_budget_pct"] = RECORDING_OVERHEAD_BUDGET_PCT
            out["recording_overhead_within_budget"] = bool(pct <= RECORDING_OVERHEAD_BUDGET_PCT)
    out["stages_recording_off"] = {n: stage_stats(v, source="system") for n, v in sorted(_pool(off).items())}
    return out


def deployed_figures(dataset: Dataset, cfg: SystemConfig, recorder_factory: Callable[[int], tuple[Recorder, Path]],
                     info: RunInfo | None, repeat: int = 1, reopen: Callable[[], Any] | None = None) -> dict:
    """What a user gets from plvo-viz: the given config (the defaults: concurrent workers), a Rerun recording on,
    frames read from disk as plvo-viz reads them (one ahead, in a thread), the workers' last results waited for;
    and KISS-ICP over the same scans, read from disk likewise (the scans alone), right after each run.

    Both are timed alike: the clock runs from the first frame read to the last result; what comes before it (the
    imports, opening the dataset, plvo's System and its worker processes' start-up, KISS-ICP's pipeline) is each
    run's setup_s, reported apart. Per run both frames a second, both setups and their ratio; medians over `repeat`.

    reopen: a picklable callable that opens the dataset again (and a picklable recorder_factory): then each run,
    plvo's and KISS-ICP's, is made in a fresh process, as a user runs plvo-viz, instead of in this one, which holds
    the runs before it (its resident memory grew by ~25 MB a run) and whatever its caller loaded."""
    runs: list[SystemRun] = []
    kiss: list[KissRun | None] = []
    calls: list[tuple[float, float]] = []  # seconds of each call, plvo's and KISS-ICP's, as the bench saw them
    for r in range(repeat):
        log.info("bench: deployed run (plvo-viz's way, recording on), run %d of %d", r + 1, repeat)
        t0 = time.perf_counter()
        if reopen is None:
            recorder, path = recorder_factory(1000 + r)
            runs.append(bench_system(dataset, cfg, recorder, info, path))
            t1 = time.perf_counter()
            kiss.append(kiss_run(dataset))
        else:
            runs.append(in_fresh_process(_deployed_run, reopen, cfg, recorder_factory, info, 1000 + r))
            t1 = time.perf_counter()
            kiss.append(in_fresh_process(_kiss_run, reopen))
        calls.append((t1 - t0, time.perf_counter() - t1))
    summaries = [run.summary() for run in runs]
    kiss_ok = [k for k in kiss if k is not None]
    # Each run against the KISS-ICP run right after it: a shared machine's speed drifts between runs by more than
    # the two differ, so the ratio of neighbours is the steadier figure.
    pairs = [{"plvo_fps": round(run.fps, 3), "kiss_icp_fps": None if k is None else round(k.fps, 3),
              "plvo_setup_s": _rounded(run.setup_s), "kiss_icp_setup_s": None if k is None else round(k.setup_s, 3),
              "ratio": None if k is None else round(run.fps / k.fps, 3),
              # the whole call: with fresh processes also their start, unpickling, closing and exit
              "plvo_call_s": round(c[0], 3), "kiss_icp_call_s": round(c[1], 3)}
             for run, k, c in zip(runs, kiss, calls)]
    ratios = [p["ratio"] for p in pairs if p["ratio"] is not None]
    fps = float(np.median([run.fps for run in runs]))
    kfps = _median([k.fps for k in kiss_ok])
    where = "each run in a fresh process, as plvo-viz runs" if reopen is not None else "in the bench's process"
    return {"how": "the config as given, recording on, frames read from disk (prefetched) as plvo-viz does; KISS-ICP "
                   "1.3 (voxel 1 m) on the same scans read from disk (the scans alone), right after each plvo run; "
                   "for both, fps = frames / wall time from the first frame read to the last result (plvo: its "
                   "workers' last results), and setup_s = the time before it (imports, opening the dataset; plvo's "
                   "System and its worker processes' start-up, of which workers_ready_s is the wait; KISS-ICP's "
                   f"pipeline); ratio = plvo fps / KISS-ICP fps of the same run; medians over the runs; {where}",
            "fresh_processes": reopen is not None,
            "fps": round(fps, 3),
            "setup_s": _rounded(_median([run.setup_s for run in runs if run.setup_s is not None])),
            "workers_ready_s": _rounded(_median([s["workers_ready_s"] for s in summaries])),
            "kiss_icp_fps": None if kfps is None else round(kfps, 3),
            "kiss_icp_setup_s": _rounded(_median([k.setup_s for k in kiss_ok])),
            "at_least_kiss_icp": None if kfps is None else bool(fps >= kfps),
            "ratio_to_kiss_icp": _rounded(_median(ratios)),
            "ratio_to_kiss_icp_runs": ratios,
            "ratio_to_kiss_icp_interval": ratio_interval(ratios),
            "pairs": pairs, "runs": summaries, "kiss_icp_runs": [None if k is None else k.summary() for k in kiss]}


def ratio_interval(ratios: Sequence[float], level: float = 0.9, draws: int = 4000) -> dict | None:
    """The geometric mean of run-by-run ratios and its bootstrap interval at `level` (the runs resampled with a
    fixed seed, so a report's figures can be computed again from its runs) -> {"geomean", "low", "high", "level"};
    None for fewer than 3 runs. On a shared machine whose speed moves between runs by more than two revisions differ
    (KISS-ICP alone at 8.6-15.1 frames/s within one bench on the project's Intel Xeon VM), two benches' medians do
    not say whether they differ; their intervals do."""
    r = np.asarray([x for x in ratios if x is not None and x > 0], float)
    if len(r) < 3:
        return None
    logs = np.log(r)
    means = logs[np.random.default_rng(0).integers(0, len(logs), (draws, len(logs)))].mean(axis=1)
    low, high = np.quantile(means, [(1 - level) / 2, (1 + level) / 2])
    return {"geomean": round(float(np.exp(logs.mean())), 3), "low": round(float(np.exp(low)), 3),
            "high": round(float(np.exp(high)), 3), "level": level}


def _median(values: Sequence[float]) -> float | None:
    return float(np.median(values)) if len(values) else None


def _rounded(value: float | None, digits: int = 3) -> float | None:
    return None if value is None else round(value, digits)


def _deployed_run(reopen: Callable[[], Any], cfg: SystemConfig,
                  recorder_factory: Callable[[int], tuple[Recorder, Path]], info: RunInfo | None,
                  run: int) -> SystemRun:
    setup_started = time.perf_counter()
    from plvo.allocator import keep_freed_memory

    keep_freed_memory()  # this process stands for plvo-viz's, whose entry point does the same (plvo_app.cli)
    recorder, path = recorder_factory(run)
    return bench_system(reopen(), cfg, recorder, info, path, setup_started)


def _kiss_run(reopen: Callable[[], Any]) -> KissRun | None:
    setup_started = time.perf_counter()
    return kiss_run(reopen(), setup_started)


def in_fresh_process(fn: Callable, *args: Any) -> Any:
    """fn(*args) in a new spawned process (plvo_eval.runner's pool of one: its processes may make worker processes
    of their own and end with this one) -> its result; a failure there is raised here as a RuntimeError of one line."""
    from plvo_eval.runner import worker_pool

    with worker_pool(1) as pool:
        try:
            return pool.submit(fn, *args).result()
        except Exception as exc:  # noqa: BLE001 - the child's error (or BrokenProcessPool), as one line
            raise RuntimeError(f"bench: {getattr(fn, '__name__', fn)} in a fresh process failed: "
                               f"{type(exc).__name__}: {exc}") from exc


@dataclass(frozen=True)
class KissRun:
    """One KISS-ICP run: frames, wall seconds from the first scan read to the last registered, setup seconds
    before that (kiss_icp's import, its pipeline; in a fresh process also opening the dataset)."""

    frames: int
    wall_s: float
    setup_s: float

    @property
    def fps(self) -> float:
        return self.frames / max(self.wall_s, 1e-9)

    def summary(self) -> dict:
        return {"frames": self.frames, "wall_s": round(self.wall_s, 3), "fps": round(self.fps, 3),
                "setup_s": round(self.setup_s, 3)}


def kiss_run(dataset: Dataset, setup_started: float | None = None) -> KissRun | None:
    """KISS-ICP over the dataset's scans, read from disk alone inside the clock, its import and set-up outside (from
    `setup_started`, time.perf_counter(); default: this call) -> KissRun, or None when kiss-icp is not installed."""
    setup_started = time.perf_counter() if setup_started is None else setup_started
    try:
        from plvo_eval.kiss import run_kiss

        out = run_kiss(dataset)
    except ImportError:
        return None
    return KissRun(len(dataset), out.wall_s, out.started_at - setup_started)


def kiss_fps(dataset: Dataset) -> float | None:
    """KISS-ICP's frames a second over the dataset (as kiss_run: scans read inside the clock, set-up outside), or
    None when kiss-icp is not installed."""
    k = kiss_run(dataset)
    return None if k is None else round(k.fps, 3)


# ---- the whole bench ------------------------------------------------------------------------------------------
def _feature_sets(frames: FrameList, cfg: SystemConfig) -> list[FeatureSet]:
    from plvo.features.extract import extract_features

    return [extract_features(f.image, cfg.orb, cfg.lines, cfg.tracking.points_only) for f in frames.frames]


def isolated_stages(frames: FrameList, cfg: SystemConfig, stages: frozenset[str], repeat: int = 1
                    ) -> tuple[dict[str, dict], dict]:
    """The isolated stage entries selected by `stages` -> (name -> stage_stats, facts about the input)."""
    out: dict[str, dict] = {}
    facts: dict[str, Any] = {}
    sets: list[FeatureSet] = []
    if stages & {"features", "matching", "depth"}:
        if "features" in stages:
            log.info("bench: features on %d frames (x%d)", len(frames), repeat)
            timings, sets = bench_features([f.image for f in frames.frames], cfg, repeat)
            out.update({n: stage_stats(v, BUDGET_MS.get(n)) for n, v in timings.items()})
        else:
            sets = _feature_sets(frames, cfg)
        facts["keypoints_median"] = int(np.median([s.n_points for s in sets]))
        facts["lines_median"] = int(np.median([s.n_lines for s in sets]))
    if "matching" in stages and len(sets) > 1:
        log.info("bench: matching %d frame pairs", len(sets) - 1)
        out["matching"] = stage_stats(bench_matching(sets, cfg, repeat))
    if "depth" in stages:
        log.info("bench: depth priors on every frame a multiple of %d", cfg.tracking.keyframe_every)
        out["depth"] = stage_stats(bench_depth(frames.frames, sets, cfg, repeat), BUDGET_MS["depth"])
    if "registration" in stages and len(frames) > cfg.tracking.keyframe_every:
        log.info("bench: registration between frames a multiple of %d apart", cfg.tracking.keyframe_every)
        seconds, facts["registration"] = bench_registration(frames.frames, cfg, repeat)
        out["registration"] = stage_stats(seconds, BUDGET_MS["registration"])
    return out, facts


def system_runs(frames: FrameList, cfg: SystemConfig, repeat: int,
                recorder_factory: Callable[[int], tuple[Recorder, Path]] | None = None,
                info: RunInfo | None = None) -> tuple[list[SystemRun], list[SystemRun]]:
    """`repeat` whole runs with recording off, each followed (when a factory is given) by one with it on."""
    off, on = [], []
    for r in range(repeat):
        log.info("bench: whole system, recording off (run %d of %d)", r + 1, repeat)
        off.append(bench_system(frames, cfg))
        if recorder_factory is not None:
            log.info("bench: whole system, recording on (run %d of %d)", r + 1, repeat)
            recorder, path = recorder_factory(r)
            on.append(bench_system(frames, cfg, recorder, info, path))
    return off, on


def input_facts(frames: FrameList, load_s: Sequence[float], cfg: SystemConfig) -> dict:
    idx = frames.frame_indices
    return {"sequence": frames.sequence, "dataset": frames.name, "frames": [idx[0], idx[-1] + 1] if idx else None,
            "n_frames": len(frames), "image_size": [frames.calib.width, frames.calib.height],
            "scan_points_median": int(np.median([len(f.scan) for f in frames.frames])),
            "load_ms_per_frame": round(1e3 * float(np.median(load_s)), 2),
            "in_memory_mb": round(frames.nbytes / 2**20, 1), "keyframe_every": cfg.tracking.keyframe_every,
            "has_ground_truth": frames.gt_T_world_cam is not None}


def run_bench(dataset: Dataset, cfg: SystemConfig, stages: frozenset[str], repeat: int = 1,
              recorder_factory: Callable[[int], tuple[Recorder, Path]] | None = None,
              info: RunInfo | None = None, reopen: Callable[[], Any] | None = None) -> dict:
    """Time the selected stage groups (STAGE_GROUPS) on a Dataset -> the JSON-ready report (schema SCHEMA).

    recorder_factory(run) -> (Recorder, .rrd path): a fresh recording for each recording-on run (with `info` to
    start it); without it, the system is only timed with recording off. reopen: see `deployed_figures`.
    """
    if repeat < 1:
        raise ConfigError(f"--repeat must be at least 1, got {repeat}")
    t0 = time.perf_counter()
    prov = provenance.start()
    report: dict[str, Any] = {"schema": SCHEMA, "created_utc": prov["started_utc"],
                              "stage_groups": [g for g in STAGE_GROUPS if g in stages], "repeat": repeat}
    if len(dataset) < 2:
        raise ConfigError(f"bench: needs at least 2 frames, the selection of {dataset.sequence} has {len(dataset)}")
    deployed = None
    if "system" in stages and recorder_factory is not None:
        # First, while this process holds no frames and has run nothing: plvo-viz's situation. Measured on 04 (3
        # runs x 2, alternating): with the 51 frames preloaded in this process, as the rest of the bench needs them,
        # every process of the deployed run took ~10 % more CPU and the runs were ~10 % slower.
        deployed = deployed_figures(dataset, cfg, recorder_factory, info, repeat, reopen)
    frames, load_s = load_frames(dataset)
    report["input"] = input_facts(frames, load_s, cfg)
    memory: dict[str, Any] = {}
    with RssSampler() as rss:
        stages_out, facts = isolated_stages(frames, cfg, stages, repeat)
    memory["isolated_stages"] = rss.summary()
    report["input"].update(facts)
    if deployed is not None:
        report["deployed"] = deployed
    if stages & SYSTEM_GROUPS:
        off, on = system_runs(frames, cfg, repeat, recorder_factory if "system" in stages else None, info)
        stages_out.update(system_stages(off))
        report["system"] = system_figures(off, on)
        report["system"]["backend_concurrent"] = cfg.backend.concurrent
        memory["system_recording_off"] = max((r.rss for r in off), key=lambda m: m["peak_mb"])
        if on:
            memory["system_recording_on"] = max((r.rss for r in on), key=lambda m: m["peak_mb"])
    report["stages"] = stages_out
    memory["ru_maxrss_mb"] = max_rss_mb()
    memory["sampled_peak_mb"] = max(m["peak_mb"] for m in memory.values() if isinstance(m, dict))
    report["memory"] = memory
    report["config"] = config_to_dict(cfg)
    report["duration_s"] = round(time.perf_counter() - t0, 2)
    report["provenance"] = provenance.finish(prov)
    return report
