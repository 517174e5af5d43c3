"""Copies of a KITTI odometry clip with one fault each, made of links to the real files (nothing copied but the
text files and a generated sequence's scene description): frozen images, repeated scans, scans a frame ahead of the
images, dropped frames."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

from plvo.data.kitti import SYNTH_MARKER


def variant(src_root: Path, seq: str, dst_root: Path, n_frames: int, image_of: Callable[[int], int] | None = None,
            scan_of: Callable[[int], int] | None = None, keep: Callable[[int], bool] | None = None) -> Path:
    """A KITTI root at dst_root holding frames 0..n_frames-1 of src_root's sequence seq, where frame i shows image
    image_of(i) and scan scan_of(i) of the source (identity by default); keep(i) False drops frame i (the later
    frames keep their numbers' times: a gap). Returns dst_root."""
    image_of = image_of or (lambda i: i)
    scan_of = scan_of or (lambda i: i)
    src, dst = src_root / "sequences" / seq, dst_root / "sequences" / seq
    (dst / "image_0").mkdir(parents=True)
    (dst / "velodyne").mkdir()
    shutil.copy(src / "calib.txt", dst / "calib.txt")
    scene = src / SYNTH_MARKER
    if scene.is_file():  # a generated sequence's: how its lidar sweeps and its elevation error, read with the scans
        (dst / SYNTH_MARKER).parent.mkdir()
        shutil.copy(scene, dst / SYNTH_MARKER)
    times = (src / "times.txt").read_text().split()
    poses = (src_root / "poses" / f"{seq}.txt").read_text().splitlines()
    kept = [i for i in range(n_frames) if keep is None or keep(i)]
    for k, i in enumerate(kept):
        os.symlink((src / "image_0" / f"{image_of(i):06d}.png").resolve(), dst / "image_0" / f"{k:06d}.png")
        os.symlink((src / "velodyne" / f"{scan_of(i):06d}.bin").resolve(), dst / "velodyne" / f"{k:06d}.bin")
    (dst / "times.txt").write_text("".join(f"{times[i]}\n" for i in kept))
    (dst_root / "poses").mkdir()
    (dst_root / "poses" / f"{seq}.txt").write_text("".join(f"{poses[i]}\n" for i in kept))
    return dst_root
