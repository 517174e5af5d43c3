"""The followed trajectory of a KITTI twin: a KITTI pose file (cam0), an optional frame range, and the town frame.

The twin's world is built in the followed file's own world frame (cam0 of its frame 0), turned z-up: the "town"
frame of the generator is T_TOWN_KITTI @ kitti (x right, y forward, z up at KITTI's frame 0). Twins of different
slices of the same file therefore share one world. The twin's poses file holds the followed rows themselves when
the range starts at 0, and the rows re-based on frame A (inv(T_A) @ T_i, so frame A is the origin) otherwise.
Poses between frames (the lidar's rolling sweep) are interpolated: linear in position, slerp in rotation.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from plvo.data.trajectory import read_kitti_poses
from plvo.errors import SynthError, TrajectoryError
from plvo_synth.sensors import CAMERA_HEIGHT_M, FRAME_DT

# KITTI's world (cam0 of frame 0: x right, y down, z forward) -> the generator's z-up town frame.
T_TOWN_KITTI = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])
MIN_FRAMES = 2
CONTEXT_M = 100.0  # the world is built this far before and after the range: what the sensors see past its ends


@dataclass(frozen=True)
class FollowedPath:
    """T_kitti_cam: (N,4,4) the followed poses of frames A..B-1 in the file's world; first: A; rows: the file's
    text lines of those frames (written verbatim when A == 0); T_town_cam: (N,4,4) the same in the town frame."""

    source: str
    first: int
    T_kitti_cam: np.ndarray
    rows: tuple[str, ...]
    context_road: np.ndarray  # (K,3) town-frame road points CONTEXT_M before and after the range (world building)
    context_first: int  # index of frame A's road point in context_road (frames A..B-1 follow it one by one)
    context_real: np.ndarray  # (K,) bool: a frame of the file (False: the straight continuation past its ends)
    file_road: np.ndarray  # (F,3) town-frame road points of every frame of the file
    file_speed: np.ndarray  # (F,) m/s at each frame of the file (zones)

    @property
    def n_frames(self) -> int:
        return len(self.T_kitti_cam)

    @property
    def T_town_cam(self) -> np.ndarray:
        return T_TOWN_KITTI[None] @ self.T_kitti_cam

    @property
    def T_world_cam(self) -> np.ndarray:
        """The twin's ground truth: the followed poses re-based on the first frame (the rows themselves if A = 0)."""
        if self.first == 0:
            return self.T_kitti_cam.copy()
        return np.linalg.inv(self.T_kitti_cam[0])[None] @ self.T_kitti_cam

    @property
    def T_town_world(self) -> np.ndarray:
        """Town frame <- the twin's world frame."""
        if self.first == 0:
            return T_TOWN_KITTI.copy()
        return T_TOWN_KITTI @ self.T_kitti_cam[0]

    def pose_file_text(self) -> str:
        if self.first == 0:
            return "".join(r + "\n" for r in self.rows)
        rows = self.T_world_cam[:, :3, :].reshape(self.n_frames, 12)
        return "".join(" ".join(f"{x:.9e}" for x in row) + "\n" for row in rows)

    def road_points(self) -> np.ndarray:
        """(N,3) the road surface under the camera (town frame): CAMERA_HEIGHT_M down the camera's y axis."""
        T = self.T_town_cam
        return T[:, :3, 3] + CAMERA_HEIGHT_M * T[:, :3, 1]

    def speeds(self) -> np.ndarray:
        """(N,) m/s between neighbouring frames."""
        p = self.T_kitti_cam[:, :3, 3]
        step = np.linalg.norm(np.diff(p, axis=0), axis=1) / FRAME_DT
        return np.concatenate([step[:1], step]) if len(step) else np.zeros(1)


def parse_range(text: str | None, n_rows: int, source: str) -> tuple[int, int]:
    """'A:B' (B exclusive; either may be empty) -> (A, B) within the file's n_rows; None -> all rows."""
    if text is None:
        return 0, n_rows
    parts = str(text).split(":")
    if len(parts) != 2:
        raise SynthError(f"--frames {text!r}: with --follow, expected A:B (first frame, end exclusive), e.g. 0:200")
    try:
        a = int(parts[0]) if parts[0].strip() else 0
        b = int(parts[1]) if parts[1].strip() else n_rows
    except ValueError:
        raise SynthError(f"--frames {text!r}: A and B must be integers") from None
    if not 0 <= a < b <= n_rows:
        raise SynthError(f"--frames {text!r}: {source} has {n_rows} poses; need 0 <= A < B <= {n_rows}")
    if b - a < MIN_FRAMES:
        raise SynthError(f"--frames {text!r}: at least {MIN_FRAMES} frames")
    return a, b


def load_followed(path: str | Path, frames: str | None = None) -> FollowedPath:
    """Read a KITTI pose file and cut frames A:B; SynthError names the file, line or range that is wrong."""
    path = Path(path)
    try:
        poses = read_kitti_poses(path)
    except TrajectoryError as exc:
        raise SynthError(f"--follow: {exc}") from None
    lines = [ln.strip() for ln in path.read_text().splitlines() if ln.strip() and not ln.strip().startswith("#")]
    return followed(poses, str(path), frames, lines)


