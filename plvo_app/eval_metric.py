"""`plvo eval metric`: one or several estimates against their truth; tables, JSON and plots.

An estimate (`--est`, repeatable) is a KITTI or TUM pose file, or a plvo results folder: its poses.txt, the
summary.json that plvo-viz writes at the end of a run ("run", "sequence", "frame_indices": the dataset's frame numbers
of poses.txt's lines, "status") and, when the data had ground truth, truth.txt (the truth of those frames, in
poses.txt's format). Its truth is `--gt` (cut to the run's frames, or paired by time: plvo_eval.associate), else the
folder's truth.txt. One estimate prints the detailed report; several print one row each.

Imported by `plvo --help` (the arguments): numpy, matplotlib and the metric come in inside the functions.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from plvo.errors import ArgumentsError, OutputError, PlvoError, TrajectoryError
from plvo_app.run_summary import POSES_FILE, SUMMARY_FILE, TRUTH_FILE

if TYPE_CHECKING:
    import numpy as np

    from plvo_eval.associate import Pairing, PoseFile
    from plvo_eval.kitti_metric import RelativeError, SequenceEvaluation

SHORT_DEFAULT = "10,20,40"  # plvo_eval.kitti_metric.SHORT_LENGTHS, spelled here so that --help imports no numpy
MAX_DT_DEFAULT = 0.02  # plvo_eval.associate.MAX_DT_S (evo's)


def add_metric_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--gt", type=Path, default=None,
                   help="ground-truth poses, KITTI or TUM (told by the column count), e.g. poses/04.txt; cut to a "
                        "run's frames or paired by time. Not needed when every --est is a results folder with a "
                        "truth.txt")
    p.add_argument("--est", type=Path, action="append", required=True, metavar="EST",
                   help="estimated poses: a KITTI or TUM file, or a results folder (results/<run>: its poses.txt, "
                        "summary.json and truth.txt); repeat to compare runs side by side")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="the frames a plain --est file covers (B exclusive), to cut a whole-sequence --gt; a results "
                        "folder's own frames are in its summary.json")
    p.add_argument("--gt-times", type=Path, default=None, metavar="FILE",
                   help="times of a KITTI --gt's lines (one a line, seconds), to pair it by time with TUM estimates; "
                        "default: ROOT/sequences/NN/times.txt for ROOT/poses/NN.txt, or a times.txt beside it")
    p.add_argument("--max-dt", type=float, default=MAX_DT_DEFAULT, metavar="S",
                   help="largest time difference in seconds to pair two poses by time (default: %(default)s)")
    p.add_argument("--plot", type=Path, default=None, metavar="DIR",
                   help="write PNG plots there: trajectory_top, error_along_path, xyz, rpy (never replaces a file)")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (a list of them for several --est) instead of a table")
    p.add_argument("--short", default=SHORT_DEFAULT, metavar="L1,L2,...",
                   help="short segment lengths in metres for the every-frame relative error (default: %(default)s)")


def parse_lengths(text: str) -> tuple[float, ...]:
    """'10,20,40' -> (10.0, 20.0, 40.0); each a positive number of metres."""
    values = []
    for part in text.split(","):
        try:
            value = float(part)
        except ValueError:
            raise PlvoError(f"--short {text!r}: {part.strip()!r} is not a number") from None
        if not math.isfinite(value) or value <= 0:
            raise PlvoError(f"--short {text!r}: lengths must be positive metres, got {part.strip()}")
        values.append(value)
    return tuple(values)


def _fmt(value: float, spec: str) -> str:
    width = int(spec.split(".")[0] or 0)
    return f"{'-':>{width}}" if math.isnan(value) else format(value, spec)


# ---- one estimate and its truth ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Estimate:
    """An --est read: name (a run's name, or the file's stem); given: the path as given; poses; frames: the dataset
    frame numbers of its lines when known, frames_from: where they came from; truth: a results folder's truth.txt."""

    name: str
    given: Path
    poses: PoseFile
    frames: np.ndarray | None
    frames_from: str
    truth: Path | None


@dataclass(frozen=True)
class Run:
    """An estimate paired with its truth and evaluated."""

    estimate: Estimate
    gt_path: Path
    pairing: Pairing
    ev: SequenceEvaluation


