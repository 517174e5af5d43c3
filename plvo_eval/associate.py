"""Pose files of either format paired with their truth, for `plvo eval metric`.

The format is told by a file's column count (12: KITTI, 8: TUM `time tx ty tz qx qy qz qw`); the two never collide,
so no option names it. A KITTI file has no times: a truth may get them from a times file (`--gt-times`, or the KITTI
odometry `ROOT/sequences/NN/times.txt` of `ROOT/poses/NN.txt`, or a `times.txt` beside it as in a plvo folder
dataset). Pairing, in this order:
- both sides have times: each estimate pose takes the truth pose nearest in time, within max_dt (evo's association,
  made one-to-one: of two estimate poses nearest the same truth pose the closer keeps it). Times index any truth,
  also one sampled faster than the frames (motion capture), so a frame cut is not needed then;
- the estimate's frame numbers are known (a run's summary.json, `--frames`): the truth's lines are those frames (one
  pose a frame, as KITTI's poses/NN.txt);
- equal counts: line by line;
- else refused, naming the file and what would pair it.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from plvo.data.trajectory import _read_rows, pair_nearest, read_kitti_poses, read_tum
from plvo.errors import TrajectoryError

PathLike = str | os.PathLike[str]
FORMAT_BY_COLUMNS = {12: "kitti", 8: "tum"}
MAX_DT_S = 0.02  # evo's default association tolerance


@dataclass(frozen=True)
class PoseFile:
    """A pose file read: poses (N,4,4) T_world_cam; times (N,) seconds or None (KITTI without a times file);
    times_from: the times file a KITTI file's times were read from."""

    path: Path
    fmt: str
    poses: np.ndarray
    times: np.ndarray | None
    times_from: Path | None = None

    def __len__(self) -> int:
        return len(self.poses)


@dataclass(frozen=True)
class Pairing:
    """Truth and estimate poses paired (N,4,4) each; frames (N,) the dataset's frame numbers where known, else the
    estimate's line numbers from 0; times (N,) seconds or None; how: how they were paired, a clause to follow the
    estimate's name ("" for two files of equal length read line by line without times)."""

    gt: np.ndarray
    est: np.ndarray
    frames: np.ndarray
    times: np.ndarray | None
    how: str


