"""`plvo eval run`: run plvo (under each ablation), KISS-ICP and KISS-SLAM over sequences, then write Table I and
plots.

Examples:
  plvo eval run --root /data/kitti --seq 00 04 --ablations full,points_only --kiss --out results/eval
  plvo eval run --synth town/ --kiss --workers 2            # every sequence under town/sequences
  plvo eval run --root ../shared/data/kitti --seq 04 --ablations none --kiss --kiss-slam
  plvo eval run --root /data/kitti --seq 00 01 02 --ray local --workers 2
  plvo eval run --root /data/kitti --seq 00 --ray ray://head:10001 --set tracking.keyframe_every=3
  plvo eval run --twins 00-10 --kitti-poses ../shared/data/kitti/poses --twin-root data/twins --frames 0:200

--twins generates (or keeps, when current) the KITTI twins NN under --twin-root, driven along --kitti-poses/NN.txt
(frames --frames of each, then run whole), and runs Table I on them: by default the ablations full,
no_depth_priors, no_scale_correction, points_only and KISS-ICP and KISS-SLAM beside them; rows are labelled twinNN.

Each (sequence, setting) is one task writing `OUT/runs/<setting>/<sequence>/` (poses.txt, gt.txt, result.json,
config.toml) atomically; the tables go to OUT/report.md and OUT/report.json, the plots to OUT/plots/*.png.
"""

from __future__ import annotations

import argparse
import ast
import logging
import os
import sys
from dataclasses import replace
from pathlib import Path

from plvo.config import ABLATIONS
from plvo.data import ROOT_ENV
from plvo.errors import OutputError, PlvoError
from plvo_app.run_outputs import refuse_existing
from plvo_app.source_args import add_source_arguments
from plvo_eval import provenance
from plvo_eval.kiss import KissOptions
from plvo_eval.report import build_report, report_markdown
from plvo_eval.report_files import write_report
from plvo_eval.runner import SequenceSource, TaskResult, build_specs, execute, kiss_threads, with_threads

log = logging.getLogger(__name__)
# the paper's Ours (*), (-), (#) and point-only, then each lidar-side component of plvo's own switched off
TABLE_I_ABLATIONS = "full,no_depth_priors,no_scale_correction,points_only,no_deskew,keyframe_ndt,no_lidar_loops"


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    p.description = __doc__.split("\n\n")[0]
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = __doc__.split("\n", 1)[1]
    src = p.add_argument_group("sequences (KITTI with --root and --seq, and/or synthetic with --synth)")
    src.add_argument("--root", type=Path, help=f"KITTI odometry root (sequences/, poses/); default ${ROOT_ENV}")
    src.add_argument("--seq", nargs="+", default=[], metavar="SEQ", help="sequences under --root, e.g. 00 04")
    src.add_argument(
        "--synth", nargs="+", type=Path, default=[], metavar="DIR",
        help="synthetic town output: a root holding sequences/* (all are run) or one sequences/NAME folder",
    )
    src.add_argument("--frames", metavar="A:B",
                     help="run frames A..B-1 of every sequence (default: all); with --twins, the twins' range")
    add_source_arguments(p)
    twins = p.add_argument_group("KITTI twins (synthetic sequences driven along KITTI's trajectories)")
    twins.add_argument("--twins", metavar="00-10", help="twins to generate (if missing) and run, e.g. 00-10 or 01,05")
    twins.add_argument("--kitti-poses", type=Path, metavar="DIR", help="folder of the KITTI pose files NN.txt")
    twins.add_argument("--twin-root", type=Path, default=Path("data/twins"),
                       help="where the twins are kept (default: %(default)s)")
    twins.add_argument("--twin-seed", type=int, default=0, help="world seed of the twins (default: 0)")
    twins.add_argument("--traffic", type=int, default=None, metavar="N",
                       help="moving cars per twin (default: one per 60 m of path)")
    twins.add_argument("--lidar", default="hdl64", help="lidar model of the twins (default: hdl64)")
    twins.add_argument("--ideal-twins", action="store_true",
                       help="twins with ideal sensors (no camera, lidar or rig imperfections, raw sweeps, KITTI "
                            "00-02's calibration), as they were generated before the realistic ones")
    p.add_argument(
        "--ablations", default=None, metavar="A,B,...",
        help=f"plvo settings, comma-separated, from {', '.join(ABLATIONS)}; 'none' runs no plvo (default: full; "
             f"with --twins: {TABLE_I_ABLATIONS})",
    )
    p.add_argument("--kiss", action="store_true", help="also run KISS-ICP (lidar only, voxel 1 m) on the same scans")
    p.add_argument("--kiss-slam", action="store_true",
                   help="also run KISS-SLAM (lidar-only SLAM with loop closure, its own defaults) on the same scans")
    p.add_argument("--inline", action="store_true", help="also run each ablation inline (backend.concurrent = "
                   "false), as column <ablation>_inline beside the deployed mode (the default, concurrent workers)")
    p.add_argument("--config", type=Path, help="plvo config TOML the ablations start from (default: built-in)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a plvo config value for every plvo run, e.g. orb.n_features=1500 (repeatable)")
    p.add_argument("--out", type=Path, default=Path("results/eval"), help="output folder (default: %(default)s)")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                   help="local worker processes (or CPUs of a local Ray); 1 runs in this process "
                        "(default: %(default)s)")
    p.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                   help="fan out over Ray: a cluster ADDRESS for ray.init, or 'local' (also the bare flag); a task "
                        "whose node dies is run again on another; the data must be on a path every node sees")
    p.add_argument("--resume", action="store_true", help="keep finished task folders of the same spec, run the rest")
    p.add_argument("--no-plots", action="store_true", help="write the tables only")


