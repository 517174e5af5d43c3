"""Run the pipeline on a sequence, streaming every stage to a Rerun recording and a viser web viewer.

With no --root and no $KITTI_ROOT it runs the synthetic town (plvo_synth, generated once and cached under
$PLVO_CACHE or ~/.cache/plvo). Outputs (never overwriting an earlier run): recordings/<seq>_<time>.rrd and
results/<seq>_<time>/ with poses.txt (cam0, first frame at identity; KITTI format, or TUM with the data's
timestamps under --format tum; written only when the run completed), truth.txt (the data's ground truth of the same
frames, alike, where it has one), summary.json (how the run ended, its speed and, with truth, its accuracy: also
the terminal's last lines), config.toml (the resolved config) and timings.json; results/latest links the newest.
A run that starts again from its first frame (a camera-lidar time offset found, docs/crosscheck.md) keeps the
recording of the frames before beside its own, as <name>-before-restart.rrd.
--root also takes a ROS 1 .bag, a ROS 2 bag folder or .mcap, or a plain images/ + scans/ folder.
Ctrl-C, SIGTERM or SIGHUP (a closed terminal) stops the run, closes the recording (readable, stamped "interrupted")
and marks timings.json likewise; a run that fails (a write, a worker, an unexpected error) or tracks less than half
its frames is marked "failed" with its reason and says so on one line. Output nobody reads any more (a closed
terminal, `| head`) is dropped and the run goes on. The faults and what each leaves: docs/faults.md.
"""

# The pipeline, the datasets and the viewers (gtsam, open3d, rerun, viser: plvo.runtime.system alone imports in ~1 s)
#  are imported inside the functions that use them: `plvo --help` imports every command module.
from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import shlex
import subprocess
import sys
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from plvo.config import (
    ABLATIONS,
    SystemConfig,
    config_from_dict,
    config_to_dict,
    config_to_toml,
    load_config,
    save_config,
    with_ablation,
)
from plvo.errors import DatasetError, OutputError, PlvoError, RecordingError, RunFailed
from plvo.recording import FanOut, RunInfo
from plvo_app.guards import check_port, deferred_signals, exit_status_of, limit_reached, signal_name
from plvo_app.run_outputs import (
    MIN_TRACKED_SHARE,
    Outputs,
    RunEnd,
    RunLog,
    check_outputs,
    remove_made,
    tracked_summary,
    write_json,
)
from plvo_app.run_summary import POSES_FILE, SUMMARY_FILE, TRUTH_FILE, point_latest, summary_lines
from plvo_app.source_args import add_source_arguments
from plvo_app.terminal import progress_enabled
from plvo_app.viz_options import VizOptions

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--root", type=Path, help="dataset root (KITTI odometry or raw layout), a ROS bag (.bag, ROS 2 "
                   "folder, .mcap) or a plain images/ + scans/ folder; default $KITTI_ROOT, else the embedded "
                   "synthetic town")
    p.add_argument("--seq", default=None, help="odometry sequence (04) or raw drive (2011_09_26_drive_0009); "
                   "with a root alone, its only sequence (several are listed)")
    p.add_argument("--frames", default=None, metavar="A:B", help="frames A to B-1 (e.g. 0:100); default all")
    p.add_argument("--config", type=Path, help="TOML config overriding the paper's defaults")
    p.add_argument("--ablation", default=None, help=f"one of {', '.join(ABLATIONS)}")
    p.add_argument("--time-offset", type=float, default=None, metavar="S",
                   help="the lidar's scans are taken S seconds after the images (negative: before); each scan is "
                        "moved to its image's instant (crosscheck.time_offset_s; a run names an offset it finds)")
    p.add_argument("--rrd", type=Path, help="recording path; default recordings/<seq>_<time>.rrd")
    p.add_argument("--out", type=Path, help="results folder; default results/<seq>_<time>/")
    p.add_argument("--no-serve", action="store_true", help="do not start the viser web viewer")
    p.add_argument("--port", type=int, default=8080, help="viser port on 127.0.0.1 (default 8080)")
    p.add_argument("--replay", type=Path, metavar="FILE.rrd", help="show a saved recording instead of running")
    p.add_argument("--format", choices=("kitti", "tum"), default="kitti",
                   help="poses.txt format: kitti (12 numbers a line) or tum (time tx ty tz qx qy qz qw, the data's "
                        "timestamps); default kitti")
    add_source_arguments(p)
    p.add_argument("--record", default="default", choices=("summary", "default", "full"),
                   help="recording level: summary (the whole-run picture), default (plus full detail on every 100th "
                   "keyframe and around events: tracking lost, loops, discarded optimisations, large corrections, "
                   "slow frames), full (every layer on every frame)")
    p.add_argument("--detail", action="append", default=[], metavar="A:B",
                   help="full detail on frames A to B-1 whatever the level (repeatable)")
    p.add_argument("--embed-inputs", default=None, metavar="A:B",
                   help="embed the raw image and scan of frames A to B-1 (lossless) so that the recording alone "
                   "reproduces them (plvo reproduce); ~2.5 MB a KITTI frame")


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
    try:
        return version("plvo")
    except PackageNotFoundError:
        return "unknown"


