"""One evaluation task: a RunSpec (sequence, method, setting) -> poses, metrics and a folder written atomically.

A RunSpec names a sequence (dataset root + sequence name + frames), a method of METHODS ("plvo", "kiss" or
"kiss_slam") and a setting (for plvo an ablation of config.ABLATIONS, plus optional config overrides; "kiss" for
KISS-ICP, "kiss_slam" for KISS-SLAM). A task runs the method, anchors its poses at the first ground-truth pose,
evaluates them with the devkit metric and writes `<out>/runs/<setting>/<label>/` atomically (built under a temporary
name, then renamed): `poses.txt` (estimate, KITTI format), `gt.txt`, `result.json` (spec, status, metrics, timings,
and a method's own figures as "details": KISS-SLAM's loop closures), and for plvo `config.toml`.
A failed task still writes its folder with status "failed" and the error, so that a sweep goes on.
The fan-out over processes or Ray is in plvo_eval.runner.

The peers where the data allow more than one reading: KISS-ICP and KISS-SLAM run on raw sweeps (a KITTI raw drive,
a bag with per-return times, a swept twin) deskewed with the per-return times plvo uses and not deskewed, and on a
lidar with KITTI's elevation error (real KITTI, realistic twins) with kiss_icp's KITTI scan correction and without;
the task reports the run closer to the truth (`better_way`: by the devkit's translation error where the sequence has
devkit segments, else by the short segments' over 10/20/40 m; on a tie, or without truth, the options as given).
Neither helps them everywhere (deskew does not on KITTI's raw drive 0009; the correction costs them on real 04's short
segments and halves their devkit error on the realistic twin of 04), and the table should hold each peer at its
best. The details keep every run's figures under "ways" with the way reported; the task's time counts every run.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from plvo.atomic import write_text_atomic
from plvo.config import SystemConfig, config_to_toml, load_config, merge, with_ablation
from plvo.data.dataset import Dataset, SourceOptions
from plvo.data.registry import open_dataset, parse_frames
from plvo.data.trajectory import read_kitti_poses, write_kitti_poses
from plvo.errors import PlvoError
from plvo_eval.kiss import KissOptions, elevation_error, raw_sweeps, run_kiss
from plvo_eval.kiss_slam import KissSlamOptions, run_kiss_slam
from plvo_eval.kitti_metric import SequenceEvaluation, evaluate_sequence, evaluation_json
from plvo_eval.revisits import loop_edge_errors
from plvo_eval.stage_drift import stage_drift

log = logging.getLogger(__name__)

RESULT_FILE = "result.json"
KISS_SETTING = "kiss"
KISS_SLAM_SETTING = "kiss_slam"
BASELINE_SETTINGS = (KISS_SETTING, KISS_SLAM_SETTING)  # the lidar-only methods beside plvo


@dataclass(frozen=True)
class SequenceSource:
    """A sequence to run: dataset root (None: $KITTI_ROOT; or a bag / plain folder), sequence name, frames 'A:B'
    (None: all), table label; the KITTI camera and, for bags and folders, SourceOptions' fields."""

    root: str | None
    sequence: str
    frames: str | None = None
    label: str = ""
    camera: int = 0
    image_topic: str | None = None
    cloud_topic: str | None = None
    calib: str | None = None
    max_pair_dt: float = SourceOptions.max_pair_dt
    lidar_elevation_offset_deg: float | None = None
    beams: int | None = None

    @property
    def name(self) -> str:
        return self.label or self.sequence

    def open(self) -> Dataset:
        frames = parse_frames(self.frames) if self.frames else None
        options = SourceOptions(self.image_topic, self.cloud_topic, self.calib, self.max_pair_dt,
                                self.lidar_elevation_offset_deg, self.beams)
        return open_dataset(self.root, self.sequence, frames=frames, camera=self.camera, options=options)


@dataclass(frozen=True)
class RunSpec:
    """One task: a sequence, a method of METHODS, a setting name (table column; the ablation for plvo), nested
    config overrides and an optional config file (plvo), KISS-ICP options (kiss), KISS-SLAM options (kiss_slam)."""

    source: SequenceSource
    method: str = "plvo"
    setting: str = "full"
    ablation: str | None = "full"
    overrides: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    config_path: str | None = None
    kiss: KissOptions = field(default_factory=KissOptions)
    kiss_slam: KissSlamOptions = field(default_factory=KissSlamOptions)

    def folder(self, out_dir: str | os.PathLike[str]) -> Path:
        return Path(out_dir) / "runs" / self.setting / self.source.name

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_json(data: Mapping[str, Any]) -> RunSpec:
        data = dict(data)
        data["source"] = SequenceSource(**data["source"])
        data["kiss"] = KissOptions(**data.get("kiss", {}))
        data["kiss_slam"] = KissSlamOptions(**data.get("kiss_slam", {}))
        return RunSpec(**data)


