"""Run the pipeline on a sequence, streaming every stage to a Rerun recording and a viser web viewer.

With no --root and no $KITTI_ROOT it runs the synthetic town (plvo.data.synth, generated once and cached under
$PLVO_CACHE or ~/.cache/plvo). Outputs (never overwriting an earlier run): recordings/<seq>_<time>.rrd and
results/<seq>_<time>/ with poses.txt (cam0, first frame at identity; KITTI format, or TUM with the data's
timestamps under --format tum; written only when the run completed), config.toml (the resolved config) and
timings.json. --root also takes a ROS 1 .bag, a ROS 2 bag folder or .mcap, or a plain images/ + scans/ folder.
Ctrl-C stops the run, closes the recording (readable, stamped "interrupted") and marks timings.json likewise.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from plvo.atomic import write_text_atomic
from plvo.config import ABLATIONS, SystemConfig, config_to_dict, config_to_toml, load_config, save_config, with_ablation
from plvo.errors import DatasetError, RecordingError
from plvo.recording import FanOut, RunInfo
from plvo_app.source_args import add_source_arguments, source_options

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--root", type=Path, help="dataset root (KITTI odometry or raw layout), a ROS bag (.bag, ROS 2 "
                   "folder, .mcap) or a plain images/ + scans/ folder; default $KITTI_ROOT, else the embedded "
                   "synthetic town")
    p.add_argument("--seq", default=None, help="odometry sequence (04) or raw drive (2011_09_26_drive_0009); "
                   "default 00 with a root")
    p.add_argument("--frames", default=None, metavar="A:B", help="frames A to B-1 (e.g. 0:100); default all")
    p.add_argument("--config", type=Path, help="TOML config overriding the paper's defaults")
    p.add_argument("--ablation", default=None, help=f"one of {', '.join(ABLATIONS)}")
    p.add_argument("--rrd", type=Path, help="recording path; default recordings/<seq>_<time>.rrd")
    p.add_argument("--out", type=Path, help="results folder; default results/<seq>_<time>/")
    p.add_argument("--no-serve", action="store_true", help="do not start the viser web viewer")
    p.add_argument("--port", type=int, default=8080, help="viser port on 127.0.0.1 (default 8080)")
    p.add_argument("--replay", type=Path, metavar="FILE.rrd", help="show a saved recording instead of running")
    p.add_argument("--format", choices=("kitti", "tum"), default="kitti",
                   help="poses.txt format: kitti (12 numbers a line) or tum (time tx ty tz qx qy qz qw, the data's "
                        "timestamps); default kitti")
    add_source_arguments(p)


def git_revision() -> str:
    """The git revision of the plvo checkout ('+dirty' with local changes), or 'unknown' when not in git."""
    repo = Path(__file__).resolve().parents[1]
    try:
        rev = subprocess.run(["git", "-C", str(repo), "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True, timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return rev + ("+dirty" if dirty else "")


def plvo_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("plvo")
    except PackageNotFoundError:
        return "unknown"


def _resolve_config(args: argparse.Namespace) -> SystemConfig:
    cfg = load_config(args.config)
    return with_ablation(cfg, args.ablation) if args.ablation else cfg


def _open(args: argparse.Namespace):
    """(dataset, run label): the dataset named by --root/$KITTI_ROOT and --seq, or the synthetic town ("town00")
    when no dataset is given."""
    from plvo.data.registry import ROOT_ENV, open_dataset, parse_frames

    frames = parse_frames(args.frames) if args.frames else None
    if args.root is None and not os.environ.get(ROOT_ENV) and args.seq is None:
        root, seq = _synthetic_town()
        return open_dataset(root, seq, frames), f"town{seq}"
    dataset = open_dataset(args.root, args.seq or "00", frames, camera=args.camera, options=source_options(args))
    return dataset, dataset.sequence


def _synthetic_town() -> tuple[Path, str]:
    """(root, sequence) of the default synthetic town, generated once into the cache (with a progress bar)."""
    from plvo.data.registry import ROOT_ENV

    try:
        from plvo.data.synth import DEFAULT_SEQUENCE, DEFAULT_SETTINGS, default_sequence_root
        from plvo.data.synth.cache import cache_dir, settings_hash
    except ImportError:
        raise DatasetError(f"no dataset: give --root DIR or set ${ROOT_ENV} (the synthetic town is not "
                           "available in this build)") from None
    st = DEFAULT_SETTINGS
    where = cache_dir() / settings_hash(st, DEFAULT_SEQUENCE)
    cached = (where / "sequences" / DEFAULT_SEQUENCE / "calib.txt").is_file()
    print(f"no --root and no ${ROOT_ENV}: running the synthetic town (sequence {DEFAULT_SEQUENCE}, {st.n_frames} "
          f"frames at {st.speed_mps:g} m/s{', with a loop' if st.loop else ''}), "
          f"{'cached in' if cached else 'generated once (a few minutes) into'} {where}", file=sys.stderr)
    if cached:
        return Path(default_sequence_root()), DEFAULT_SEQUENCE
    from tqdm import tqdm

    with tqdm(total=st.n_frames, unit="frame", desc="synthetic town", dynamic_ncols=True) as bar:
        def progress(done: int, total: int) -> None:
            bar.update(done - bar.n)

        return Path(default_sequence_root(progress)), DEFAULT_SEQUENCE


def _unique(path: Path) -> Path:
    """`path`, or path with -2, -3... appended to its stem when taken."""
    candidate, n = path, 2
    while candidate.exists():
        candidate = path.with_name(f"{path.stem}-{n}{path.suffix}")
        n += 1
    return candidate


@dataclass(frozen=True)
class Outputs:
    run: str
    rrd: Path
    out: Path


def _outputs(args: argparse.Namespace, sequence: str) -> Outputs:
    run = f"{sequence}_{time.strftime('%Y%m%d-%H%M%S')}"
    if args.rrd is not None and args.rrd.exists():
        raise RecordingError(f"{args.rrd}: already exists; plvo-viz never overwrites a recording")
    if args.out is not None and args.out.exists() and any(args.out.iterdir()):
        raise RecordingError(f"{args.out}: results folder exists and is not empty; choose another --out")
    rrd = args.rrd or _unique(Path("recordings") / f"{run}.rrd")
    out = args.out or _unique(Path("results") / run)
    return Outputs(rrd.stem if args.rrd else run, rrd, out)


def _write_results(out: Path, system, cfg: SystemConfig, status: str, fps: float, dataset,
                   fmt: str = "kitti") -> None:
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.toml")
    timings = {"status": status, "frames_done": system.frames_done, "frames_total": len(dataset),
               "frames_per_second": fps, "stages": system.timing_summary(),
               "per_frame_ms": {k: [round(1e3 * v, 3) for v in vals] for k, vals in system.timings.items()}}
    write_text_atomic(out / "timings.json", json.dumps(timings, indent=1) + "\n")
    if status == "complete":
        from plvo.data.trajectory import write_poses
        write_poses(out / "poses.txt", system.poses_cam0(dataset.frame_indices), dataset.times, fmt)


def _run_frames(system, dataset) -> None:
    """Step through the dataset (each frame read while the previous one is tracked) with a progress bar, then let
    the workers finish. Ctrl-C propagates."""
    from tqdm import tqdm

    from plvo.data.prefetch import prefetched

    with tqdm(total=len(dataset), unit="frame", desc=dataset.sequence, dynamic_ncols=True) as bar:
        for frame in prefetched(dataset):
            system.step(frame)
            bar.update(1)
    system.finish()  # the back end and loop closer finish their keyframes; their results are recorded


def run(args: argparse.Namespace) -> int:
    if args.replay is not None:
        from plvo_app.cmd_view import view

        return view(args.replay, port=args.port, serve=not args.no_serve)
    from plvo.system import System
    from plvo_app.rerun_recorder import RerunRecorder

    cfg = _resolve_config(args)
    dataset, label = _open(args)
    outs = _outputs(args, label)
    info = RunInfo(
        name=outs.run, sequence=dataset.sequence, calib=dataset.calib, frame_indices=dataset.frame_indices,
        gt_T_world_cam=dataset.gt_T_world_cam, config=config_to_dict(cfg), version=plvo_version(),
        git_revision=git_revision(), command_line=shlex.join(["plvo-viz", *sys.argv[1:]]),
        extra={"config_toml": config_to_toml(cfg)})
    recorders, viewer = [RerunRecorder(outs.rrd)], None
    if not args.no_serve:
        from plvo_app.viser_viewer import SceneStore, ViserRecorder, ViserViewer, serve_until_interrupted

        viewer = ViserViewer(SceneStore(), port=args.port, live=True)
        recorders.append(ViserRecorder(viewer))
        print(f"viser viewer: http://127.0.0.1:{viewer.port}", file=sys.stderr)
    system = System(cfg, FanOut(recorders))
    system.start(info)
    status, fps = "interrupted", 0.0
    t0 = time.perf_counter()
    try:
        _run_frames(system, dataset)
        status = "complete"
    except KeyboardInterrupt:
        print(f"interrupted after {system.frames_done} of {len(dataset)} frames; keeping what was recorded",
              file=sys.stderr)
    except BaseException:
        status = "failed"
        raise
    finally:
        # What a user waits for: every frame read, tracked and recorded, and the workers' last results applied.
        fps = system.frames_done / max(time.perf_counter() - t0, 1e-9)
        recorders[0].set_status(status, system.frames_done)
        system.close()
        _write_results(outs.out, system, cfg, status, fps, dataset, args.format)
    print(f"recording: {outs.rrd}\nresults:   {outs.out}/", file=sys.stderr)
    if status != "complete":
        if viewer is not None:
            viewer.close()
        return 130
    if viewer is not None:
        serve_until_interrupted(viewer, "serving the run")
    return 0