def run_info(name: str, dataset, cfg: SystemConfig, command_line: str, /, **extra) -> RunInfo:
    """What the recorders are told of a run: the dataset's sequence, calibration, frames and truth, the config (as
    TOML too), this plvo's version and revision, and the input files, whose digests the recorder keeps frame by frame
    (plvo-viz's and the bench's recorded runs alike); `extra` adds entries (positional parameters above, since
    plvo-viz adds one named "dataset": the source's identity)."""
    from plvo_app.run_identity import input_files

    return RunInfo(
        name=name, sequence=dataset.sequence, calib=dataset.calib, frame_indices=dataset.frame_indices,
        gt_T_world_cam=dataset.gt_T_world_cam, config=config_to_dict(cfg), version=plvo_version(),
        git_revision=git_revision(), command_line=command_line,
        extra={"config_toml": config_to_toml(cfg), **extra, "input_files": input_files(dataset)})


def _resolve_config(opts: VizOptions) -> SystemConfig:
    cfg = load_config(opts.config)
    if opts.time_offset is not None:
        cfg = config_from_dict({**config_to_dict(cfg), "crosscheck": {**config_to_dict(cfg)["crosscheck"],
                                                                     "time_offset_s": opts.time_offset}})
    return with_ablation(cfg, opts.ablation) if opts.ablation else cfg


def _open(opts: VizOptions):
    """(dataset, run label, identity): the dataset named by --root/$KITTI_ROOT and --seq, or the synthetic town
    ("town00") when no dataset is given; identity says where it came from (recorded for plvo reproduce)."""
    from plvo.data.registry import ROOT_ENV, only_sequence, open_dataset
    from plvo_app.run_identity import dataset_identity

    frames = opts.frame_slice
    if opts.root is None and not os.environ.get(ROOT_ENV) and opts.seq is None:
        root, seq = _synthetic_town(frames)
        dataset = open_dataset(root, seq, frames)
        return dataset, f"town{seq}", dataset_identity(dataset, root, opts.frames, synthetic=True)
    root = opts.root if opts.root is not None else os.environ.get(ROOT_ENV)
    seq = opts.seq
    # a bag or plain folder needs no --seq; a dataset root's only sequence runs, several are listed (exit 2)
    if seq is None and root is not None:
        what = "--root" if opts.root is not None else f"${ROOT_ENV}"
        seq = only_sequence(root, what)
        if seq is not None:
            print(f"{what} {root}: running {seq}, the only sequence there", file=sys.stderr)
    dataset = open_dataset(root, seq, frames, camera=opts.camera, options=opts.source)
    return dataset, dataset.sequence, dataset_identity(dataset, root, opts.frames, synthetic=False)


def recorder_options(opts: VizOptions):
    """RerunOptions from --record, --detail and --embed-inputs."""
    from plvo_app.rerun_recorder import RerunOptions

    return RerunOptions(detail=opts.detail, embed_inputs=opts.embed)