def followed(poses: np.ndarray, source: str, frames: str | None = None,
             lines: list[str] | None = None) -> FollowedPath:
    """(F,4,4) KITTI cam0 poses at 10 Hz (a pose file's, or a raw drive's from its oxts) cut to frames A:B; lines:
    the pose file's rows (None: written from the poses). SynthError names the line (frame) that is wrong."""
    where = "line" if lines is not None else "frame"
    first_line = 1 if lines is not None else 0
    a, b = parse_range(frames, len(poses), source)
    R = poses[a:b, :3, :3]
    bad = np.flatnonzero(np.abs(np.linalg.det(R) - 1.0) > 1e-3)
    if len(bad):
        raise SynthError(f"{source}: {where} {a + bad[0] + first_line}: the rotation is not a rotation "
                         f"(det {np.linalg.det(R[bad[0]]):.4f})")
    step = np.linalg.norm(np.diff(poses[a:b, :3, 3], axis=0), axis=1)
    if len(step) and step.max() > 6.0:
        k = int(np.argmax(step))
        raise SynthError(f"{source}: {where} {a + k + 1 + first_line}: a jump of {step[k]:.1f} m in one frame "
                         "(> 60 m/s at 10 Hz)")
    if lines is None:
        lines = [" ".join(f"{x:.9e}" for x in T[:3].ravel()) for T in poses]
    road = _road(poses)
    step = np.linalg.norm(np.diff(road, axis=0), axis=1) / FRAME_DT
    speed = np.concatenate([step[:1], step]) if len(step) else np.zeros(1)
    context, first, real = _context(poses, a, b)
    return FollowedPath(source, a, poses[a:b].copy(), tuple(lines[a:b]), context, first, real, road, speed)


def _road(T_kitti_cam: np.ndarray) -> np.ndarray:
    T = T_TOWN_KITTI[None] @ T_kitti_cam
    return T[:, :3, 3] + CAMERA_HEIGHT_M * T[:, :3, 1]


def _context(poses: np.ndarray, a: int, b: int) -> tuple[np.ndarray, int, np.ndarray]:
    """Road points of the file from CONTEXT_M before frame A to CONTEXT_M after frame B-1, continued straight
    along the end headings where the file ends sooner."""
    road = _road(poses)
    step = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(road, axis=0), axis=1))])
    lo = int(np.searchsorted(step, step[a] - CONTEXT_M))
    hi = int(np.searchsorted(step, step[b - 1] + CONTEXT_M, side="right"))
    out = road[lo:hi]
    parts = [out]
    real = [np.ones(len(out), bool)]
    first = a - lo
    for end, sign in ((0, -1.0), (len(road) - 1, 1.0)):
        missing = CONTEXT_M - abs(step[end] - step[a if sign < 0 else b - 1])
        if missing <= 0:
            continue
        heading = T_TOWN_KITTI[:3, :3] @ poses[end, :3, 2]
        heading[2] = 0.0
        heading /= max(np.linalg.norm(heading), 1e-9)
        s = np.arange(2.0, missing + 2.0, 2.0)[:, None]
        extra = road[end] + sign * s * heading
        if sign < 0:
            parts, real = [extra[::-1], *parts], [np.zeros(len(extra), bool), *real]
            first += len(extra)
        else:
            parts, real = [*parts, extra], [*real, np.zeros(len(extra), bool)]
    return np.concatenate(parts), first, np.concatenate(real)


class PoseInterpolator:
    """T_town(t) of the camera at any time t (s, frame i at i * FRAME_DT), extrapolated past the ends."""

    def __init__(self, T: np.ndarray) -> None:
        self.T = np.asarray(T, np.float64)
        n = len(self.T)
        self.times = np.arange(n) * FRAME_DT
        self._rot = Rotation.from_matrix(self.T[:, :3, :3])
        self._slerp = Slerp(self.times, self._rot) if n >= 2 else None

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """(K,) times -> (K,4,4) poses."""
        t = np.atleast_1d(np.asarray(t, np.float64))
        n = len(self.T)
        i = np.clip(np.floor(t / FRAME_DT).astype(np.int64), 0, n - 2)
        w = (t - self.times[i]) / FRAME_DT  # may leave [0, 1] at the ends: linear extrapolation
        p = self.T[i, :3, 3] * (1.0 - w)[:, None] + self.T[i + 1, :3, 3] * w[:, None]
        inside = np.clip(t, self.times[0], self.times[-1])
        assert self._slerp is not None, "a trajectory of one pose has no motion to interpolate"
        R = self._slerp(inside).as_matrix()
        out_lo, out_hi = t < self.times[0], t > self.times[-1]
        for mask, k in ((out_lo, 0), (out_hi, n - 2)):  # extrapolate the rotation with the end step's rate
            if mask.any():
                rel = (self._rot[k].inv() * self._rot[k + 1]).as_rotvec()
                base = self._rot[k] if k == 0 else self._rot[k + 1]
                dt = (t[mask] - (self.times[0] if k == 0 else self.times[-1])) / FRAME_DT
                R[mask] = (base * Rotation.from_rotvec(dt[:, None] * rel[None])).as_matrix()
        out = np.tile(np.eye(4), (len(t), 1, 1))
        out[:, :3, :3], out[:, :3, 3] = R, p
        return out
