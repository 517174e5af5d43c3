"""`plvo eval stages`: where real frames cost plvo and KISS-ICP, stage by stage, against the twin of the same stretch.

Examples:
  plvo eval stages --real ../shared/data/kitti 04 --twin data/twins 04 --frames 0:51 --out results/stages04
  plvo eval stages --real ../shared/data/kitti_raw 2011_09_26_drive_0009 --twin data/twins_raw 0009 --out OUT
  plvo eval stages --real ROOT 04 --twin TWINS 04 --frames 0:51 --set depth.point_patch_px=9 --out OUT

Runs plvo (as `plvo eval run` does: the defaults or --config and --set, deployed mode) and KISS-ICP (voxel 1 m,
deskewed where the scans are raw sweeps) on both sequences, gathering per-stage statistics (plvo_eval.stage_stats,
plvo_eval.kiss_stats), and writes OUT/report.md and OUT/report.json: per statistic the real clip's and the twin's
figure, twin / real, flagged outside 0.8-1.25; each system's accuracy on both (plvo_eval.stage_report).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import shlex
import sys
from pathlib import Path

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = __doc__.split("\n\n")[0]
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = __doc__.split("\n", 1)[1]
    p.add_argument("--real", nargs=2, required=True, metavar=("ROOT", "SEQ"),
                   help="the real clip: a dataset root and a sequence in it, as --root and --seq of plvo eval run "
                        "take them (KITTI odometry 04, a raw drive 2011_09_26_drive_0009)")
    p.add_argument("--twin", nargs=2, required=True, metavar=("ROOT", "SEQ"),
                   help="its twin: a root and sequence (e.g. the twins' folder and 04)")
    p.add_argument("--frames", metavar="A:B", help="frames A..B-1 of both (default: all)")
    p.add_argument("--twin-frames", metavar="A:B", help="the twin's frames when they differ from --frames")
    p.add_argument("--config", type=Path, help="plvo config TOML (default: built-in)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a plvo config value on both sides (repeatable)")
    p.add_argument("--out", type=Path, default=Path("results/stages"), help="output folder (default: %(default)s)")


def _source(pair: list[str], frames: str | None, label: str):
    from plvo_eval.tasks import SequenceSource

    root, seq = pair
    return SequenceSource(str(Path(root).resolve()), seq, frames, label=label)


def run(args: argparse.Namespace) -> int:
    from plvo.atomic import write_text_atomic
    from plvo.data.registry import parse_frames
    from plvo.errors import OutputError
    from plvo_app.eval_run import parse_overrides
    from plvo_app.run_outputs import refuse_existing
    from plvo_eval import provenance
    from plvo_eval.stage_report import report_markdown, stage_report
    from plvo_eval.stage_runs import run_side
    from plvo_eval.tasks import RunSpec

    started = provenance.start()
    if args.out.exists() and not args.out.is_dir():
        raise OutputError(f"--out {args.out}: is a file, not an output folder")
    refuse_existing([args.out / "report.json", args.out / "report.md"], "plvo eval stages", "choose another --out")
    for text in (args.frames, args.twin_frames):
        if text:
            parse_frames(text)  # a bad range fails before anything runs
    overrides = parse_overrides(args.set)
    config = str(args.config.resolve()) if args.config else None
    real = _source(args.real, args.frames, "real")
    twin = _source(args.twin, args.twin_frames or args.frames, "twin")
    for source in (real, twin):
        source.open()  # a missing root, sequence or frame fails here, before the first run
    sides = []
    for source in (real, twin):
        print(f"{source.label}: {source.root} {source.sequence} {source.frames or ''}".rstrip(), flush=True)
        sides.append(run_side(source, RunSpec(source, overrides=overrides, config_path=config)))
    data = json_safe(stage_report(*sides))
    data["provenance"] = provenance.finish(started)
    command = "plvo " + shlex.join(sys.argv[1:]) if sys.argv and Path(sys.argv[0]).name == "plvo" else ""
    markdown = report_markdown(data, command)
    args.out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out / "report.json", json.dumps(data, indent=1, allow_nan=False) + "\n")
    write_text_atomic(args.out / "report.md", markdown + "\n")
    print(markdown)
    print(f"wrote {args.out / 'report.md'} and {args.out / 'report.json'}")
    return 0


def json_safe(value):
    """Nested dicts, lists and numbers (numpy's as Python's) with every non-finite float as None (JSON has no
    NaN)."""
    import numpy as np

    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


COMMAND = (add_arguments, run, "a real clip and its twin side by side, stage by stage, for plvo and KISS-ICP")