@dataclass(frozen=True)
class MethodOutput:
    """poses: (N,4,4) T_world_cam of cam0 (world = cam0 of the first frame); timings: stage -> seconds a run;
    details: the method's own figures, JSON-able (KISS-SLAM: its loop closures)."""

    poses: np.ndarray
    timings: Mapping[str, Sequence[float]] = field(default_factory=dict)
    details: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class TaskOutput:
    """What a task computed (picklable, written to a folder by `write_task`). est/gt: (N,4,4) or None."""

    spec: RunSpec
    status: str  # "ok" or "failed"
    error: str = ""
    est: np.ndarray | None = None
    gt: np.ndarray | None = None
    n_frames: int = 0
    seconds: float = 0.0
    metrics: Mapping[str, Any] | None = None
    timings: Mapping[str, Any] = field(default_factory=dict)
    config_toml: str | None = None
    details: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class TaskResult:
    """A task's summary as read back from its folder: the result.json fields and the folder (details: {} for a
    method without its own figures)."""

    spec: RunSpec
    status: str
    error: str
    n_frames: int
    seconds: float
    fps: float
    metrics: Mapping[str, Any] | None
    timings: Mapping[str, Any]
    folder: Path
    details: Mapping[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == "ok"


# ---------------------------------------------------------------- methods


def plvo_config(spec: RunSpec) -> SystemConfig:
    """The resolved SystemConfig of a plvo spec: file (or defaults), then the ablation, then the overrides."""
    config = load_config(spec.config_path)
    if spec.ablation:
        config = with_ablation(config, spec.ablation)
    if spec.overrides:
        config = merge(config, {k: dict(v) for k, v in spec.overrides.items()})
    return config


def run_pipeline(dataset: Dataset, config: SystemConfig) -> MethodOutput:
    """Dataset + SystemConfig -> plvo's cam0 poses (N,4,4) T_world_cam0 and per-stage timings; with ground truth
    its details say what each stage left of the heading and scale (plvo_eval.stage_drift) and how true each accepted
    loop is (plvo_eval.revisits.loop_edge_errors)."""
    from plvo.runtime.run import run_dataset

    out = run_dataset(dataset, config)
    poses = np.asarray(out.poses, dtype=np.float64)
    return MethodOutput(poses, dict(out.timings), run_details(dataset, out, poses))


def run_details(dataset: Dataset, out: Any, poses: np.ndarray) -> dict[str, Any]:
    """A plvo run's figures beside its poses: the loops it accepted, keyframes, tracking losses, and with ground
    truth the stage drift and each loop's error."""
    details: dict[str, Any] = {"keyframes": int(out.n_keyframes), "tracking_losses": int(out.n_lost),
                               "frames_by_source": getattr(out, "trust", {}).get("frames_by_source", {}),
                               "loops_accepted": len(out.loop_edges)}
    gt = dataset.gt_T_world_cam
    if gt is None:
        return details
    T_cam0_cam = np.asarray(dataset.calib.T_cam0_cam, float)
    gt_cam0 = gt @ np.linalg.inv(T_cam0_cam)
    details["stage_drift"] = stage_drift(out.stage_steps, out.frame_indices, gt_cam0, poses, T_cam0_cam)
    row = {int(f): k for k, f in enumerate(out.frame_indices)}
    kf_row = {k: row[f] for k, f in enumerate(out.keyframe_frames) if f in row}
    loops = loop_edge_errors(gt, kf_row, out.loop_edges)
    details["loops"] = loops
    details["loops_true"] = sum(1 for e in loops if e["true"])
    return details


def _method_plvo(dataset: Dataset, spec: RunSpec) -> MethodOutput:
    return run_pipeline(dataset, plvo_config(spec))


def _method_kiss(dataset: Dataset, spec: RunSpec) -> MethodOutput:
    def run(options: KissOptions) -> MethodOutput:
        out = run_kiss(dataset, options)
        return MethodOutput(out.poses, {"registration": out.seconds.tolist()})

    return _both_ways(dataset, spec.kiss, run)


def _method_kiss_slam(dataset: Dataset, spec: RunSpec) -> MethodOutput:
    def run(options: KissSlamOptions) -> MethodOutput:
        out = run_kiss_slam(dataset, options)
        details = {
            "loop_closures": out.n_closures,
            "closures": [asdict(c) for c in out.closures],
            "local_maps": out.n_local_maps,
        }
        return MethodOutput(out.poses, {"registration": out.seconds.tolist(), "finalize": [out.finalize_s]},
                            details)

    return _both_ways(dataset, spec.kiss_slam, run)


DESKEWED, NOT_DESKEWED = "deskewed", "not_deskewed"
AS_DELIVERED = "as_delivered"  # compensated scans: nothing to deskew
CORRECTED = "+elevation_corrected"  # suffix of a way with kiss_icp's KITTI scan correction


def peer_ways(dataset: Dataset, options: Any) -> dict[str, Any]:
    """A peer's options (KissOptions or KissSlamOptions) -> way name -> the options of each reading the data allow:
    deskewed or not where the scans are raw sweeps (and deskew is asked for), and with kiss_icp's KITTI scan
    correction or not where the lidar carries KITTI's elevation error; one way without `both_ways`."""
    raw = raw_sweeps(dataset)
    ways = {DESKEWED if raw and options.deskew else AS_DELIVERED: options}
    if not options.both_ways:
        return ways
    if options.deskew and raw:
        ways[NOT_DESKEWED] = replace(options, deskew=False)
    if not options.kitti_correction and elevation_error(dataset):
        ways.update({way + CORRECTED: replace(opts, kitti_correction=True) for way, opts in list(ways.items())})
    return ways


def _both_ways(dataset: Dataset, options: Any, run: Callable[[Any], MethodOutput]) -> MethodOutput:
    """A peer's run with its options; where the data allow more readings (`peer_ways`), each of them, and the best
    against the truth (`better_way`)."""
    ways = peer_ways(dataset, options)
    if len(ways) == 1:
        return run(options)
    return better_way({way: run(opts) for way, opts in ways.items()}, dataset.gt_T_world_cam, dataset.sequence)


def better_way(runs: Mapping[str, MethodOutput], gt: np.ndarray | None, name: str = "") -> MethodOutput:
    """A peer's runs by way (`peer_ways`: the options as given first) and the truth (N,4,4) or None -> the
    run closer to the truth, by the devkit's translation error where all have devkit segments, else by the short
    segments' (10, 20, 40 m); the first way on a tie, without truth or without a figure. Its details gain "ways": the
    way reported, the figure it was judged by, and each way's metrics (as result.json's) and details."""
    metrics = {way: None if gt is None else evaluate_poses(gt, out.poses, name) for way, out in runs.items()}
    judged_by = None
    for key in ("t_err_pct", "short_t_err_pct"):
        if all(m is not None and m.get(key) is not None for m in metrics.values()):
            judged_by = key
            break
    order = list(runs)
    reported = order[0]
    if judged_by is not None:
        reported = min(order, key=lambda way: (float(metrics[way][judged_by]), order.index(way)))  # type: ignore[index]
    chosen = runs[reported]
    ways = {"reported": reported, "judged_by": judged_by,
            "ways": {way: {"metrics": metrics[way], "details": dict(out.details)} for way, out in runs.items()}}
    return MethodOutput(chosen.poses, chosen.timings, {**chosen.details, "ways": ways})


# method name -> (dataset, spec) -> MethodOutput
METHODS: dict[str, Callable[[Dataset, RunSpec], MethodOutput]] = {
    "plvo": _method_plvo, "kiss": _method_kiss, "kiss_slam": _method_kiss_slam,
}


# ---------------------------------------------------------------- one task


def evaluate_poses(gt: np.ndarray, poses: np.ndarray, name: str = "") -> dict[str, Any]:
    """A method's poses (N,4,4), anchored at the first ground-truth pose, against the truth (N,4,4) -> metrics_dict."""
    est = anchor(np.asarray(poses, dtype=np.float64), gt[0])
    return metrics_dict(evaluate_sequence(gt, est, name=name), gt, est)


def metrics_dict(ev: SequenceEvaluation, gt: np.ndarray, est: np.ndarray) -> dict[str, Any]:
    """A sequence's figures with the keys of `plvo eval metric --json` (NaN as null), plus final_drift_m: the
    distance (m) between the last estimated and ground-truth positions, est anchored at the first gt pose."""
    return {**evaluation_json(ev), "final_drift_m": float(np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]))}


