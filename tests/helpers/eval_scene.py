"""Tiny synthetic sequences for the evaluation tests, in the KITTI odometry layout, written in well under a second.

A street of boxes (road, two rows of walls with gaps, pillars) ray-cast analytically by a 32-beam lidar; the
camera images are blank (only KISS-ICP and the machinery run on them). Calibration is KITTI seq 00's, as the
synthetic town uses. The car drives along x at `speed_mps` with a gentle sinusoidal yaw.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from plvo.data.trajectory import write_kitti_poses
from plvo_synth.sensors import KITTI_CALIB_00_TEXT, T_CAM_VELO

LIDAR_HEIGHT_M = 1.73


def _boxes(rng: np.random.Generator, length: float) -> np.ndarray:
    """(B,2,3) lo, hi corners in the street frame (x along, y left, z up): road, building fronts with random
    setbacks and street clutter (their faces across the street pin the motion along it)."""
    boxes = [[[-90, -40, -1.0], [length + 90, 40, 0.0]]]  # road
    for side in (-1, 1):
        x = -80.0
        while x < length + 80:
            w, y0 = rng.uniform(3, 8), side * rng.uniform(7, 11)
            boxes.append([[x, min(y0, y0 + side * 8), 0], [x + w, max(y0, y0 + side * 8), rng.uniform(4, 15)]])
            for _ in range(2):  # clutter (cars, kiosks, bins): faces at every angle of view
                px, py, size = x + rng.uniform(0, w), side * rng.uniform(3.5, 6.5), rng.uniform(0.6, 2.5, 2)
                boxes.append([[px, py, 0], [px + size[0], py + size[1], rng.uniform(0.8, 3.5)]])
            x += w
    return np.asarray(boxes, dtype=np.float64)


def _lidar_dirs(n_azimuth: int = 360) -> np.ndarray:
    elev = np.radians(np.linspace(2.0, -24.8, 32))
    azim = np.linspace(-np.pi, np.pi, n_azimuth, endpoint=False)
    e, a = np.meshgrid(elev, azim, indexing="ij")
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1).reshape(-1, 3)


def _cast(origin: np.ndarray, dirs: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Ranges (R,) of rays from origin (3,) along dirs (R,3) to the nearest box, inf where none (slab test)."""
    centre = boxes.mean(axis=1)
    boxes = boxes[np.abs(centre[:, 0] - origin[0]) < 60.0 + (boxes[:, 1, 0] - boxes[:, 0, 0]) / 2]  # in reach
    inv = 1.0 / np.where(np.abs(dirs) < 1e-12, 1e-12, dirs)
    near = np.full((len(dirs), len(boxes)), -np.inf, np.float32)
    far = np.full((len(dirs), len(boxes)), np.inf, np.float32)
    for axis in range(3):
        t0 = (boxes[None, :, 0, axis] - origin[axis]) * inv[:, None, axis].astype(np.float32)
        t1 = (boxes[None, :, 1, axis] - origin[axis]) * inv[:, None, axis].astype(np.float32)
        np.maximum(near, np.minimum(t0, t1), out=near)
        np.minimum(far, np.maximum(t0, t1), out=far)
    near[(near > far) | (near < 0.5)] = np.inf
    return near.min(axis=1).astype(np.float64)


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [x, y, LIDAR_HEIGHT_M]
    return T


def write_box_sequence(root: Path, name: str, n_frames: int = 30, speed_mps: float = 10.0, seed: int = 0) -> Path:
    """Write root/sequences/<name> and root/poses/<name>.txt; returns root. GT poses are cam0's, world = frame 0."""
    rng = np.random.default_rng(seed)
    length = speed_mps * 0.1 * n_frames
    boxes, dirs = _boxes(rng, length), _lidar_dirs()
    seq = Path(root) / "sequences" / name
    (seq / "image_0").mkdir(parents=True, exist_ok=True)
    (seq / "velodyne").mkdir(parents=True, exist_ok=True)
    (Path(root) / "poses").mkdir(parents=True, exist_ok=True)
    (seq / "calib.txt").write_text(KITTI_CALIB_00_TEXT)
    (seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(n_frames)))
    image = np.zeros((32, 96), np.uint8)
    T_velo_cam = np.linalg.inv(T_CAM_VELO)
    T_street_cam = []
    y, yaw = 0.0, 0.0
    for i in range(n_frames):
        x = speed_mps * 0.1 * i
        yaw = 0.06 * np.sin(0.15 * i + seed)
        y += speed_mps * 0.1 * np.sin(yaw)
        T = _pose(x, y, yaw)
        ranges = _cast(T[:3, 3], dirs @ T[:3, :3].T, boxes)
        ok = ranges < 60.0
        points = dirs[ok] * (ranges[ok] + rng.normal(0, 0.01, ok.sum()))[:, None]
        scan = np.hstack([points, np.full((len(points), 1), 0.5)]).astype(np.float32)
        scan.tofile(seq / "velodyne" / f"{i:06d}.bin")
        cv2.imwrite(str(seq / "image_0" / f"{i:06d}.png"), image)
        T_street_cam.append(T @ T_velo_cam)
    T_street_cam = np.asarray(T_street_cam)
    write_kitti_poses(Path(root) / "poses" / f"{name}.txt", np.linalg.inv(T_street_cam[0]) @ T_street_cam)
    return Path(root)
