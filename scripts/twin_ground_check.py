"""How far cam0 stands from 1.65 m above a full-length twin's ground, per KITTI sequence (no rendering).

Usage: python scripts/twin_ground_check.py KITTI_POSES_DIR     (prints a Markdown table)
Where two passes over one place carry ground-truth heights that disagree, the ground follows the lower one
(plvo_synth.twin.layout): the camera of the higher pass floats by the disagreement.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from plvo_synth.sensors import CAMERA_HEIGHT_M
from plvo_synth.twin.follow import load_followed
from plvo_synth.twin.layout import Layout


def main(argv: list[str]) -> int:
    print("| seq | frames | height span m | cam0 above ground: median, p99, min, max (m) | frames off by > 0.1 m |")
    print("| --- | ---: | ---: | --- | ---: |")
    for f in sorted(Path(argv[0]).glob("[0-9][0-9].txt")):
        path = load_followed(f)
        layout = Layout(path.context_road, path.file_road, path.file_speed, 0, path.context_real)
        cam = path.T_town_cam[:, :3, 3]
        h = cam[:, 2] - layout.height(cam[:, :2])
        off = np.abs(h - CAMERA_HEIGHT_M)
        print(f"| {f.stem} | {len(h)} | {np.ptp(cam[:, 2]):.1f} | {np.median(h):.3f}, {np.percentile(h, 99):.2f}, "
              f"{h.min():.2f}, {h.max():.2f} | {int((off > 0.1).sum())} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
