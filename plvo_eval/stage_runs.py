"""One side of a stage report (plvo_eval.stage_report): plvo and KISS-ICP run on one sequence as `plvo eval run`
runs them (plvo_eval.tasks: the defaults or the given config, deployed mode; KISS-ICP with its options, on raw
sweeps deskewed and not with the way closer to the truth reported), each with its per-stage statistics
(plvo_eval.stage_stats, plvo_eval.kiss_stats) and its accuracy against the ground truth.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from plvo.data.dataset import Dataset
from plvo_eval.kiss import KissOptions
from plvo_eval.kiss_stats import kiss_summary, run_kiss_stats
from plvo_eval.kitti_metric import evaluate_sequence
from plvo_eval.shared_error import shared_error
from plvo_eval.stage_stats import StageStatsRecorder, backend_moves, drift_stats
from plvo_eval.tasks import (
    DESKEWED,
    MethodOutput,
    RunSpec,
    SequenceSource,
    anchor,
    better_way,
    metrics_dict,
    peer_ways,
    plvo_config,
    run_details,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SideResult:
    """A sequence's statistics: plvo's and KISS-ICP's (name -> plvo_eval.stage_stats.describe entry), each system's
    accuracy (accuracy_figures; {} without ground truth), plvo's run details (keyframes, losses, stage drift), the
    peer's ways and what the two systems' errors share."""

    source: SequenceSource
    n_frames: int
    plvo: Mapping[str, Mapping[str, Any]]
    kiss: Mapping[str, Mapping[str, Any]]
    accuracy: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    plvo_details: Mapping[str, Any] = field(default_factory=dict)
    kiss_way: str = DESKEWED
    kiss_ways: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    # what plvo's and KISS-ICP's errors share (plvo_eval.shared_error; a = plvo, b = KISS-ICP), by segment length
    shared: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"source": asdict(self.source), "n_frames": self.n_frames, "accuracy": dict(self.accuracy),
                "plvo_details": dict(self.plvo_details), "kiss_way": self.kiss_way, "kiss_ways": dict(self.kiss_ways),
                "shared": dict(self.shared)}


def accuracy_figures(metrics: Mapping[str, Any]) -> dict[str, Any]:
    """plvo_eval.tasks.metrics_dict's figures -> the short-segment translation errors (%) by length and over all
    short segments, as they are and (by length) with the heading offset taken out where the metric gives that
    reading (else None), the angle, the devkit error, ATE and the final drift."""
    aligned = metrics.get("heading_aligned")
    return {
        "path_length_m": metrics["path_length_m"],
        "t_err_pct": {k: v["t_err_pct"] for k, v in metrics["short"].items()},
        "short_t_err_pct": metrics["short_t_err_pct"],
        "aligned_t_err_pct": None if aligned is None else {k: v["t_err_pct"] for k, v in aligned["short"].items()},
        "heading_offset_deg": None if aligned is None else aligned["heading_offset_deg"],
        "devkit_t_err_pct": metrics["t_err_pct"],
        "ate_m": metrics["ate_m"],
        "final_drift_m": metrics["final_drift_m"],
    }


def _accuracy(dataset: Dataset, poses: np.ndarray) -> dict[str, Any]:
    gt = dataset.gt_T_world_cam
    if gt is None:
        return {}
    est = anchor(np.asarray(poses, np.float64), gt[0])
    return accuracy_figures(metrics_dict(evaluate_sequence(gt, est, name=dataset.sequence), gt, est))


def _gt_cam0(dataset: Dataset) -> np.ndarray | None:
    gt = dataset.gt_T_world_cam
    return None if gt is None else gt @ np.linalg.inv(np.asarray(dataset.calib.T_cam0_cam, float))


def run_plvo_side(dataset: Dataset, spec: RunSpec
                  ) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any], np.ndarray]:
    """plvo on a dataset with spec's config (plvo_eval.tasks.plvo_config) -> (statistics, accuracy, run details,
    poses (N,4,4))."""
    from plvo.runtime.run import run_dataset

    recorder = StageStatsRecorder()
    # handed in directly, not in a FanOut: a FanOut drops a recorder that fails and the run goes on, which would
    # leave statistics that look complete but are not; here a failure fails the run
    out = run_dataset(dataset, plvo_config(spec), recorder)
    poses = np.asarray(out.poses, np.float64)
    details = run_details(dataset, out, poses)
    stats = recorder.summary()
    stats.update(backend_moves(out.stage_steps))
    if "stage_drift" in details:
        stats.update(drift_stats(details["stage_drift"]))
    return stats, _accuracy(dataset, poses), details, poses


def run_kiss_side(dataset: Dataset, options: KissOptions
                  ) -> tuple[str, dict[str, dict[str, Any]], np.ndarray]:
    """KISS-ICP on a dataset as `plvo eval run` runs it: in every reading the data allow (plvo_eval.tasks.peer_ways),
    the way closer to the truth reported (plvo_eval.tasks.better_way) -> (the way reported, way -> {"stats",
    "accuracy"}, the reported way's poses (N,4,4))."""
    ways = peer_ways(dataset, options)
    runs, outputs = {}, {}
    for way, opts in ways.items():
        out, per_frame = run_kiss_stats(dataset, opts)
        outputs[way] = MethodOutput(out.poses)
        runs[way] = {"stats": kiss_summary(per_frame, dataset.frame_indices, _gt_cam0(dataset), out.poses),
                     "accuracy": _accuracy(dataset, out.poses)}
    reported = next(iter(runs))
    if len(runs) > 1:
        reported = better_way(outputs, dataset.gt_T_world_cam, dataset.sequence).details["ways"]["reported"]
    return reported, runs, np.asarray(outputs[reported].poses)


def run_side(source: SequenceSource, spec: RunSpec | None = None, kiss: KissOptions | None = None) -> SideResult:
    """Open a source and run plvo (spec: the config; default `plvo eval run`'s, ablation full) and KISS-ICP on it."""
    spec = spec or RunSpec(source)
    dataset = source.open()
    log.info("%s: plvo on %d frames", source.name, len(dataset))
    plvo_stats, plvo_acc, details, plvo_poses = run_plvo_side(dataset, spec)
    log.info("%s: KISS-ICP on %d frames", source.name, len(dataset))
    way, kiss_ways, kiss_poses = run_kiss_side(dataset, kiss or spec.kiss)
    accuracy = {k: v for k, v in (("plvo", plvo_acc), ("kiss", kiss_ways[way]["accuracy"])) if v}
    gt = dataset.gt_T_world_cam
    shared = {} if gt is None else shared_error(gt, anchor(plvo_poses, gt[0]), anchor(kiss_poses, gt[0]))
    return SideResult(source, len(dataset), plvo_stats, kiss_ways[way]["stats"], accuracy, details, way, kiss_ways,
                      shared)