def parse_overrides(items: list[str]) -> dict[str, dict[str, object]]:
    """['orb.n_features=1500', ...] -> {'orb': {'n_features': 1500}}; values parsed as Python literals if they can."""
    out: dict[str, dict[str, object]] = {}
    for item in items:
        key, sep, text = item.partition("=")
        section, dot, name = key.strip().partition(".")
        if not sep or not dot or not section or not name:
            raise PlvoError(f"--set {item!r}: expected SECTION.KEY=VALUE, e.g. orb.n_features=1500")
        lowered = text.strip().lower()
        if lowered in ("true", "false"):
            value: object = lowered == "true"
        else:
            try:
                value = ast.literal_eval(text.strip())
            except (ValueError, SyntaxError):
                value = text.strip()
        out.setdefault(section, {})[name] = value
    return out


def synth_sources(paths: list[Path], frames: str | None) -> list[SequenceSource]:
    """--synth folders -> sources: a root's sequences/* (sorted), or a sequences/NAME folder itself."""
    sources = []
    for path in paths:
        if (path / "sequences").is_dir():
            names = sorted(d.name for d in (path / "sequences").iterdir() if d.is_dir() and not d.name.startswith("."))
            if not names:
                raise PlvoError(f"--synth {path}: no sequence folder under {path / 'sequences'}")
            sources += [SequenceSource(str(path.resolve()), n, frames) for n in names]
        elif path.parent.name == "sequences" and path.is_dir():
            sources.append(SequenceSource(str(path.parent.parent.resolve()), path.name, frames))
        else:
            raise PlvoError(f"--synth {path}: neither a root with sequences/ nor a sequences/NAME folder")
    return sources


def _label(sources: list[SequenceSource]) -> list[SequenceSource]:
    """Give every source a distinct table label: its name, prefixed with its root's name when names clash."""
    names = [s.sequence for s in sources]
    out = []
    for s in sources:
        label = s.sequence if names.count(s.sequence) == 1 else f"{Path(s.root or '').name}/{s.sequence}"
        out.append(replace(s, label=label.replace("/", "_")))
    return out


def gather_sources(args: argparse.Namespace) -> list[SequenceSource]:
    if args.frames:
        from plvo.data.registry import parse_frames  # the dataset readers: imported when a run starts

        parse_frames(args.frames)  # fail early on a bad range
    sources = []
    from plvo.data.folder import is_folder
    from plvo.data.rosbag import is_bag

    extra = dict(camera=args.camera, image_topic=args.image_topic, cloud_topic=args.cloud_topic,
                 calib=None if args.calib is None else str(Path(args.calib).resolve()), max_pair_dt=args.max_pair_dt,
                 lidar_elevation_offset_deg=args.lidar_elevation_offset, beams=args.beams)
    if args.root is not None and (is_bag(args.root) or is_folder(args.root)):  # a recording: one sequence
        name = args.root.stem if args.root.is_file() else args.root.resolve().name
        sources.append(SequenceSource(str(args.root.resolve()), name, args.frames, **extra))
    elif args.seq:
        root = args.root if args.root is not None else os.environ.get(ROOT_ENV)
        if not root:
            raise PlvoError(f"--seq {' '.join(args.seq)}: give --root or set ${ROOT_ENV}")
        sources += [SequenceSource(str(Path(root).resolve()), s, args.frames, **extra) for s in args.seq]
    elif args.root is not None:
        raise PlvoError("--root given without --seq: name the sequences to run, e.g. --seq 00 04")
    sources += [replace(s, **extra) for s in synth_sources(args.synth, args.frames)]
    twins = getattr(args, "twins", None)
    if not sources and not twins:
        raise PlvoError("no sequence to run: give --root DIR --seq 04 ..., --synth DIR or --twins 00-10")
    return _label(sources) if sources else []  # the --twins sources come after the checks (twin_sources)


