"""Evaluate trajectories: `plvo eval metric --gt GT.txt --est EST.txt [--json] [--short 10,20,40]`.

`metric` prints the KITTI devkit figures (translation error in %, rotation error in deg/m, per segment length
100..800 m, a start every 10 frames), the ATE after SE(3) and Sim(3) alignment, and the relative error over short
lengths with every frame a start; then the devkit and short errors again with one constant heading offset of the
truth against the estimate taken out, and the fitted angle (plvo.eval.kitti_metric says why). Both files are KITTI
pose files (12 numbers a line, one line per frame).
`run` runs plvo ablations and KISS-ICP over sequences and writes Table I (see plvo_app/eval_run.py).
`stages` runs plvo and KISS-ICP on a real clip and on its twin and sets their per-stage statistics side by side
(plvo_app/cmd_eval_stages.py).
Further actions are added to EVAL_COMMANDS.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
from pathlib import Path

from plvo.data.trajectory import read_kitti_poses
from plvo.errors import PlvoError, TrajectoryError
from plvo.eval.kitti_metric import SHORT_LENGTHS, RelativeError, SequenceEvaluation, evaluate_sequence, evaluation_json
from plvo_app import cmd_eval_stages


def _add_metric_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--gt", type=Path, required=True, help="ground-truth poses, KITTI format (e.g. poses/04.txt)")
    p.add_argument("--est", type=Path, required=True, help="estimated poses, KITTI format, same number of lines")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.add_argument(
        "--short",
        default=",".join(f"{v:g}" for v in SHORT_LENGTHS),
        metavar="L1,L2,...",
        help="short segment lengths in metres for the every-frame relative error (default: %(default)s)",
    )


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


def metric_json(ev: SequenceEvaluation, gt: Path, est: Path) -> dict:
    """The --json object: the files, then the figures (plvo.eval.kitti_metric.evaluation_json)."""
    return {"gt": str(gt), "est": str(est), **evaluation_json(ev)}


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


def _run_metric(args: argparse.Namespace) -> int:
    short = parse_lengths(args.short)
    gt = read_kitti_poses(args.gt)
    est = read_kitti_poses(args.est)
    if len(gt) != len(est):
        raise TrajectoryError(f"{args.est}: {len(est)} poses, but the ground truth {args.gt} has {len(gt)}")
    ev = evaluate_sequence(gt, est, name=args.est.stem, short_lengths=short)
    if args.json:
        print(json.dumps(metric_json(ev, args.gt, args.est)))
    else:
        print(metric_table(ev, args.gt, args.est))
    return 0


def _add_run_arguments(p: argparse.ArgumentParser) -> None:
    from plvo_app.eval_run import add_run_arguments  # imports the runner (and kiss_icp lazily) only when used

    add_run_arguments(p)


def _run_run(args: argparse.Namespace) -> int:
    from plvo_app.eval_run import run_run

    return run_run(args)


# name -> (add_arguments, run, one-line help); `plvo eval run` and friends register here.
EVAL_COMMANDS: dict[str, tuple[Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int], str]] = {
    "metric": (_add_metric_arguments, _run_metric, "KITTI devkit metric, ATE and short relative error of poses"),
    "run": (
        _add_run_arguments,
        _run_run,
        "run plvo ablations and KISS-ICP over sequences (local processes or Ray); Table I, JSON and plots",
    ),
    "stages": cmd_eval_stages.COMMAND,
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="eval_command", required=True, metavar="ACTION")
    for name, (add, run_func, help_text) in EVAL_COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        add(p)
        p.set_defaults(eval_run=run_func)


def run(args: argparse.Namespace) -> int:
    return int(args.eval_run(args))
