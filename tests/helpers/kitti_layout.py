"""A tiny KITTI odometry sequence written to disk (calib.txt, times.txt, images, scans, poses): the loaders' and the
input faults' tests read it."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from plvo.data.trajectory import write_kitti_poses
from plvo.geometry import se3

FX, CX, CY, BASELINE = 100.0, 20.0, 10.0, 0.5
W, H = 40, 20
# velodyne (x fwd, y left, z up) -> camera (x right, y down, z fwd)
R_CAM_VELO = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def row(values) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(values, dtype=float).reshape(-1))


def projection(tx: float) -> np.ndarray:
    return np.array([[FX, 0, CX, tx], [0, FX, CY, 0], [0, 0, 1, 0]])


def make_odometry(root: Path, n: int = 5, seq: str = "07", with_tr: bool = True, cameras=(0, 1, 2)) -> Path:
    """A tiny KITTI odometry sequence: n frames of W x H images, 100-point scans, poses moving 1 m along z."""
    seq_dir = root / "sequences" / seq
    T_velo = se3.from_rt(R_CAM_VELO, [0.0, -0.08, -0.27])
    calib = [f"P{c}: {row(projection(-FX * BASELINE if c in (1, 3) else 0.0))}" for c in range(4)]
    if with_tr:
        calib.append(f"Tr: {row(T_velo[:3])}")
    seq_dir.mkdir(parents=True)
    (seq_dir / "calib.txt").write_text("\n".join(calib) + "\n")
    (seq_dir / "times.txt").write_text("".join(f"{0.1 * k:.6e}\n" for k in range(n + 3)))
    rng = np.random.default_rng(0)
    for c in cameras:
        (seq_dir / f"image_{c}").mkdir()
    (seq_dir / "velodyne").mkdir()
    for k in range(n):
        for c in cameras:
            img = np.full((H, W, 3) if c >= 2 else (H, W), 10 * k + c, np.uint8)
            cv2.imwrite(str(seq_dir / f"image_{c}" / f"{k:06d}.png"), img)
        rng.normal(0, 5, (100, 4)).astype(np.float32).tofile(seq_dir / "velodyne" / f"{k:06d}.bin")
    poses = np.stack([se3.from_rt(np.eye(3), [0.0, 0.0, float(k)]) for k in range(n + 3)])
    write_kitti_poses(root / "poses" / f"{seq}.txt", poses)
    return seq_dir
