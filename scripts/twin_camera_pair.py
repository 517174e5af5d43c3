"""One twin world seen by two cameras: the ideal camera (the old twins') and the realistic one (KITTI cam0's
imperfections, plvo_synth.twin.camera_effects), frame by frame, so that scripts/camera_stats.py can set the
camera's effect alone beside the real frames. The world, calibration and lidar are the ideal twin's.

Usage: python scripts/twin_camera_pair.py FOLLOW SEQ A:B OUT
e.g.   python scripts/twin_camera_pair.py ../shared/data/kitti/poses/04.txt 04 0:51 /tmp/pair04
Writes OUT/ideal/image_0/NNNNNN.png and OUT/realistic/image_0/NNNNNN.png, each folder with the twin's calib.txt.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from plvo_synth import sensors
from plvo_synth.twin.camera_effects import IDEAL_CAMERA, CameraRealism
from plvo_synth.twin.follow import PoseInterpolator
from plvo_synth.twin.generate import TwinSettings, build_twin
from plvo_synth.twin.realism import IDEAL


def main(argv: list[str]) -> int:
    if len(argv) != 4:
        raise SystemExit(__doc__)
    follow, seq, frames, out = argv[0], argv[1], argv[2], Path(argv[3])
    twin = build_twin(TwinSettings(follow=follow, frames=frames, realism=IDEAL), seq)
    poses = PoseInterpolator(twin.path.T_town_cam)
    cameras = {"ideal": IDEAL_CAMERA, "realistic": CameraRealism()}
    for name in cameras:
        (out / name / "image_0").mkdir(parents=True, exist_ok=True)
        (out / name / "calib.txt").write_text(sensors.KITTI_CALIB_00_TEXT)
    for i in range(twin.path.n_frames):
        for name, camera in cameras.items():
            # the generator's per-frame generator: the ideal images are the ideal twin's, byte for byte
            rng = np.random.default_rng(np.random.SeedSequence([twin.seed, 5, i]))
            image = twin.renderer.render_twin(twin.path.T_town_cam[i], i * sensors.FRAME_DT, rng, camera, poses,
                                              twin.seed)[0]
            if not cv2.imwrite(str(out / name / "image_0" / f"{i:06d}.png"), image):
                raise SystemExit(f"{out / name / 'image_0'}: cannot write frame {i}")
    print(f"wrote {twin.path.n_frames} frames a camera under {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
