"""Rerun a recording's frames with its config and report whether the run reproduces.

  plvo reproduce FILE.rrd [--root DIR] [--set backend.concurrent=false]

Without --root the inputs come from the recording (frames embedded with `plvo-viz --embed-inputs A:B`), else from
the dataset root the recording names. Exit status: 0 when the run reproduces, 1 when it departs (the first frame
whose pose departs by more than the tolerance and the first stage result that changed are printed), 2 on bad input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from plvo.errors import RecordingError

# plvo_app.reproduce (the pipeline, the recording's reader) is imported by `run`: `plvo reproduce --help` answers at
# once.


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", type=Path, metavar="FILE.rrd", help="a recording written by plvo-viz")
    p.add_argument("--root", type=Path, help="dataset root holding the recorded sequence (default: the inputs "
                   "embedded in the recording, else the root it was recorded from)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="change one config value of the recorded config (repeatable), e.g. orb.n_features=1500")
    p.add_argument("--tol-m", type=float, default=0.01, help="pose tolerance, metres (default 0.01)")
    p.add_argument("--tol-deg", type=float, default=0.1, help="pose tolerance, degrees (default 0.1)")
    p.add_argument("--keep", type=Path, metavar="OUT.rrd", help="keep the rerun's recording (summary level) here")


def run(args: argparse.Namespace) -> int:
    from plvo_app.reproduce import parse_set, reproduce

    if args.keep is not None and args.keep.exists():
        raise RecordingError(f"{args.keep}: already exists; plvo reproduce never overwrites a file")
    report = reproduce(args.file, args.root, parse_set(args.set), args.tol_m, args.tol_deg, args.keep)
    for line in report.lines(args.tol_m, args.tol_deg):
        print(line, file=sys.stdout)
    return 0 if report.reproduces else 1