def _synthetic_town(frames: slice | None = None) -> tuple[Path, str]:
    """(root, sequence) of the default synthetic town holding the frames asked for (all by default): generated into
    the cache as far as needed (with a progress bar), the cache extended when a later run wants more."""
    from plvo.data.registry import ROOT_ENV

    try:
        from plvo_synth import DEFAULT_SEQUENCE, DEFAULT_SETTINGS, default_sequence_root
        from plvo_synth.cache import cache_dir, cached_frames, settings_hash
    except ImportError:
        raise DatasetError(f"no dataset: give --root DIR or set ${ROOT_ENV} (the synthetic town is not "
                           "available in this build)") from None
    st = DEFAULT_SETTINGS
    stop = st.n_frames
    if frames is not None and frames.stop is not None and frames.stop >= 0 and (frames.step or 1) > 0:
        stop = min(frames.stop, st.n_frames)
    where = cache_dir() / settings_hash(st, DEFAULT_SEQUENCE)
    have = cached_frames(st, DEFAULT_SEQUENCE)
    todo = max(0, stop - have)
    how = (f"cached in {where}" if not todo else
           f"{'generating' if not have else 'adding'} frames {have}..{stop - 1} (~0.15 s each on 2 cores) in {where}")
    print(f"no --root and no ${ROOT_ENV}: running the synthetic town (sequence {DEFAULT_SEQUENCE}, {st.n_frames} "
          f"frames at {st.speed_mps:g} m/s{', with a loop' if st.loop else ''}), {how}; its ground truth: "
          f"{where / 'poses' / (DEFAULT_SEQUENCE + '.txt')}", file=sys.stderr)
    if not todo:
        return Path(default_sequence_root(stop=stop)), DEFAULT_SEQUENCE
    from tqdm import tqdm

    with tqdm(total=todo, unit="frame", desc="synthetic town", dynamic_ncols=True,
              disable=not progress_enabled()) as bar:
        def progress(done: int, total: int) -> None:
            bar.update(done - bar.n)

        return Path(default_sequence_root(progress, stop=stop)), DEFAULT_SEQUENCE


def _claim_folder(path: Path) -> tuple[Path, list[Path]]:
    """The first of path, path-2, path-3... that this process makes itself (mkdir without exist_ok), so that two
    runs started in the same second cannot share a results folder -> (the folder, the folders made, outer first)."""
    made = [p for p in path.parents if not p.exists()][::-1]
    candidate, n = path, 2
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            try:
                candidate.mkdir()
                return candidate, [*made, candidate]
            except FileExistsError:
                candidate = path.with_name(f"{path.name}-{n}")
                n += 1
    except OSError as exc:
        remove_made(made)
        raise OutputError(f"{candidate}: cannot make the results folder ({exc.strerror or exc})") from None


# what a run writes in its results folder
RESULTS_FILES = (POSES_FILE, TRUTH_FILE, SUMMARY_FILE, "timings.json", "config.toml", "run.log")


def _outputs(opts: VizOptions, sequence: str) -> tuple[Outputs, list[Path]]:
    """The run's outputs -> (Outputs, the folders made for them here: the default results folder, claimed)."""
    run = f"{sequence}_{time.strftime('%Y%m%d-%H%M%S')}"
    if opts.rrd is not None and opts.rrd.exists():
        raise RecordingError(f"{opts.rrd}: already exists; plvo-viz never overwrites a recording")
    if opts.out is not None and opts.out.is_dir() and any(opts.out.iterdir()):
        raise RecordingError(f"{opts.out}: results folder exists and is not empty; choose another --out")
    if opts.rrd is not None and opts.out is not None and opts.rrd.name in RESULTS_FILES \
            and opts.rrd.resolve().parent == opts.out.resolve():
        raise OutputError(f"--rrd {opts.rrd}: the run writes its {opts.rrd.name} there, over the recording; name "
                          f"the recording otherwise (e.g. {opts.out / 'run.rrd'})")
    out, made = opts.out, []
    if out is None:
        out, made = _claim_folder(Path("results") / run)
        run = out.name
    # a default recording's name is claimed when the recorder creates it (RrdFileSink, next_free: run-2.rrd...)
    rrd = opts.rrd or Path("recordings") / f"{run}.rrd"
    return Outputs(rrd.stem if opts.rrd else run, rrd, out), made


def _timings(system, status: str, reason: str, fps: float, n_total: int) -> dict:
    tracked, share = tracked_summary(system.frames_done, system.n_lost)
    return {"status": status, "reason": reason, "frames_done": system.frames_done, "frames_total": n_total,
            "frames_tracked": tracked, "tracked_share": round(share, 4), "frames_per_second": fps,
            **system.trust_summary(),
            "stages": system.timing_summary(),
            "per_frame_ms": {k: [round(1e3 * v, 3) for v in vals] for k, vals in system.timings.items()}}


DEGRADED = "degraded"  # complete, but some frames' poses are the motion model's guess (docs/faults.md)
DEGRADED_EXIT = 3


