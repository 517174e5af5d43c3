"""KITTI and TUM pose files: read with errors that name the file and line, write atomically.

KITTI: one pose a line, the 3x4 matrix T_world_cam row-major (12 numbers). TUM: `time tx ty tz qx qy qz qw`.
Blank lines and lines starting with `#` are skipped by both readers.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from plvo.atomic import write_text_atomic
from plvo.errors import TrajectoryError

PathLike = str | os.PathLike[str]

# A pose's 3x3 block must be a rotation: |R^T R - I| and |det R - 1| below this. KITTI's ground truth is printed with
# 7 significant digits (errors ~1e-6); a scaled or all-zero matrix is off by 0.1 or more.
ROTATION_TOLERANCE = 1e-3


def _read_rows(path: PathLike, n_cols: int, what: str, with_lines: bool = False, kind: str = "pose") -> Any:
    """Parse a whitespace-separated text file into (N, n_cols) float64, naming the file and line on error
    (with_lines: also the (N,) line numbers; kind: what the file is called in errors, "pose" or "times")."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise TrajectoryError(f"{path}: no such {kind} file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise TrajectoryError(f"{path}: cannot read {kind} file ({exc})") from None
    rows, linenos = [], []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) != n_cols:
            raise TrajectoryError(
                f"{path}:{lineno}: expected {n_cols} numbers ({what}), got {len(fields)}"
            )
        try:
            values = [float(f) for f in fields]
        except ValueError:
            bad = next(f for f in fields if not _is_float(f))
            raise TrajectoryError(f"{path}:{lineno}: not a number: {bad!r}") from None
        if not np.all(np.isfinite(values)):
            raise TrajectoryError(f"{path}:{lineno}: NaN or infinite value")
        rows.append(values)
        linenos.append(lineno)
    if not rows:
        raise TrajectoryError(f"{path}: no {'poses' if kind == 'pose' else kind} in file")
    poses = np.asarray(rows, dtype=np.float64)
    return (poses, np.asarray(linenos)) if with_lines else poses


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _as_poses(path: PathLike, poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] not in ((4, 4), (3, 4)):
        raise TrajectoryError(f"{path}: poses to write must be (N,4,4) or (N,3,4), got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        bad = int(np.flatnonzero(~np.isfinite(poses).all(axis=(1, 2)))[0])
        raise TrajectoryError(f"{path}: pose {bad} to write has NaN or infinite values")
    return poses


def read_kitti_poses(path: PathLike) -> np.ndarray:
    """KITTI pose file -> (N,4,4) T_world_cam."""
    rows, linenos = _read_rows(path, 12, "a 3x4 pose, row-major", with_lines=True)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    _check_rotations(path, poses[:, :3, :3], linenos)
    return poses


def _check_rotations(path: PathLike, R: np.ndarray, linenos: np.ndarray) -> None:
    """Raise naming the first line whose 3x3 block is not a rotation (all zeros, scaled, sheared, a reflection)."""
    ortho = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = np.flatnonzero((ortho > ROTATION_TOLERANCE) | (np.abs(det - 1.0) > ROTATION_TOLERANCE))
    if len(bad):
        i = int(bad[0])
        raise TrajectoryError(
            f"{path}:{linenos[i]}: the 3x3 block is not a rotation (|R^T R - I| = {ortho[i]:.3g}, det = {det[i]:.3g};"
            f" tolerance {ROTATION_TOLERANCE:g})")


def write_kitti_poses(path: PathLike, poses: np.ndarray) -> None:
    """(N,4,4) or (N,3,4) T_world_cam -> KITTI pose file (12 numbers a line), written atomically."""
    poses = _as_poses(path, poses)
    lines = [" ".join(f"{v:.12e}" for v in T[:3, :].reshape(-1)) for T in poses]
    write_text_atomic(path, "\n".join(lines) + "\n")


def read_tum(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """TUM file -> times (N,) seconds and (N,4,4) T_world_cam (quaternion normalised)."""
    from scipy.spatial.transform import Rotation  # scipy's import is slow; only TUM needs it

    rows = _read_rows(path, 8, "time tx ty tz qx qy qz qw")
    norms = np.linalg.norm(rows[:, 4:8], axis=1)
    if np.any(norms < 1e-9):
        i = int(np.argmax(norms < 1e-9))
        raise TrajectoryError(f"{path}: pose {i} (time {rows[i, 0]}) has a zero quaternion")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(rows[:, 4:8] / norms[:, None]).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    return rows[:, 0].copy(), poses


def write_tum(path: PathLike, times: np.ndarray, poses: np.ndarray) -> None:
    """times (N,) seconds and (N,4,4) T_world_cam -> TUM file `time tx ty tz qx qy qz qw`, written atomically."""
    from scipy.spatial.transform import Rotation

    poses = _as_poses(path, poses)
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    if len(times) != len(poses):
        raise TrajectoryError(f"{path}: {len(times)} times for {len(poses)} poses")
    quats = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x, y, z, w
    lines = [
        " ".join(f"{v:.9f}" if k == 0 else f"{v:.12e}" for k, v in enumerate([t, *T[:3, 3], *q]))
        for t, T, q in zip(times, poses, quats)
    ]
    write_text_atomic(path, "\n".join(lines) + "\n")


POSE_FORMATS = ("kitti", "tum")


def write_poses(path: PathLike, poses: np.ndarray, times: np.ndarray, fmt: str = "kitti") -> None:
    """(N,4,4) T_world_cam -> pose file in `fmt` (kitti, or tum with the (N,) times in seconds), atomically."""
    if fmt == "kitti":
        write_kitti_poses(path, poses)
    elif fmt == "tum":
        write_tum(path, times, poses)
    else:
        raise TrajectoryError(f"{path}: pose format {fmt!r} unknown (one of {', '.join(POSE_FORMATS)})")


def pair_nearest(queries: np.ndarray, stamps: np.ndarray, max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """For each query time the index of the nearest of the sorted `stamps` (the earlier on a tie) and whether it is
    within max_dt (a bag's images and scans, an estimate's poses and the truth's)."""
    right = np.clip(np.searchsorted(stamps, queries), 0, len(stamps) - 1)
    left = np.clip(right - 1, 0, len(stamps) - 1)
    nearest = np.where(np.abs(stamps[left] - queries) <= np.abs(stamps[right] - queries), left, right)
    return nearest, np.abs(stamps[nearest] - queries) <= max_dt
