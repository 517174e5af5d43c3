"""Generate a synthetic sequence in the KITTI odometry layout (images, scans, calib, poses, ground truth).

Examples:
  plvo synth --out data/synth --seq 00 --frames 300 --seed 1 --loop        # the town: a grid of blocks
  plvo synth --out data/twins --seq 05 --follow ../shared/data/kitti/poses/05.txt --frames 0:200
  plvo synth --out data/twins --twins 00-10 --kitti-poses ../shared/data/kitti/poses --frames 0:100 --workers 2
  plvo synth --out data/rawtwins --raw-drive ../shared/data/kitti_raw --seq 2011_09_26_drive_0009 --frames 0:51
write OUT/sequences/NN/{image_0,velodyne,gt}/..., calib.txt, times.txt and OUT/poses/NN.txt, readable by
pykitti.odometry('OUT', 'NN') and by `plvo-viz --root OUT --seq NN`. A twin (--follow, --twins) is driven along a
KITTI pose file, with traffic, sun and shadows and a rolling lidar sweep (see plvo_synth.twin), and the
imperfections of KITTI's sensors (twin.realism; --ideal: none, the twins as they were before). A raw drive's twin
(--raw-drive ROOT --seq DATE_drive_NNNN) follows the drive's oxts and is written in KITTI's raw layout under
OUT/DATE, read as the real drive is (`plvo-viz --root OUT --seq DATE_drive_NNNN`).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from plvo.errors import SynthError

# The generators (numpy, open3d, the renderer) and tqdm are imported when a sequence is made: `plvo synth --help`
# answers at once.
# plvo_synth.twin.lidars.LIDAR_MODELS's names, for --help (tests/plvo_app/test_terminal.py checks that they agree)
LIDAR_NAMES = ("hdl64", "hdl32", "vlp16", "os128")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.ArgumentDefaultsHelpFormatter
    parser.description = __doc__.strip()
    parser.add_argument("--out", required=True, help="dataset root to write (sequences/NN and poses/NN.txt)")
    parser.add_argument("--seq", default="00",
                        help="two-digit sequence number (with --raw-drive: the drive, e.g. 2011_09_26_drive_0009)")
    parser.add_argument("--frames", default=None,
                        help="the town: number of frames (10 per second, default 300); a twin: range A:B of the "
                             "followed file (B exclusive; default all)")
    parser.add_argument("--seed", type=int, default=0, help="town and trajectory seed; same seed, same files")
    parser.add_argument("--speed", type=float, default=10.0, help="driving speed in m/s (KITTI: 5-15)")
    parser.add_argument("--loop", action="store_true",
                        help="circle a block and drive on along the first street (revisits it, for loop closure)")
    parser.add_argument("--stops", action="store_true", help="stop for 2 s now and then (frames without motion)")
    parser.add_argument("--exposure-change", type=float, default=0.0, metavar="AMPLITUDE",
                        help="relative camera gain swing between frames, 0..0.5 (0: constant exposure)")
    parser.add_argument("--depth", action="store_true", help="also write per-pixel cam0 depth (gt/depth/*.npy)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing sequence NN")
    twin = parser.add_argument_group("KITTI twins (driven along a KITTI pose file)")
    twin.add_argument("--follow", metavar="POSES.txt", help="KITTI pose file (cam0) to drive along")
    twin.add_argument("--twins", metavar="00-10", help="several twins at once, following --kitti-poses/NN.txt")
    twin.add_argument("--kitti-poses", metavar="DIR", help="folder of KITTI pose files NN.txt (for --twins)")
    twin.add_argument("--traffic", type=int, default=None, metavar="N",
                      help="moving cars in a twin (default: one per 60 m of path; 0: none)")
    twin.add_argument("--lidar", default="hdl64", help=f"lidar model of a twin: {', '.join(LIDAR_NAMES)}")
    twin.add_argument("--ideal", action="store_true",
                      help="ideal sensors: no camera, lidar or rig imperfections, KITTI 00-02's calibration for "
                           "every twin and raw sweeps (the twins as written before the realism existed)")
    twin.add_argument("--raw-drive", metavar="ROOT",
                      help="the twin of a KITTI raw drive under ROOT (--seq DATE_drive_NNNN; its oxts, timestamps "
                           "and calibration), written in KITTI's raw layout under --out")
    twin.add_argument("--workers", type=int, default=1, help="--twins: local worker processes (or CPUs of local Ray)")
    twin.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                      help="--twins: fan out over Ray ('local' or a cluster address; --out and the pose files on a "
                           "path every node sees; a twin whose node dies is carried on by another)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _town_frames(text) -> int:
    if text is None:
        return 300
    try:
        return int(text)
    except ValueError:
        raise SynthError(f"--frames {text!r}: the town takes a number of frames (A:B ranges are for --follow)") \
            from None


def run(args: argparse.Namespace) -> int:
    if args.raw_drive:
        return run_raw_twin(args)
    if args.follow or args.twins:
        return run_twins(args)
    if args.ideal:
        raise SynthError("--ideal: for twins (--follow, --twins, --raw-drive); the town's sensors are ideal already")
    from tqdm import tqdm

    from plvo_synth import SynthSettings, generate_sequence
    from plvo_synth.generate import check_request

    args.frames = _town_frames(args.frames)
    settings = SynthSettings(args.frames, args.seed, args.speed, args.loop, args.stops, args.exposure_change,
                             args.depth)
    check_request(args.out, args.seq, settings, args.overwrite)  # clear errors before any output
    bar = None if args.no_progress else tqdm(total=args.frames, unit="frame", desc=f"synth seq {args.seq}")

    def progress(done: int, total: int) -> None:
        if bar is not None:
            bar.update(done - bar.n)

    start = time.perf_counter()
    try:
        root = generate_sequence(
            args.out, sequence=args.seq, n_frames=args.frames, seed=args.seed, speed_mps=args.speed,
            loop=args.loop, stops=args.stops, exposure_change=args.exposure_change, write_depth=args.depth,
            progress=progress, overwrite=args.overwrite,
        )
    finally:
        if bar is not None:
            bar.close()
    seconds = time.perf_counter() - start
    print(f"wrote {root}/sequences/{args.seq}: {args.frames} frames in {seconds:.1f} s "
          f"({args.frames / seconds:.1f} frames/s including town setup)", file=sys.stderr)
    return 0


def run_twins(args: argparse.Namespace) -> int:
    """--follow (one twin as --seq) or --twins (several, in parallel): generate, report frames a second."""
    from plvo_app.twin_progress import twin_progress
    from plvo_synth.twin.batch import TwinJob, ensure_twins, parse_twins, twin_jobs
    from plvo_synth.twin.generate import TwinSettings

    if args.follow and args.twins:
        raise SynthError("--follow and --twins: give one (--twins follows --kitti-poses/NN.txt)")
    if args.workers < 1:
        raise SynthError(f"--workers {args.workers}: must be at least 1")
    base = TwinSettings(str(args.follow or ""), args.frames, args.seed, args.traffic, args.lidar, args.depth,
                        _realism(args))
    if args.twins:
        if not args.kitti_poses:
            raise SynthError("--twins: give --kitti-poses DIR (the folder of KITTI pose files 00.txt ...)")
        jobs = twin_jobs(parse_twins(args.twins), args.kitti_poses, base)
    else:
        from plvo_synth.twin.generate import check_twin_request

        check_twin_request(args.out, args.seq, base, args.overwrite)
        jobs = [TwinJob(args.seq, base)]
    start = time.perf_counter()
    with twin_progress("twins " + ",".join(j.sequence for j in jobs), bar=not args.no_progress) as (progress, on_done):
        results = ensure_twins(jobs, args.out, workers=args.workers, ray=args.ray, progress=progress, on_done=on_done,
                               overwrite=args.overwrite)
    seconds = time.perf_counter() - start
    frames = sum(r.frames for r in results)
    print(f"wrote {sum(not r.cached and not r.error for r in results)} twin(s) under {args.out}: {frames} frames in "
          f"{seconds:.1f} s ({frames / max(seconds, 1e-9):.2f} frames/s over the batch)", file=sys.stderr)
    return 0 if not any(r.error for r in results) else 1


def _realism(args: argparse.Namespace):
    from plvo_synth.twin.realism import IDEAL, REALISTIC

    return IDEAL if args.ideal else REALISTIC


def run_raw_twin(args: argparse.Namespace) -> int:
    """--raw-drive ROOT --seq DATE_drive_NNNN: the drive's twin in KITTI's raw layout under --out."""
    from tqdm import tqdm

    from plvo_synth.twin.generate import TwinSettings
    from plvo_synth.twin.raw_drive import check_raw_request, generate_raw_twin, parse_drive_name

    if args.follow or args.twins:
        raise SynthError("--raw-drive and --follow/--twins: give one (a raw drive's twin follows its own oxts)")
    date, number = parse_drive_name(args.seq)
    drive = f"{date}_drive_{number}"
    settings = TwinSettings(str(Path(args.raw_drive).resolve() / date / f"{drive}_sync"), args.frames, args.seed,
                            args.traffic, args.lidar, args.depth, _realism(args))
    plan = check_raw_request(args.out, args.raw_drive, drive, settings, args.overwrite)  # errors before any output
    bar = None if args.no_progress else tqdm(total=plan.path.n_frames, unit="frame", desc=f"twin {drive}")

    def progress(done: int, total: int) -> None:
        if bar is not None:
            bar.update(done - bar.n)

    start = time.perf_counter()
    try:
        generate_raw_twin(args.out, args.raw_drive, drive, settings, progress, args.overwrite, plan)
    finally:
        if bar is not None:
            bar.close()
    seconds = time.perf_counter() - start
    print(f"wrote {args.out}/{date}/{drive}_sync in {seconds:.1f} s", file=sys.stderr)
    return 0