def trust_line(system) -> str:
    """The last line's account of where the poses came from, when not all from the camera: ': 48 by the camera,
    3 by the lidar alone (frozen image 3)'."""
    summary = system.trust_summary()
    by = summary.get("frames_by_source", {})
    if not by or by.get("camera", 0) == system.frames_done:
        return rig_line(summary)
    names = {"camera": "by the camera", "camera, seeded by the lidar": "by the camera from the lidar's motion",
             "lidar": "by the lidar alone", "motion model": "lost (motion model)"}
    parts = [f"{n} {names[k]}" for k, n in by.items() if n]
    findings = ", ".join(f"{k} {n}" for k, n in summary.get("findings", {}).items())
    return ": " + ", ".join(parts) + (f" ({findings}; see the warnings)" if findings else "") + rig_line(summary)


def rig_line(summary: dict) -> str:
    """A found camera-lidar time offset or extrinsic error, as the run's last word on it (empty when none was
    found)."""
    for why in summary.get("restarts", ()):
        reason, out = why.get("reason", "camera-lidar time offset"), ""
        if "time offset" in reason:
            what = "after" if why["time_offset_s"] > 0 else "before"
            out += (f"\ncamera-lidar time offset: the scans are taken {abs(why['time_offset_s']):.3f} s {what} the "
                    f"images (found at frame {why['at_frame']}); the run started again from its first frame with them "
                    "moved to the images' instants")
        if "extrinsic" in reason:
            turn = _angles(why["extrinsic_correction_deg"])
            out += (f"\ncamera-lidar extrinsic: turned by {turn} deg (found at frame {why['at_frame']}); the run "
                    "started again from its first frame with it corrected")
        return out
    out = ""
    found = (summary.get("time_offset") or {}).get("found")
    if found:
        out += (f"\ncamera-lidar time offset: the scans are taken {found['offset_s']:.3f} s (+- "
                f"{found['sigma_s']:.3f}) after the images; run again with --time-offset {found['offset_s']:.3f}")
    turned = (summary.get("extrinsic") or {}).get("found")
    if turned:
        turn, spread = _angles(turned["correction_deg"]), _angles(turned["sigma_deg"], signed=False)
        out += (f"\ncamera-lidar extrinsic: the lidar's motions agree with the camera's through it turned by {turn} "
                f"deg (+- {spread}); run again with crosscheck.extrinsic_correction_deg = {turn} composed with the "
                "one stated")
    return out


def _angles(values, signed: bool = True) -> str:
    return "[" + ", ".join(f"{float(v):+.2f}" if signed else f"{float(v):.2f}" for v in values) + "]"


def _write_poses(out: Path, system, dataset, fmt: str = "kitti"):
    """poses.txt, and truth.txt beside it where the data has ground truth -> (poses, truth or None), cam0."""
    from plvo.data.trajectory import write_poses
    from plvo_app.run_summary import truth_cam0

    poses, truth = system.poses_cam0(dataset.frame_indices), truth_cam0(dataset)
    for name, what in ((POSES_FILE, poses), (TRUTH_FILE, truth)):
        if what is None:
            continue
        try:
            write_poses(out / name, what, dataset.times, fmt)
        except OSError as exc:
            raise RunFailed(f"{out / name}: cannot write the results ({exc.strerror or exc})") from None
    return poses, truth


def _write_summary(outs: Outputs, system, dataset, status: str, reason: str, fps: float, fmt: str,
                   scored) -> dict:
    """summary.json: how the run ended, how fast, and with truth how accurate (plvo_app.run_summary)."""
    from plvo_app.run_summary import accuracy, build_summary

    figures = None
    if scored is not None and scored[1] is not None:
        figures = accuracy(scored[1], scored[0])
    tracked, _ = tracked_summary(system.frames_done, system.n_lost)
    summary = build_summary(
        run=outs.run, sequence=dataset.sequence, status=status, reason=reason, frame_indices=dataset.frame_indices,
        frames_done=system.frames_done, frames_tracked=tracked, fps=fps,
        poses_file=outs.out / POSES_FILE if scored is not None else None, pose_format=fmt,
        truth_source=getattr(dataset, "truth_source", None),
        truth_file=outs.out / TRUTH_FILE if figures is not None else None, figures=figures)
    write_json(outs.out / SUMMARY_FILE, summary)
    return summary


def _run_frames(system, dataset, at: list[int]) -> float:
    """Step through the dataset (plvo.runtime.run.step_through: each frame read while the previous one is tracked, the
    run started again from its first frame where the System finds it must) with a progress bar, then let the
    workers finish; returns frames a second over all of it (what a user waits for, a restart's frames included in
    the time). `at` holds the frame being processed. Ctrl-C propagates."""
    from tqdm import tqdm

    from plvo.runtime.run import step_through

    t0 = time.perf_counter()
    with tqdm(total=len(dataset), unit="frame", desc=dataset.sequence, dynamic_ncols=True,
              disable=not progress_enabled()) as bar:
        step_through(system, dataset, bar.update, at)
    return system.frames_done / max(time.perf_counter() - t0, 1e-9)


