"""Calibration for your own data: `plvo calib write` and `plvo calib check`.

`plvo calib write --kitti FILE_OR_FOLDER --out calib.yaml [--camera N] [--size WxH]`: the plain-folder layout's
calib.yaml from a KITTI odometry calib.txt (P0..P3, Tr) or a raw day's calib_cam_to_cam.txt + calib_velo_to_cam.txt;
read back by the folder reader it gives the K and T_cam_lidar the KITTI reader gives (checked before it is kept).

`plvo calib check --root DATA [--seq S] [--frame N] --out check.png`: frame N's scan projected onto its image with the
calibration plvo would use for that data (any layout plvo reads), coloured by depth, and one line of figures that
tell a good calibration from a bad one (plvo.data.calib_score).

Neither replaces an existing file (docs/faults.md, "Outputs").
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

from plvo.errors import ArgumentsError
from plvo_app.source_args import add_source_arguments

ROUND_TRIP_TOL = 1e-9


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    w = sub.add_parser("write", help="write a plain folder's calib.yaml from a KITTI calibration",
                       description="Write the plain-folder layout's calib.yaml from a KITTI odometry calib.txt or a "
                                   "raw day's calib_cam_to_cam.txt + calib_velo_to_cam.txt.")
    w.add_argument("--kitti", required=True, type=Path, metavar="FILE_OR_FOLDER",
                   help="an odometry calib.txt or its sequence folder; a raw day's calib_cam_to_cam.txt, its folder "
                        "or one of its drives")
    w.add_argument("--out", required=True, type=Path, metavar="calib.yaml", help="the file to write (a new one)")
    w.add_argument("--camera", type=int, default=0, choices=(0, 1, 2, 3),
                   help="KITTI camera: 0/1 grey left/right, 2/3 colour left/right (as plvo-viz --camera); default 0")
    w.add_argument("--size", default=None, metavar="WxH",
                   help="the images' width and height in pixels; default: the first image beside the calibration, "
                        "else a raw day's S_rect_0N")
    c = sub.add_parser("check", help="project a frame's scan onto its image; score how well they fit",
                       description="Project frame N's scan onto its image with the calibration plvo would use, "
                                   "write it as a PNG and print figures that tell a good calibration from a bad one.")
    c.add_argument("--root", type=Path, default=None,
                   help="the data: a KITTI root (default $KITTI_ROOT), a ROS bag or a plain folder")
    c.add_argument("--seq", default=None, help="the sequence or drive under a KITTI root; default its only one")
    c.add_argument("--frame", type=int, default=0, metavar="N", help="the frame to check (default 0)")
    c.add_argument("--out", required=True, type=Path, metavar="check.png", help="the picture to write (a new file)")
    add_source_arguments(c)


def run(args: argparse.Namespace) -> int:
    return _write(args) if args.action == "write" else _check(args)


def _parse_size(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if match is None or int(match.group(1)) <= 0 or int(match.group(2)) <= 0:
        raise ArgumentsError(f"--size {text!r}: expected WIDTHxHEIGHT in pixels, e.g. 1226x370")
    return int(match.group(1)), int(match.group(2))


def _write(args: argparse.Namespace) -> int:
    import numpy as np

    from plvo.data.calib_write import read_kitti_calibration, write_folder_calib
    from plvo.data.calib_yaml import read_calib_yaml
    from plvo_app.run_outputs import refuse_existing

    size = _parse_size(args.size)
    refuse_existing([args.out], "plvo calib write", "choose another --out")
    kc = read_kitti_calibration(args.kitti, args.camera, size)
    write_folder_calib(args.out, kc)
    written = read_calib_yaml(args.out)
    back = written.camera.calibration(written.T_cam_lidar)  # as the folder reader makes it
    c = kc.calib
    if not (np.allclose(back.K, c.K, rtol=0, atol=ROUND_TRIP_TOL)
            and np.allclose(back.T_cam_velo, c.T_cam_velo, rtol=0, atol=ROUND_TRIP_TOL)):
        args.out.unlink()  # a file that would mislead every later run: not kept
        raise ArgumentsError(f"{args.out}: read back, K or T_cam_lidar differs from {kc.files[0]}'s (a bug; not kept)")
    t = c.T_cam_velo[:3, 3]
    print(f"wrote {args.out}: camera {kc.camera} of {' + '.join(map(str, kc.files))}; {c.width}x{c.height} "
          f"(from {kc.size_from}); fx {c.fx:g} fy {c.fy:g} cx {c.cx:g} cy {c.cy:g}; T_cam_lidar translation "
          f"[{t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}] m; lidar elevation offset {c.lidar_elevation_offset_deg:g} deg")
    return 0


def _check(args: argparse.Namespace) -> int:
    import cv2

    from plvo.atomic import atomic_path
    from plvo.data.calib_score import overlay, score_frame
    from plvo.data.registry import ROOT_ENV, only_sequence, open_dataset
    from plvo.errors import OutputError
    from plvo_app.run_outputs import refuse_existing
    from plvo_app.source_args import source_options

    if args.frame < 0:
        raise ArgumentsError(f"--frame {args.frame}: must be >= 0")
    if args.out.suffix.lower() != ".png":
        raise ArgumentsError(f"--out {args.out}: the picture is a PNG: name it .png")
    refuse_existing([args.out], "plvo calib check", "choose another --out")
    root = args.root if args.root is not None else os.environ.get(ROOT_ENV)
    if root is None:  # no synthetic town here: a calibration is checked on the user's own data
        raise ArgumentsError(f"no data: give --root DATA (a KITTI root, a ROS bag or a plain folder) or set "
                             f"${ROOT_ENV}")
    seq = args.seq if args.seq is not None else only_sequence(root, "--root" if args.root else f"${ROOT_ENV}")
    dataset = open_dataset(root, seq, slice(args.frame, args.frame + 1), camera=args.camera,
                           options=source_options(args))
    frame = dataset[0]
    score, proj = score_frame(frame.image, frame.scan, frame.calib)
    title = f"plvo calib check: {dataset.name} {dataset.sequence} frame {frame.index}"
    ok, png = cv2.imencode(".png", overlay(frame.color if frame.color is not None else frame.image, proj, score,
                                           title))
    if not ok:
        raise OutputError(f"{args.out}: the picture could not be encoded as PNG")
    try:
        with atomic_path(args.out) as tmp:
            tmp.write_bytes(png.tobytes())
    except OSError as exc:
        raise OutputError(f"{args.out}: cannot write ({exc.strerror or exc})") from None
    print(f"{dataset.name} {dataset.sequence} frame {frame.index}: {score.line()}")
    print(f"wrote {args.out}", file=sys.stderr)
    return 0
