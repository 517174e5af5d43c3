"""Evaluate trajectories: `plvo eval metric --gt GT.txt --est EST.txt [--json] [--short 10,20,40]`.

`metric` prints the KITTI devkit figures (translation error in %, rotation error in deg/m, per segment length
100..800 m, a start every 10 frames), the ATE after SE(3) and Sim(3) alignment, and the relative error over short
lengths with every frame a start; then the devkit and short errors again with one constant heading offset of the
truth against the estimate taken out, and the fitted angle (plvo_eval.kitti_metric says why). Either file is KITTI (12
numbers a line) or TUM (time tx ty tz qx qy qz qw); an estimate may be a results folder (its poses.txt, summary.json
and truth.txt), and `--est` repeats to compare runs in one table; `--plot DIR` draws them (plvo_app/eval_metric.py).
`run` runs plvo ablations and KISS-ICP over sequences and writes Table I (see plvo_app/eval_run.py).
`stages` runs plvo and KISS-ICP on a real clip and on its twin and sets their per-stage statistics side by side
(plvo_app/cmd_eval_stages.py).
Further actions are added to EVAL_COMMANDS.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

from plvo_app import cmd_eval_stages, eval_metric


def _add_metric_arguments(p: argparse.ArgumentParser) -> None:
    eval_metric.add_metric_arguments(p)


def _run_metric(args: argparse.Namespace) -> int:
    return eval_metric.run_metric(args)


def _add_run_arguments(p: argparse.ArgumentParser) -> None:
    from plvo_app.eval_run import add_run_arguments  # imports the runner (and kiss_icp lazily) only when used

    add_run_arguments(p)


def _run_run(args: argparse.Namespace) -> int:
    from plvo_app.eval_run import run_run

    return run_run(args)


# name -> (add_arguments, run, one-line help); `plvo eval run` and friends register here.
EVAL_COMMANDS: dict[str, tuple[Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int], str]] = {
    "metric": (_add_metric_arguments, _run_metric,
               "KITTI devkit metric, ATE and short relative error of poses (KITTI, TUM, results folders); plots"),
    "run": (
        _add_run_arguments,
        _run_run,
        "run plvo ablations and KISS-ICP over sequences (local processes or Ray); Table I, JSON and plots",
    ),
    "stages": cmd_eval_stages.COMMAND,
}


class _DeferredArguments(argparse.ArgumentParser):
    """An action's parser whose arguments are added when it parses (or prints its help): `plvo eval --help` and
    every other action then never import `run`'s runner (the dataset readers, pykitti and pandas: ~0.4 s)."""

    pending: Callable[[argparse.ArgumentParser], None] | None = None

    def _add_pending(self) -> None:
        if self.pending is not None:
            add, self.pending = self.pending, None
            add(self)

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        self._add_pending()
        return super().parse_known_args(args, namespace)

    def format_help(self) -> str:
        self._add_pending()
        return super().format_help()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="eval_command", required=True, metavar="ACTION", parser_class=_DeferredArguments)
    for name, (add, run_func, help_text) in EVAL_COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.pending = add
        p.set_defaults(eval_run=run_func)


def run(args: argparse.Namespace) -> int:
    return int(args.eval_run(args))