def anchor(est: np.ndarray, gt_first: np.ndarray) -> np.ndarray:
    """(N,4,4) estimate -> the same trajectory moved so that its first pose is gt_first (4,4)."""
    return gt_first @ np.linalg.inv(est[0]) @ est


def summarize_timings(timings: Mapping[str, Any]) -> dict[str, Any]:
    """stage -> seconds per run (list) -> stage -> runs, median_ms, p90_ms, total_s; other values kept if JSON-able."""
    out: dict[str, Any] = {}
    for name, values in timings.items():
        if isinstance(values, (list, tuple, np.ndarray)) and len(values) and np.isscalar(np.asarray(values)[0]):
            v = np.asarray(values, dtype=np.float64)
            out[str(name)] = {
                "runs": int(v.size),
                "median_ms": float(np.median(v) * 1e3),
                "p90_ms": float(np.percentile(v, 90) * 1e3),
                "total_s": float(v.sum()),
            }
        else:
            try:
                json.dumps(values)
                out[str(name)] = values
            except TypeError:
                out[str(name)] = repr(values)
    return out


def execute_task(spec: RunSpec) -> TaskOutput:
    """Run one spec (in any process) -> its poses and metrics; failures become status "failed", never raise."""
    t0 = time.perf_counter()
    try:
        if spec.method not in METHODS:
            raise PlvoError(f"unknown method {spec.method!r} (choose from {', '.join(METHODS)})")
        config_toml = config_to_toml(plvo_config(spec)) if spec.method == "plvo" else None
        dataset = spec.source.open()
        out = METHODS[spec.method](dataset, spec)
        est = np.asarray(out.poses, dtype=np.float64)
        if est.shape != (len(dataset), 4, 4):
            raise PlvoError(f"{spec.method} on {spec.source.name}: poses {est.shape}, expected ({len(dataset)},4,4)")
        gt = dataset.gt_T_world_cam
        metrics = None
        if gt is not None:
            est = anchor(est, gt[0])
            metrics = metrics_dict(evaluate_sequence(gt, est, name=spec.source.name), gt, est)
        return TaskOutput(
            spec, "ok", est=est, gt=gt, n_frames=len(dataset), seconds=time.perf_counter() - t0,
            metrics=metrics, timings=summarize_timings(out.timings), config_toml=config_toml,
            details=dict(out.details),
        )
    except Exception as exc:  # one bad run must not end a sweep: record it
        kind = "" if isinstance(exc, PlvoError) else f"{type(exc).__name__}: "
        log.warning("task %s/%s failed: %s", spec.setting, spec.source.name, exc)
        detail = "" if isinstance(exc, PlvoError) else "\n" + traceback.format_exc(limit=8)
        return TaskOutput(spec, "failed", error=f"{kind}{exc}{detail}", seconds=time.perf_counter() - t0)