def _summary(folder: Path) -> dict[str, Any] | None:
    path = folder / SUMMARY_FILE
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise TrajectoryError(f"{path}: cannot read ({exc})") from None
    except json.JSONDecodeError as exc:
        raise TrajectoryError(f"{path}: not JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(data, dict):
        raise TrajectoryError(f"{path}: not a JSON object")
    return data


def _summary_frames(path: Path, summary: dict[str, Any], n_poses: int) -> np.ndarray:
    import numpy as np

    frames = summary.get("frame_indices")
    if not isinstance(frames, list) or not all(isinstance(f, int) and not isinstance(f, bool) and f >= 0
                                               for f in frames):
        raise TrajectoryError(f"{path}: 'frame_indices' must be a list of frame numbers (integers >= 0)")
    if len(frames) != n_poses:
        raise TrajectoryError(f"{path}: 'frame_indices' lists {len(frames)} frames, but {path.parent / POSES_FILE} "
                              f"has {n_poses} poses")
    return np.asarray(frames, dtype=np.int64)


def read_results_folder(folder: Path) -> Estimate:
    """A results folder: poses.txt, with summary.json's name and frames when there is one, and truth.txt."""
    from plvo_eval.associate import read_pose_file

    summary = _summary(folder)
    poses_file = folder / POSES_FILE
    if not poses_file.is_file():
        status = summary.get("status") if summary else None
        why = (f"the run's status is {status!r} in summary.json; poses.txt is written when a run completes"
               if status else "not a plvo results folder, or its run did not complete")
        raise TrajectoryError(f"{folder}: no poses.txt ({why})")
    poses = read_pose_file(poses_file)
    frames = _summary_frames(folder / SUMMARY_FILE, summary, len(poses)) if summary else None
    name = summary.get("run") if summary else None
    truth = folder / TRUTH_FILE
    return Estimate(name if isinstance(name, str) and name else folder.name, folder, poses, frames,
                    str(folder / SUMMARY_FILE), truth if truth.is_file() else None)


def read_estimate(path: Path, frames_arg: str | None) -> Estimate:
    from plvo_eval.associate import read_pose_file

    if path.is_dir():
        est = read_results_folder(path)
        if frames_arg is not None and est.frames is None:
            return Estimate(est.name, path, est.poses, None, f"--frames {frames_arg}", est.truth)
        return est
    return Estimate(path.stem, path, read_pose_file(path), None, f"--frames {frames_arg}" if frames_arg else "", None)


def _frames_arg(frames_arg: str, n_gt: int, gt: Path) -> np.ndarray:
    """--frames A:B as frame numbers of a truth of n_gt lines (one a frame)."""
    import numpy as np

    from plvo.data.registry import parse_frames

    frames = parse_frames(frames_arg)
    if (frames.start or 0) >= n_gt or (frames.stop is not None and frames.stop > n_gt):
        raise ArgumentsError(f"--frames {frames_arg}: {gt} has {n_gt} poses (frames 0:{n_gt})")
    return np.arange(n_gt)[frames]


def pair_estimate(est: Estimate, gt: PoseFile | None, frames_arg: str | None, max_dt: float) -> tuple[Path, Pairing]:
    """An estimate with its truth: --gt (read already, None if not given) or the folder's truth.txt."""
    from plvo_eval.associate import frames_text, pair, pair_by_lines, read_pose_file, times_beside, with_times

    if gt is None:
        if est.truth is None:
            if est.given.is_dir():
                raise TrajectoryError(f"{est.given}: no truth.txt (the run's data had no ground truth); give --gt")
            raise ArgumentsError(f"--est {est.given}: a pose file needs --gt (only a results folder has its truth)")
        truth = read_pose_file(est.truth)
        if len(truth) != len(est.poses):
            raise TrajectoryError(f"{est.truth}: {len(truth)} poses, but {est.poses.path} has {len(est.poses)}: a "
                                  "run's truth.txt holds the truth of each line of its poses.txt")
        frames_note = f" (frames {frames_text(est.frames)})" if est.frames is not None else ""
        return est.truth, pair_by_lines(truth, est.poses, est.frames, f"truth from {est.truth}{frames_note}")
    frames = est.frames
    if frames is None and frames_arg is not None:
        frames = _frames_arg(frames_arg, len(gt), gt.path)
    if gt.times is None and est.poses.times is not None:
        found = times_beside(gt.path) if gt.fmt == "kitti" else None
        if found is not None:
            try:
                gt = with_times(gt, found)
            except TrajectoryError as exc:
                raise TrajectoryError(f"{exc} (found beside {gt.path}; give the right one as --gt-times FILE)") \
                    from None
    return gt.path, pair(gt, est.poses, frames, est.frames_from, max_dt)


def _check_frames_arg(frames_arg: str | None, estimates: list[Estimate]) -> None:
    """--frames given where every estimate knows its frames already: said, not silently ignored."""
    if frames_arg is not None and estimates and all(e.frames is not None for e in estimates):
        raise ArgumentsError(f"--frames {frames_arg}: every --est is a results folder whose summary.json gives its "
                             "frames; --frames is for a plain pose file")


# ---- output ------------------------------------------------------------------------------------------------------

def metric_json(ev: SequenceEvaluation, gt: Path, est: Path) -> dict:
    """The --json object: the files, then the figures (plvo_eval.kitti_metric.evaluation_json)."""
    from plvo_eval.kitti_metric import evaluation_json

    return {"gt": str(gt), "est": str(est), **evaluation_json(ev)}


def run_json(run: Run) -> dict:
    """metric_json, with the run's name and how it was paired."""
    return {"name": run.estimate.name, **metric_json(run.ev, run.gt_path, run.estimate.given),
            "pairing": run.pairing.how}


def _table_rows(rel: RelativeError) -> list[str]:
    rows = [f"  {'length':>8}  {'segments':>8}  {'t_err %':>9}  {'r_err deg/m':>11}"]
    for e in rel.per_length:
        rows.append(
            f"  {e.length_m:>6g} m  {e.n_segments:>8d}  {_fmt(e.t_err_pct, '9.3f')}  "
            f"{_fmt(e.r_err_deg_per_m, '11.5f')}"
        )
    rows.append(
        f"  {'all':>8}  {rel.n_segments:>8d}  {_fmt(rel.t_err_pct, '9.3f')}  {_fmt(rel.r_err_deg_per_m, '11.5f')}"
    )
    return rows


def metric_table(ev: SequenceEvaluation, gt: Path, est: Path) -> str:
    """Readable report of one evaluation."""
    lines = [
        f"ground truth {gt}, estimate {est}: {ev.n_frames} frames, {ev.path_length_m:.1f} m of ground-truth path",
        "KITTI devkit metric (segments of 100..800 m, a start every 10 frames):",
        *_table_rows(ev.kitti),
    ]
    if ev.kitti.n_segments == 0:
        lines.append("  (no segment: the trajectory is shorter than 100 m; see the short relative error)")
    lines += [
        f"ATE RMSE: {ev.ate_se3.rmse_m:.4f} m after SE(3) alignment, " + (
            f"{ev.ate_sim3.rmse_m:.4f} m after Sim(3) alignment (scale {ev.ate_sim3.scale:.5f})"
            if math.isfinite(ev.ate_sim3.rmse_m) else
            "none after Sim(3) alignment: the ground truth does not move (a scale fitted to it would shrink the "
            "estimate to a point)"),
        "short relative error (devkit error on short lengths, every frame a start):",
        *_table_rows(ev.short),
    ]
    if math.isnan(ev.heading_offset_deg):
        lines.append("heading offset: none fitted (no segment of any length)")
        return "\n".join(lines)
    lines.append(f"heading offset taken out: {ev.heading_offset_deg:.3f} deg about the camera's vertical axis, "
                 "fitted (> 0: the truth runs right of the estimate)")
    if ev.kitti_aligned.n_segments:  # an empty devkit table was shown and explained above
        lines += ["KITTI devkit metric, heading offset taken out:", *_table_rows(ev.kitti_aligned)]
    lines += ["short relative error, heading offset taken out:", *_table_rows(ev.short_aligned)]
    return "\n".join(lines)


def runs_table(runs: list[Run]) -> str:
    """Several runs, a row each: frames, ATE, short errors per length, devkit errors (when any run has a segment),
    heading offset; then a line per run on its files and pairing."""
    columns = ["run", "frames", "ATE SE3 m", "ATE Sim3 m"]
    lengths = [e.length_m for e in runs[0].ev.short.per_length]
    for length in lengths:
        columns += [f"{length:g}m t%", f"{length:g}m deg/m"]
    devkit = any(r.ev.kitti.n_segments for r in runs)
    if devkit:
        columns += ["devkit t%", "devkit deg/m"]
    columns.append("heading deg")
    rows = []
    for r in runs:
        ev = r.ev
        row = [r.estimate.name, str(ev.n_frames), _fmt(ev.ate_se3.rmse_m, ".4f"), _fmt(ev.ate_sim3.rmse_m, ".4f")]
        for e in ev.short.per_length:
            row += [_fmt(e.t_err_pct, ".3f"), _fmt(e.r_err_deg_per_m, ".5f")]
        if devkit:
            row += [_fmt(ev.kitti.t_err_pct, ".3f"), _fmt(ev.kitti.r_err_deg_per_m, ".5f")]
        row.append(_fmt(ev.heading_offset_deg, ".3f"))
        rows.append(row)
    widths = [max(len(c), *(len(row[i]) for row in rows)) for i, c in enumerate(columns)]

    def line(cells: list[str]) -> str:
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))

    notes = [f"  {r.estimate.name}: {r.estimate.given} against {r.gt_path}" + (f"; {r.pairing.how}" if r.pairing.how
                                                                                  else "") for r in runs]
    return "\n".join([line(columns), *(line(row) for row in rows),
                      f"{len(runs)} runs (short errors: every frame a start; devkit: 100..800 m segments; heading: "
                      "the fitted offset of the truth, > 0 to the right):", *notes])