def twin_sources(args: argparse.Namespace) -> list[SequenceSource]:
    """Generate the --twins that are missing or stale under --twin-root (in parallel, with a progress bar), then
    one source per twin, labelled twinNN."""
    from plvo_app.twin_progress import twin_progress
    from plvo_synth.twin.batch import ensure_twins, parse_twins, twin_jobs
    from plvo_synth.twin.generate import TwinSettings

    if args.kitti_poses is None:
        raise PlvoError("--twins: give --kitti-poses DIR (the folder of KITTI pose files 00.txt ... 10.txt)")
    from plvo_synth.twin.realism import IDEAL, REALISTIC

    base = TwinSettings("", args.frames, args.twin_seed, args.traffic, args.lidar,
                        realism=IDEAL if args.ideal_twins else REALISTIC)
    jobs = twin_jobs(parse_twins(args.twins), args.kitti_poses, base)
    from plvo_app.terminal import progress_enabled

    with twin_progress("twins", bar=progress_enabled(), lines=sys.stderr) as (progress, on_done):
        done = ensure_twins(jobs, args.twin_root, workers=args.workers, ray=args.ray, progress=progress,
                            on_done=on_done)
    failed = [d for d in done if d.error]
    if failed:
        raise PlvoError(f"twin {failed[0].sequence}: generation failed: {failed[0].error}")
    root = str(args.twin_root.resolve())
    return [SequenceSource(root, j.sequence, None, f"twin{j.sequence}") for j in jobs]


def parse_ablations(text: str) -> list[str]:
    names = [a.strip() for a in text.split(",") if a.strip()]
    if names == ["none"]:
        return []
    bad = [a for a in names if a not in ABLATIONS]
    if bad:
        raise PlvoError(f"--ablations: unknown {bad[0]!r} (choose from {', '.join(ABLATIONS)}, or none)")
    return list(dict.fromkeys(names))


def _progress(total: int):
    done = [0]

    def report(r: TaskResult) -> None:
        done[0] += 1
        figure = ""
        if r.ok and r.metrics:
            figure = f"short t_err {r.metrics.get('short_t_err_pct') or float('nan'):.2f} %"
        if r.ok and "loop_closures" in r.details:
            figure += f" ({r.details['loop_closures']} loop closures)"
        state = "ok" if r.ok else "FAILED: " + (r.error.splitlines()[0] if r.error else "?")
        print(f"[{done[0]}/{total}] {r.spec.setting} / {r.spec.source.name}: {state} {figure}", file=sys.stderr)

    return report


def run_run(args: argparse.Namespace) -> int:
    """Build the specs, fan them out, write the report; exit 1 when a task failed (the tables are written)."""
    started = provenance.start()  # report.json's provenance: the load as the runs begin
    if args.workers < 1:
        raise PlvoError(f"--workers {args.workers}: must be at least 1")
    if args.out.exists() and not args.out.is_dir():
        raise OutputError(f"--out {args.out}: is a file, not an output folder")
    if not args.resume:  # --resume keeps the finished task folders and writes the report anew
        refuse_existing([args.out / "report.json", args.out / "runs"], "plvo eval run",
                        "--resume continues that evaluation; or choose another --out")
    twins = getattr(args, "twins", None)
    if args.ablations is None:
        args.ablations = TABLE_I_ABLATIONS if twins else "full"
    if twins:
        args.kiss = args.kiss_slam = True  # Table I on the twins: KISS-ICP and KISS-SLAM beside the ablations
    sources = gather_sources(args)
    ablations = parse_ablations(args.ablations)
    if not ablations and not args.kiss and not args.kiss_slam:
        raise PlvoError("nothing to run: --ablations none and neither --kiss nor --kiss-slam")
    if twins:
        sources += twin_sources(args)  # generates what is missing: after every cheap check
    config = str(args.config.resolve()) if args.config else None
    specs = build_specs(sources, ablations, args.kiss, parse_overrides(args.set), config, KissOptions(),
                        inline=args.inline, kiss_slam=args.kiss_slam)
    specs = with_threads(specs, kiss_threads(args.workers, args.ray))
    results = execute(specs, args.out, workers=args.workers, ray=args.ray, resume=args.resume,
                      on_result=_progress(len(specs)))
    report = build_report(results)
    paths = write_report(report, args.out, plots=not args.no_plots, started=started)
    print(report_markdown(report))
    plots = "" if args.no_plots else f", plots in {args.out / 'plots'}"
    print(f"wrote {paths['markdown']} and {paths['json']}{plots}")
    return 0 if all(r.ok for r in results) else 1
