"""Generate a synthetic town sequence in the KITTI odometry layout (images, scans, calib, poses, ground truth).

Example: plvo synth --out data/synth --seq 00 --frames 300 --seed 1 --loop
writes data/synth/sequences/00/{image_0,velodyne,gt}/..., calib.txt, times.txt and data/synth/poses/00.txt,
readable by pykitti.odometry('data/synth', '00') and by `plvo-viz --root data/synth --seq 00`.
"""

from __future__ import annotations

import argparse
import logging
import time

from tqdm import tqdm

from plvo.data.synth import SynthSettings, generate_sequence
from plvo.data.synth.generate import check_request

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.ArgumentDefaultsHelpFormatter
    parser.description = __doc__.strip()
    parser.add_argument("--out", required=True, help="dataset root to write (sequences/NN and poses/NN.txt)")
    parser.add_argument("--seq", default="00", help="two-digit sequence number")
    parser.add_argument("--frames", type=int, default=300, help="number of frames (10 per second)")
    parser.add_argument("--seed", type=int, default=0, help="town and trajectory seed; same seed, same files")
    parser.add_argument("--speed", type=float, default=10.0, help="driving speed in m/s (KITTI: 5-15)")
    parser.add_argument("--loop", action="store_true",
                        help="circle a block and drive on along the first street (revisits it, for loop closure)")
    parser.add_argument("--stops", action="store_true", help="stop for 2 s now and then (frames without motion)")
    parser.add_argument("--exposure-change", type=float, default=0.0, metavar="AMPLITUDE",
                        help="relative camera gain swing between frames, 0..0.5 (0: constant exposure)")
    parser.add_argument("--depth", action="store_true", help="also write per-pixel cam0 depth (gt/depth/*.npy)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing sequence NN")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
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
    log.info("wrote %s/sequences/%s: %d frames in %.1f s (%.1f frames/s including town setup)",
             root, args.seq, args.frames, seconds, args.frames / seconds)
    return 0