def _names_unique(estimates: list[Estimate]) -> list[Estimate]:
    """Two runs of one name (two poses.txt, two results folders of one run name) are told apart by their paths."""
    from dataclasses import replace

    names = [e.name for e in estimates]
    return [replace(e, name=str(e.given)) if names.count(e.name) > 1 else e for e in estimates]


# ---- the command -------------------------------------------------------------------------------------------------

def _plan_plots(plot_dir: Path | None) -> None:
    """Refuse the plots before any work if their folder is a file or a plot exists (docs/faults.md, "Outputs")."""
    if plot_dir is None:
        return
    from plvo_app.run_outputs import refuse_existing
    from plvo_eval.metric_plots import plot_paths

    if plot_dir.exists() and not plot_dir.is_dir():
        raise OutputError(f"--plot {plot_dir}: is a file, not a folder for the plots")
    existing = next(p for p in (plot_dir, *plot_dir.absolute().parents) if p.exists())
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise OutputError(f"--plot {plot_dir}: cannot write the plots in {existing}")
    refuse_existing(list(plot_paths(plot_dir).values()), "plvo eval metric --plot", "choose another --plot folder")


def _write_plots(runs: list[Run], plot_dir: Path) -> dict[str, Path]:
    from plvo_eval.metric_plots import PlottedRun, write_metric_plots

    plotted = [PlottedRun(r.estimate.name, r.pairing.gt, r.pairing.est, r.pairing.frames, r.pairing.times,
                          r.ev.ate_se3) for r in runs]
    try:
        return write_metric_plots(plotted, plot_dir)
    except OSError as exc:
        raise OutputError(f"--plot {plot_dir}: cannot write the plots ({exc.strerror or exc})") from None


