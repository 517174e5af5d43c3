"""Time plvo's stages and the whole system on KITTI-sized input; write the figures as JSON.

Per stage (stable names): features (ORB + LSD + repair + LBD) and its parts features_orb, features_lsd,
features_repair, features_lbd, features_1241x376 (the budget's image size), matching, depth, registration,
measured on their own; pnpl, matching_pnpl, scale_correction, bundle_adjustment, scale_correction_ba, backend,
loop_query, loop_verify, loop_correct, loop_apply, loop_global_ba, loop, as the System records them in a whole
run (the loop correction stages over accepted loops only: bench a sequence with a revisit for them). Each has n,
median_ms, p90_ms, mean_ms, max_ms and the design's budget with within_budget (median). The whole system: frames
a second with recording off and with a Rerun recording on (the overhead in %, .rrd bytes a frame); peak memory; the
machine, its load average and thread settings, library versions, git revision and command line.

Default input: the real frames of KITTI odometry sequence 04 in ../shared/data/kitti (or $KITTI_ROOT), else the
first 51 frames of the embedded synthetic town. Example:
  plvo bench --root ../shared/data/kitti --seq 04 --out results/bench/04.json
  plvo bench --stages features,matching --frames 0:10
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import shlex
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING

from plvo.atomic import write_text_atomic
from plvo.config import config_to_dict, load_config
from plvo.errors import DatasetError, OutputError
from plvo_app.run_outputs import refuse_existing
from plvo_app.source_args import add_source_arguments, source_options
from plvo_eval import provenance

if TYPE_CHECKING:
    from plvo.recording import RunInfo

# plvo_eval.bench (numpy, the pipeline) is imported when the bench runs: `plvo bench --help` answers at once
log = logging.getLogger(__name__)
# plvo_eval.bench.STAGE_GROUPS, named here for --help (tests/plvo_app/test_terminal.py checks that the two agree)
STAGE_GROUPS = ("features", "matching", "depth", "registration", "backend", "loop", "system")

REPO = Path(__file__).resolve().parents[1]
SHARED_KITTI = REPO.parent / "shared" / "data" / "kitti"
SYNTH_DEFAULT_FRAMES = "0:51"  # as many as the shared real frames
THREAD_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENCV_FOR_THREADS_NUM")
VERSION_OF = {"plvo": "plvo", "numpy": "numpy", "scipy": "scipy", "opencv": "opencv-contrib-python-headless",
              "open3d": "open3d", "gtsam": "gtsam", "poselib": "poselib", "rerun": "rerun-sdk", "psutil": "psutil"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = __doc__.strip()
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    src = p.add_mutually_exclusive_group()
    src.add_argument("--root", type=Path, help="KITTI root (sequences/NN); default $KITTI_ROOT, else "
                     "../shared/data/kitti beside the repository, else the synthetic town")
    src.add_argument("--synth", type=Path, metavar="DIR", help="a synthetic sequence root written by `plvo synth`")
    p.add_argument("--seq", default=None, help="sequence (default 04 for KITTI, the first one under --synth)")
    p.add_argument("--frames", default=None, metavar="A:B", help="frames A to B-1 (default all; synthetic: 0:51)")
    p.add_argument("--out", type=Path, metavar="FILE.json", help="where to write the JSON "
                   "(default results/bench/<seq>_<time>.json)")
    p.add_argument("--repeat", type=int, default=1, metavar="N", help="time each stage N times a frame and run "
                   "the whole system N times each way (default 1)")
    p.add_argument("--stages", default="all", help=f"all, or a comma list of {','.join(STAGE_GROUPS)}; "
                   "backend, loop and system run the whole system (system also with recording on)")
    p.add_argument("--config", type=Path, help="TOML config overriding the paper's defaults")
    p.add_argument("--soak", action="store_true", help="instead: one whole run of the sequence as plvo-viz runs it "
                   "(recording on), reporting per 100-frame window frames a second, memory, recording size and pose "
                   "error, and per run the loops, corrections and losses (plvo_eval.soak); e.g. --synth DIR --seq 40 "
                   "of `plvo synth --out DIR --seq 40 --frames 4541 --seed 7 --speed 11 --loop --stops`")
    add_source_arguments(p)


def _open(args: argparse.Namespace):
    """(dataset, its root) the arguments name; see add_arguments for the defaults."""
    from plvo.data.registry import ROOT_ENV, open_dataset, parse_frames

    frames = parse_frames(args.frames) if args.frames else None
    source = dict(camera=args.camera, options=source_options(args))
    if args.synth is not None:
        if not (args.synth / "sequences").is_dir():
            raise DatasetError(f"--synth {args.synth}: no sequences/ folder (write one with `plvo synth --out DIR`)")
        seq = args.seq or sorted(q.name for q in (args.synth / "sequences").iterdir())[0]
        return open_dataset(args.synth, seq, frames), args.synth
    if args.root is not None or os.environ.get(ROOT_ENV):
        root = args.root or Path(os.environ[ROOT_ENV])
        return open_dataset(root, args.seq or "04", frames, **source), root
    if (SHARED_KITTI / "sequences" / (args.seq or "04")).is_dir():
        return open_dataset(SHARED_KITTI, args.seq or "04", frames, **source), SHARED_KITTI
    from plvo_synth import DEFAULT_SEQUENCE, default_sequence_root

    log.info("no KITTI frames found: benchmarking the synthetic town (generated on first use)")
    root = default_sequence_root()
    return open_dataset(root, DEFAULT_SEQUENCE, frames or parse_frames(SYNTH_DEFAULT_FRAMES)), root


def machine_info() -> dict:
    """CPU model, core counts, memory, load average now, thread settings (environment and OpenCV's)."""
    import cv2
    import psutil

    return {"cpu_model": provenance.cpu_model(), "cpu_count": os.cpu_count(),
            "cpu_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
            "mem_total_mb": round(psutil.virtual_memory().total / 2**20), "platform": platform.platform(),
            "python": platform.python_version(), "load_avg_start": [round(x, 2) for x in os.getloadavg()],
            "threads": {**{k: os.environ.get(k) for k in THREAD_ENV}, "opencv_num_threads": cv2.getNumThreads()}}


def versions() -> dict[str, str | None]:
    """Installed versions of plvo and of the libraries that set its speed."""
    out: dict[str, str | None] = {}
    for key, dist in VERSION_OF.items():
        try:
            out[key] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[key] = None
    return out


class RerunFactory:
    """run -> (a RerunRecorder writing folder/bench_<run>.rrd, that path); picklable, so that a deployed run can make
    its recorder in a fresh process (plvo_eval.bench.deployed_figures)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)

    def __call__(self, run: int):
        from plvo_app.rerun_recorder import RerunRecorder

        path = self.folder / f"bench_{run}.rrd"
        return RerunRecorder(path), path


class Reopen:
    """Opens the dataset the arguments name again (picklable: for the deployed runs' fresh processes)."""

    def __init__(self, args: argparse.Namespace):
        self.args = args

    def __call__(self):
        return _open(self.args)[0]


def run_bench(*args, **kwargs) -> dict:
    """plvo_eval.bench.run_bench, imported when called (a name of this module, as it was: a test replaces it)."""
    from plvo_eval.bench import run_bench as run_bench_

    return run_bench_(*args, **kwargs)


def run(args: argparse.Namespace) -> int:
    from plvo_app.cmd_viz import run_info
    from plvo_eval.bench import parse_stages

    stages = parse_stages(args.stages)  # bad arguments fail before any work
    if args.out is not None and args.out.is_dir():
        raise OutputError(f"--out {args.out}: is a folder; give the JSON file's name (e.g. {args.out / 'bench.json'})")
    cfg = load_config(args.config)
    dataset, root = _open(args)
    kind = "soak_" if args.soak else ""
    out = args.out or Path("results") / "bench" / f"{kind}{dataset.sequence}_{time.strftime('%Y%m%d-%H%M%S')}.json"
    refuse_existing([out], "plvo bench", "choose another --out")  # before the minutes of timing
    machine = machine_info()
    command = shlex.join(sys.argv)
    info = run_info("bench", dataset, cfg, command)
    if args.soak:
        return _soak(args, cfg, dataset, info, machine, command, out)
    with tempfile.TemporaryDirectory(prefix="plvo-bench-") as tmp:
        report = run_bench(dataset, cfg, stages, args.repeat, RerunFactory(Path(tmp)), info, Reopen(args))
    if "system" in stages:
        from plvo_app.level_sizes import measure_levels

        log.info("bench: one more run, recorded at every level side by side (bytes a frame per level)")
        report["recording_levels"] = measure_levels(dataset, cfg, len(dataset))
    machine["load_avg_end"] = [round(x, 2) for x in os.getloadavg()]
    options = {k: str(v) if isinstance(v, Path) else v for k, v in sorted(vars(args).items())}
    head = {"schema": report["schema"], "created_utc": report["created_utc"], "command_line": command,
            "options": options, "git_revision": info.git_revision, "versions": versions(), "machine": machine,
            "provenance": provenance.finish(report["provenance"])}  # its end: after the recording levels' run
    report = {**head, **report, "input": {**report["input"], "root": str(root)}}
    write_text_atomic(out, json.dumps(_finite(report), indent=1, allow_nan=False) + "\n")
    print(format_table(report))
    print(f"written: {out}")
    return 0


def _soak(args: argparse.Namespace, cfg, dataset, info: RunInfo, machine: dict, command: str, out: Path) -> int:
    """`plvo bench --soak`: the whole sequence as plvo-viz runs it; the JSON of plvo_eval.soak."""
    from tqdm import tqdm

    from plvo_app.rerun_recorder import RerunRecorder
    from plvo_app.terminal import progress_enabled
    from plvo_eval.soak import run_soak

    with tempfile.TemporaryDirectory(prefix="plvo-soak-") as tmp:
        rrd = Path(tmp) / "soak.rrd"
        with tqdm(total=len(dataset), unit="frame", desc=f"soak {dataset.sequence}", dynamic_ncols=True,
                  disable=not progress_enabled()) as bar:
            report = run_soak(dataset, cfg, RerunRecorder(rrd), info, rrd, progress=bar.update)
    machine["load_avg_end"] = [round(x, 2) for x in os.getloadavg()]
    report = {"command_line": command, "git_revision": info.git_revision, "versions": versions(),
              "machine": machine, "input": {"sequence": dataset.sequence, "frames": len(dataset)}, **report,
              "config": config_to_dict(cfg), "provenance": provenance.finish(report["provenance"])}
    write_text_atomic(out, json.dumps(_finite(report), indent=1, allow_nan=False) + "\n")
    f = report.get("final") or {}
    print(f"soak {dataset.sequence}: {report['fps']:.2f} frames/s overall, windows median "
          f"{report['fps_window_median']} "
          f"worst {report['fps_window_worst']}; RSS {report['rss_mb_at']}; ATE {f.get('ate_m')} m, "
          f"devkit {f.get('t_err_pct')} %; recording {report['recording']['bytes']} bytes")
    print(f"written: {out}")
    return 0


def _finite(obj):
    """NaN and infinities become null: the file stays strict JSON."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _fig(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"


def format_table(report: dict) -> str:
    """A short human summary of a bench report."""
    m, inp = report["machine"], report["input"]
    lines = [f"plvo bench: {inp['dataset']} {inp['sequence']} frames {inp['frames']} ({inp['image_size'][0]}x"
             f"{inp['image_size'][1]}, ~{inp['scan_points_median']} scan points); {m['cpu_model']}, "
             f"{m['cpu_count']} cores, load {m['load_avg_start'][0]:.1f} -> {m['load_avg_end'][0]:.1f}",
             f"{'stage':22s} {'source':8s} {'n':>4s} {'median':>8s} {'p90':>8s} {'max':>8s} {'budget':>7s}  ok"]
    for name, s in report["stages"].items():
        ok = {None: "", True: "yes", False: "NO"}[s["within_budget"]]
        lines.append(f"{name:22s} {s['source']:8s} {s['n']:4d} {_ms(s['median_ms']):>8s} {_ms(s['p90_ms']):>8s} "
                     f"{_ms(s['max_ms']):>8s} {_ms(s['budget_ms']):>7s}  {ok}")
    sysfig = report.get("system")
    if sysfig:
        off = sysfig["recording_off"]
        lines.append(f"whole system, recording off: {off['fps']:.2f} frames/s (budget >= {off['fps_budget']:g})")
        on = sysfig.get("recording_on")
        if on:
            lines.append(f"whole system, recording on:  {on['fps']:.2f} frames/s, overhead "
                         f"{sysfig.get('recording_overhead_pct', float('nan')):.1f} % (budget <= "
                         f"{sysfig.get('recording_overhead_budget_pct', 25):g} %), "
                         f"{on['rrd_bytes_per_frame'] or 0:,} bytes of .rrd a frame")
    dep = report.get("deployed")
    if dep:
        lines.append(f"deployed (as plvo-viz: from disk, recording on): {dep['fps']:.2f} frames/s, set-up "
                     f"{dep['setup_s']:.2f} s; KISS-ICP on the same scans: {_fig(dep['kiss_icp_fps'])} frames/s, "
                     f"set-up {_fig(dep['kiss_icp_setup_s'])} s; ratio, run by run, median "
                     f"{_fig(dep['ratio_to_kiss_icp'])} (medians of {len(dep['pairs'])} runs)")
        ci = dep.get("ratio_to_kiss_icp_interval")
        if ci:
            lines.append(f"  ratio's geometric mean {ci['geomean']:.3f}, {100 * ci['level']:.0f} % bootstrap interval "
                         f"{ci['low']:.3f}-{ci['high']:.3f}")
        for n, p in enumerate(dep["pairs"]):
            lines.append(f"  run {n + 1}: plvo {p['plvo_fps']:.2f} frames/s (set-up {p['plvo_setup_s']:.2f} s), "
                         f"KISS-ICP {_fig(p['kiss_icp_fps'])} frames/s (set-up {_fig(p['kiss_icp_setup_s'])} s), "
                         f"ratio {_fig(p['ratio'])}")
    levels = report.get("recording_levels")
    if levels:
        lines.append("recording, bytes a frame: " + ", ".join(
            f"{lv} {v.get('bytes_per_frame', 0):,.0f}" for lv, v in levels.items()))
    mem = report["memory"]
    lines.append(f"peak memory: {mem['ru_maxrss_mb']:.0f} MB (ru_maxrss), {mem['sampled_peak_mb']:.0f} MB sampled; "
                 f"bench took {report['duration_s']:.0f} s")
    return "\n".join(lines)