def pose_format(path: PathLike) -> str:
    """'kitti' or 'tum' by the column count of the file's first pose line (the reader then holds every line to it)."""
    path = Path(path)
    if path.is_dir():
        raise TrajectoryError(f"{path}: is a folder, not a pose file")
    try:
        with path.open() as f:
            for lineno, line in enumerate(f, start=1):
                fields = line.strip().replace(",", " ").split()
                if not fields or fields[0].startswith("#"):
                    continue
                fmt = FORMAT_BY_COLUMNS.get(len(fields))
                if fmt is None:
                    raise TrajectoryError(f"{path}:{lineno}: {len(fields)} numbers: neither a KITTI pose (12 numbers) "
                                          "nor a TUM line (8: time tx ty tz qx qy qz qw)")
                return fmt
    except FileNotFoundError:
        raise TrajectoryError(f"{path}: no such pose file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise TrajectoryError(f"{path}: cannot read pose file ({exc})") from None
    raise TrajectoryError(f"{path}: no poses in file")


def read_pose_file(path: PathLike) -> PoseFile:
    """A KITTI or TUM file, told by its columns (times None for KITTI)."""
    path = Path(path)
    fmt = pose_format(path)
    if fmt == "kitti":
        return PoseFile(path, fmt, read_kitti_poses(path), None)
    times, poses = read_tum(path)
    return PoseFile(path, fmt, poses, times)


def read_times(path: PathLike, n: int) -> np.ndarray:
    """A times file (one time in seconds a line, as KITTI's times.txt) -> the first n times; it may hold more, as
    plvo's KITTI loader allows, but not fewer."""
    values = _read_rows(path, 1, "a time in seconds", kind="times")[:, 0]
    if len(values) < n:
        raise TrajectoryError(f"{path}: {len(values)} times for {n} poses")
    return values[:n]


def times_beside(path: PathLike) -> Path | None:
    """The times file of a KITTI pose file when there is one: ROOT/sequences/NN/times.txt for ROOT/poses/NN.txt (the
    odometry layout), else a times.txt in the same folder (a plvo folder dataset's poses.txt)."""
    path = Path(path)
    candidates = [path.parent / "times.txt"]
    if path.parent.name == "poses":
        candidates.insert(0, path.parent.parent / "sequences" / path.stem / "times.txt")
    return next((c for c in candidates if c.is_file()), None)


def with_times(pose_file: PoseFile, times_file: PathLike) -> PoseFile:
    """A KITTI file given the times of its lines from times_file."""
    if pose_file.fmt != "kitti":
        raise TrajectoryError(f"--gt-times {times_file}: {pose_file.path} is a TUM file, with its own times")
    return replace(pose_file, times=read_times(times_file, len(pose_file)), times_from=Path(times_file))


def associate(est_times: np.ndarray, gt_times: np.ndarray, max_dt: float = MAX_DT_S) -> tuple[np.ndarray, np.ndarray]:
    """(M,) estimate and (N,) truth times -> (i_est, i_gt) index pairs, i_est increasing: each estimate pose with the
    truth pose nearest in time if within max_dt, one-to-one (the closer of two estimate poses keeps a truth pose)."""
    est_times, gt_times = np.asarray(est_times, np.float64), np.asarray(gt_times, np.float64)
    if len(est_times) == 0 or len(gt_times) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.argsort(gt_times, kind="stable")
    g = gt_times[order]
    nearest, within = pair_nearest(est_times, g, max_dt)
    dt = np.abs(g[nearest] - est_times)
    cand = np.flatnonzero(within)
    by_truth = cand[np.lexsort((dt[cand], nearest[cand]))]  # per truth pose, its closest estimate pose first
    _, first = np.unique(nearest[by_truth], return_index=True)
    i_est = np.sort(by_truth[first])
    return i_est.astype(np.int64), order[nearest[i_est]].astype(np.int64)


def frames_text(frames: Sequence[int] | np.ndarray) -> str:
    """Frame numbers as the user gives them: 'A:B' when consecutive, else 'A..B (n frames)'."""
    f = np.asarray(frames)
    if len(f) == 0:
        return "none"
    if len(f) == 1 or np.all(np.diff(f) == 1):
        return f"{f[0]}:{f[-1] + 1}"
    return f"{f[0]}..{f[-1]} ({len(f)} frames)"


def pair_by_time(gt: PoseFile, est: PoseFile, frames: np.ndarray | None, max_dt: float) -> Pairing:
    """Both sides with times: associated by time (see associate); refused below 2 pairs."""
    assert gt.times is not None and est.times is not None
    i_est, i_gt = associate(est.times, gt.times, max_dt)
    if len(i_est) < 2:
        raise TrajectoryError(
            f"{est.path}: {len(i_est)} of {len(est)} poses have a truth pose in {gt.path} within {max_dt:g} s "
            f"(estimate times {est.times.min():.3f}..{est.times.max():.3f} s, truth "
            f"{gt.times.min():.3f}..{gt.times.max():.3f} s); both must count time on the same clock, or raise --max-dt")
    source = f" (truth times from {gt.times_from})" if gt.times_from is not None else ""
    how = f"paired by time{source}: {len(i_est)} of {len(est)} estimate poses matched a truth pose within {max_dt:g} s"
    frames_out = (frames if frames is not None else np.arange(len(est)))[i_est]
    return Pairing(gt.poses[i_gt], est.poses[i_est], frames_out, est.times[i_est], how)


def pair_by_frames(gt: PoseFile, est: PoseFile, frames: np.ndarray, frames_from: str) -> Pairing:
    """The truth's lines cut to the estimate's frame numbers (one truth pose a frame)."""
    frames = np.asarray(frames, dtype=np.int64)
    if len(frames) != len(est):
        raise TrajectoryError(f"{est.path}: {len(est)} poses, but {frames_from} gives {len(frames)} frames")
    if len(frames) and frames.max() >= len(gt):
        raise TrajectoryError(f"{gt.path}: {len(gt)} poses (frames 0..{len(gt) - 1}), but {est.path} holds frame "
                              f"{frames.max()} ({frames_from})")
    times = est.times if est.times is not None else (gt.times[frames] if gt.times is not None else None)
    how = f"truth cut to frames {frames_text(frames)} of {gt.path} ({frames_from})"
    return Pairing(gt.poses[frames], est.poses, frames, times, how)


def pair_by_lines(gt: PoseFile, est: PoseFile, frames: np.ndarray | None = None, why: str = "") -> Pairing:
    """Line by line, the counts being equal (the caller has said why that is right)."""
    if len(gt) != len(est):
        raise TrajectoryError(f"{est.path}: {len(est)} poses, but the ground truth {gt.path} has {len(gt)}")
    times = est.times if est.times is not None else gt.times
    frames_out = np.asarray(frames, dtype=np.int64) if frames is not None else np.arange(len(est))
    return Pairing(gt.poses, est.poses, frames_out, times, why)


def pair(gt: PoseFile, est: PoseFile, frames: np.ndarray | None = None, frames_from: str = "",
         max_dt: float = MAX_DT_S) -> Pairing:
    """An estimate and its truth paired (module docstring: by time, by frame numbers, line by line, else refused).
    frames: the dataset frame numbers of the estimate's lines when known, frames_from where they were read."""
    if gt.times is not None and est.times is not None:
        return pair_by_time(gt, est, frames, max_dt)
    if frames is not None:
        return pair_by_frames(gt, est, frames, frames_from)
    if len(gt) == len(est):
        why = "" if gt.fmt == est.fmt else "paired line by line (equal counts; the KITTI side has no times)"
        return pair_by_lines(gt, est, why=why)
    if gt.fmt == est.fmt == "kitti":
        raise TrajectoryError(f"{est.path}: {len(est)} poses, but the ground truth {gt.path} has {len(gt)} (for a "
                              "part of the sequence give --frames A:B)")
    if gt.times is None:
        raise TrajectoryError(
            f"{gt.path}: KITTI poses have no times to pair with the {len(est)} TUM poses of {est.path} "
            f"({len(gt)} != {len(est)}); give --gt-times FILE (the sequence's times.txt) or --frames A:B")
    raise TrajectoryError(
        f"{est.path}: KITTI poses have no times to pair with the {len(gt)} TUM poses of {gt.path} "
        f"({len(est)} != {len(gt)}); give --frames A:B (the frames run, lines of {gt.path}) or the estimate in TUM "
        "format (plvo-viz --format tum)")