def run_metric(args: argparse.Namespace) -> int:
    """The command: read and pair every estimate, evaluate each, print, plot."""
    from plvo_eval.associate import read_pose_file, with_times
    from plvo_eval.kitti_metric import evaluate_sequence

    short = parse_lengths(args.short)
    if not (math.isfinite(args.max_dt) and args.max_dt > 0):
        raise ArgumentsError(f"--max-dt {args.max_dt:g}: must be a positive number of seconds")
    if args.gt_times is not None and args.gt is None:
        raise ArgumentsError(f"--gt-times {args.gt_times}: there is no --gt to give times to")
    _plan_plots(args.plot)
    gt = read_pose_file(args.gt) if args.gt is not None else None
    if gt is not None and args.gt_times is not None:
        gt = with_times(gt, args.gt_times)
    estimates = _names_unique([read_estimate(path, args.frames) for path in args.est])
    _check_frames_arg(args.frames, estimates)
    runs = []
    for est in estimates:
        gt_path, pairing = pair_estimate(est, gt, args.frames, args.max_dt)
        ev = evaluate_sequence(pairing.gt, pairing.est, name=est.name, short_lengths=short)
        runs.append(Run(est, gt_path, pairing, ev))
    if args.json:
        out = [run_json(r) for r in runs]
        print(json.dumps(out[0] if len(out) == 1 else out))
    elif len(runs) == 1:
        if runs[0].pairing.how:
            print(f"{runs[0].estimate.given}: {runs[0].pairing.how}")
        print(metric_table(runs[0].ev, runs[0].gt_path, runs[0].estimate.given))
    else:
        print(runs_table(runs))
    if args.plot is not None:
        import sys

        written = _write_plots(runs, args.plot)
        for path in written.values():  # beside JSON, on stderr: stdout stays one JSON document
            print(f"plot: {path}", file=sys.stderr if args.json else sys.stdout)
    return 0