def write_task(output: TaskOutput, out_dir: str | os.PathLike[str]) -> TaskResult:
    """Write a task's folder atomically: fill a temporary sibling, then swap it in for any previous one."""
    final = output.spec.folder(out_dir)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".part", dir=final.parent))
    try:
        if output.est is not None:
            write_kitti_poses(tmp / "poses.txt", output.est)
        if output.gt is not None:
            write_kitti_poses(tmp / "gt.txt", output.gt)
        if output.config_toml is not None:
            write_text_atomic(tmp / "config.toml", output.config_toml)
        fps = output.n_frames / output.seconds if output.status == "ok" and output.seconds > 0 else 0.0
        result = {
            "spec": output.spec.to_json(),
            "status": output.status,
            "error": output.error,
            "n_frames": output.n_frames,
            "seconds": output.seconds,
            "fps": fps,
            "metrics": output.metrics,
            "timings": dict(output.timings),
        }
        if output.details:  # only a method with figures of its own: the other results keep their fields
            result["details"] = dict(output.details)
        write_text_atomic(tmp / RESULT_FILE, json.dumps(result, indent=1, allow_nan=False) + "\n")
        _swap_in(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return read_result(final)


def _swap_in(tmp: Path, final: Path) -> None:
    """Replace `final` by `tmp`; an old folder is renamed away first, so `final` is always old or new, complete."""
    if final.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".old", dir=final.parent))
        os.replace(final, old / final.name)
        os.replace(tmp, final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, final)


def read_result(folder: str | os.PathLike[str]) -> TaskResult:
    """A task folder -> its TaskResult (from result.json)."""
    folder = Path(folder)
    path = folder / RESULT_FILE
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise PlvoError(f"{path}: cannot read task result ({exc})") from None
    return TaskResult(
        spec=RunSpec.from_json(data["spec"]), status=data["status"], error=data.get("error", ""),
        n_frames=int(data.get("n_frames", 0)), seconds=float(data.get("seconds", 0.0)),
        fps=float(data.get("fps", 0.0)), metrics=data.get("metrics"), timings=data.get("timings", {}), folder=folder,
        details=data.get("details", {}),
    )


def load_poses(result: TaskResult) -> tuple[np.ndarray | None, np.ndarray | None]:
    """A task's (gt, est) (N,4,4) from its folder, None where absent."""
    gt_path, est_path = result.folder / "gt.txt", result.folder / "poses.txt"
    gt = read_kitti_poses(gt_path) if gt_path.is_file() else None
    est = read_kitti_poses(est_path) if est_path.is_file() else None
    return gt, est


def run_and_write(spec: RunSpec, out_dir: str) -> TaskResult:
    """execute_task + write_task: what a local worker process runs."""
    return write_task(execute_task(spec), out_dir)