def _save_config(cfg: SystemConfig, out: Path) -> None:
    try:
        save_config(cfg, out / "config.toml")
    except OSError as exc:
        raise OutputError(f"{out / 'config.toml'}: cannot write ({exc.strerror or exc})") from None


def _start_outputs(outs: Outputs, cfg: SystemConfig, n_frames: int) -> RunLog:
    """run.log, config.toml and timings.json marked "running": the first real writes, before the first frame."""
    runlog = RunLog(outs.out / "run.log")
    try:
        _save_config(cfg, outs.out)
    except OutputError:
        runlog.close()
        raise
    write_json(outs.out / "timings.json", {"status": "running", "frames_total": n_frames})
    return runlog


def _unstart(outs: Outputs, made: list[Path]) -> None:
    """A run that ended before its first frame (Ctrl-C or a signal while the worker processes start, too few open
    files, a thread or process that cannot be made): the files `_start_outputs` wrote and the folders made for
    them are removed, so that no folder says "running" for ever and the same --out can be given again; the one
    line (and for a bug, the log with its traceback: plvo_app.cli) says what happened."""
    for name in RESULTS_FILES:
        (outs.out / name).unlink(missing_ok=True)
    remove_made(made)


def run(args: argparse.Namespace) -> int:
    opts = VizOptions.from_args(args)
    serve = opts.serve
    if serve:
        check_port(opts.port)
    if opts.replay is not None:
        from plvo_app.cmd_view import view

        return view(opts.replay, port=opts.port, serve=serve)
    from plvo.runtime.system import System
    from plvo_app.rerun_recorder import RerunRecorder

    cfg = _resolve_config(opts)
    options = recorder_options(opts)
    dataset, label, identity = _open(opts)
    emb = options.embed_inputs
    if emb is not None and not any(emb[0] <= f < emb[1] for f in dataset.frame_indices):
        raise DatasetError(f"--embed-inputs {opts.embed_text}: none of these frames runs (frames "
                           f"{dataset.frame_indices[0]}..{dataset.frame_indices[-1]})")
    outs, claimed = _outputs(opts, label)
    try:
        made = claimed + check_outputs(outs, len(dataset), opts.rrd is not None, opts.out is not None)
    except BaseException:
        remove_made(claimed)
        raise
    try:
        runlog = _start_outputs(outs, cfg, len(dataset))
    except BaseException:
        _unstart(outs, made)
        raise
    # Made first: its worker processes start up (their imports take a second or two) while the recorder and the
    # viewer start, not only while the first frames are tracked.
    system = None
    try:
        system = System(cfg, FanOut([]), calib=dataset.calib)
        info = run_info(outs.run, dataset, cfg, shlex.join(["plvo-viz", *sys.argv[1:]]), dataset=identity)
    except BaseException:
        if system is not None:
            system.close()
        runlog.close()
        _unstart(outs, made)
        raise
    viewer = None
    end, fps, at = RunEnd(), 0.0, [dataset.frame_indices[0]]
    recorders = system.recorder.recorders  # filled below, inside the try: a failing recorder is a failed run
    try:
        recorders.append(RerunRecorder(outs.rrd, options, next_free=opts.rrd is None))
        outs = dataclasses.replace(outs, rrd=recorders[-1].path)  # another run may have taken the default name
        if serve:
            from plvo_app.viser_viewer import SceneStore, ViserRecorder, ViserViewer

            viewer = ViserViewer(SceneStore(), port=opts.port, live=True)
            recorders.append(ViserRecorder(viewer))
            if viewer.port != opts.port:  # taken since check_port: viser moved on, and says nothing itself
                print(f"port {opts.port} was taken meanwhile; serving on {viewer.port}", file=sys.stderr)
            print(f"viser viewer: http://127.0.0.1:{viewer.port}", file=sys.stderr)
        system.start(info)
        fps = _run_frames(system, dataset, at)
        if system.restarts:  # the config the poses come from: given again, it runs them without a restart
            _save_config(system.config, outs.out)
        end.status = "complete"
    except KeyboardInterrupt as exc:
        end.status, end.exit_code, end.reason = "interrupted", exit_status_of(exc), signal_name(exc)
    except PlvoError as exc:
        end.fail(exc)
        runlog.traceback(f"frame {at[0]}: {exc}")
    except Exception as exc:  # noqa: BLE001 - the last resort: one line, the traceback in the run log
        at[0] = getattr(exc, "plvo_frame", at[0])  # an error of the frames read ahead: the frame it came from
        runlog.traceback(f"frame {at[0]}: unexpected error")
        cause = f": {type(exc.__cause__).__name__}: {exc.__cause__}" if exc.__cause__ is not None else ""
        limit = limit_reached(exc)
        what = limit if limit is not None else f"unexpected {type(exc).__name__}: {exc}{cause}"
        end.fail(RunFailed(f"frame {at[0]}: {what} (see the log {runlog.path})"))
    # From here to the exit, Ctrl-C and SIGTERM are held: the clean-up is not cut short by a second Ctrl-C, and
    # after a complete run a signal quits the viewer (exit 0, nothing said "interrupted").
    with deferred_signals("writing the results") as held:
        if end.status == "interrupted":
            print(f"interrupted after {system.frames_done} of {len(dataset)} frames ({end.reason}); keeping what was "
                  "recorded", file=sys.stderr)
        summary = _finish(system, recorders, outs, dataset, end, fps, runlog, opts.pose_format)
        latest = point_latest(outs.out) if opts.out is None and summary else None
        print(f"recording: {outs.rrd}\nresults:   {outs.out}/", file=sys.stderr)
        if end.whole:
            for line in summary_lines(summary):
                print(line, file=sys.stderr)
            print(f"summary:   {(latest or outs.out) / SUMMARY_FILE}", file=sys.stderr)
            tracked, share = tracked_summary(system.frames_done, system.n_lost)  # the last line: how it ended
            print(f"{end.status}: {system.frames_done} frames at {fps:.1f} frames/s, {tracked} tracked ({share:.0%})"
                  f"{trust_line(system)}", file=sys.stderr)
            end.exit_code = DEGRADED_EXIT if end.status == DEGRADED else end.exit_code
            if viewer is not None and not held.seen:
                held.what = None
                print(f"serving the run: http://127.0.0.1:{viewer.port} - Ctrl-C to quit", file=sys.stderr)
                while not held.seen:
                    time.sleep(0.2)
        if viewer is not None:
            viewer.close()
    if end.error is not None:
        if end.error.exit_status != RunFailed.exit_status:  # bad data met mid-run, a failed write: the run failed
            raise RunFailed(str(end.error)) from None
        raise end.error
    return end.exit_code


