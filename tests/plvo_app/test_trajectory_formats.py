"""Trajectories in KITTI and TUM formats: plvo-viz --format writes either, TUM with the data's own
timestamps, and evo reads both back."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
from evo.tools import file_interface  # the test extras' evo: an independent reader of both formats

from plvo.data.trajectory import write_poses
from plvo.errors import TrajectoryError
from plvo.geometry import se3


def _poses(n: int) -> np.ndarray:
    rng = np.random.default_rng(3)
    return np.stack([se3.exp(np.r_[rng.normal(0, 2, 3), rng.normal(0, 0.3, 3)]) for _ in range(n)])


def test_evo_reads_both_formats(tmp_path):
    poses, times = _poses(7), 1_700_000_000.0 + 0.1037 * np.arange(7)
    write_poses(tmp_path / "k.txt", poses, times, "kitti")
    write_poses(tmp_path / "t.txt", poses, times, "tum")
    kitti = file_interface.read_kitti_poses_file(str(tmp_path / "k.txt"))
    tum = file_interface.read_tum_trajectory_file(str(tmp_path / "t.txt"))
    np.testing.assert_allclose(np.stack(kitti.poses_se3), poses, atol=1e-9)
    np.testing.assert_allclose(np.stack(tum.poses_se3), poses, atol=1e-9)
    np.testing.assert_allclose(tum.timestamps, times, atol=1e-6)
    with pytest.raises(TrajectoryError, match="pose format 'csv' unknown"):
        write_poses(tmp_path / "x.txt", poses, times, "csv")


class _System:
    """What plvo-viz's result writer reads from a finished System."""

    frames_done = 4
    timings = {"track": [0.01] * 4}

    def __init__(self, poses: np.ndarray) -> None:
        self._poses = poses

    def timing_summary(self) -> dict:
        return {}

    def poses_cam0(self, frame_indices) -> np.ndarray:
        return self._poses[list(frame_indices)]


class _Dataset:
    frame_indices = (0, 1, 2, 3)
    times = np.array([12.5, 12.6, 12.7, 12.8])

    def __len__(self) -> int:
        return 4


@pytest.mark.parametrize("fmt", ["kitti", "tum"])
def test_viz_format_option(tmp_path, fmt):
    from plvo_app import cmd_viz

    parser = argparse.ArgumentParser()
    cmd_viz.add_arguments(parser)
    args = parser.parse_args(["--format", fmt])
    poses = _poses(4)
    cmd_viz._write_poses(tmp_path, _System(poses), _Dataset(), args.format)
    path = str(tmp_path / "poses.txt")
    if fmt == "tum":
        traj = file_interface.read_tum_trajectory_file(path)
        np.testing.assert_allclose(traj.timestamps, _Dataset.times, atol=1e-9)  # the data's stamps
    else:
        traj = file_interface.read_kitti_poses_file(path)
    np.testing.assert_allclose(np.stack(traj.poses_se3), poses, atol=1e-9)