def _finish(system, recorders, outs, dataset, end: RunEnd, fps, runlog, fmt="kitti") -> dict:
    """Write the poses, stamp and close the recording, then write timings.json with the status as it ends up (end,
    settled here) -> the summary. poses.txt comes first, so that neither the recording nor timings.json says
    "complete" for a run whose poses could not be written."""
    if end.status == "complete":
        tracked, share = tracked_summary(system.frames_done, system.n_lost)
        if share < MIN_TRACKED_SHARE:
            end.reason = (f"tracked only {tracked} of {system.frames_done} frames ({share:.0%}), "
                          f"below {MIN_TRACKED_SHARE:.0%}")
            end.error = RunFailed(f"{end.reason}: results marked failed, no poses.txt")
        elif system.n_lost:
            # the trajectory is not whole: some frames hold the motion model's guess, neither sensor's
            end.status, end.reason = DEGRADED, (f"{system.n_lost} of {system.frames_done} frames lost: neither the "
                                                "camera nor the lidar placed them, their poses are the motion model's "
                                                "guess")
    scored = None  # (poses, truth or None) once poses.txt is written
    if end.whole:
        try:
            scored = _write_poses(outs.out, system, dataset, fmt)
        except PlvoError as exc:
            end.error, end.reason = exc, str(exc)
    if end.error is not None:
        end.status = "failed"
        scored = None
    try:
        if recorders:
            recorders[0].set_status(end.status, system.frames_done)
        system.close()
    except PlvoError as exc:  # the recording's last write failed
        if end.error is None:
            end.fail(exc)
            scored = None
            (outs.out / POSES_FILE).unlink(missing_ok=True)
            (outs.out / TRUTH_FILE).unlink(missing_ok=True)
    summary: dict = {}
    try:
        write_json(outs.out / "timings.json", _timings(system, end.status, end.reason, fps, len(dataset)))
        summary = _write_summary(outs, system, dataset, end.status, end.reason, fps, fmt, scored)
    except PlvoError as exc:
        end.error = end.error or exc
        log.error("%s", exc)
    runlog.close()
    return summary
