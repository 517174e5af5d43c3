"""KITTI and TUM pose files: round trips, atomic writes, errors naming file and line."""

from __future__ import annotations

import numpy as np
import pytest

from plvo.data.trajectory import read_kitti_poses, read_tum, write_kitti_poses, write_tum
from plvo.errors import TrajectoryError
from plvo.geometry import se3


def _random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([se3.exp(np.concatenate([rng.normal(0, 50, 3), rng.normal(0, 1.0, 3)])) for _ in range(n)])


def test_kitti_round_trip(tmp_path):
    poses = _random_poses(20)
    path = tmp_path / "out" / "poses.txt"
    write_kitti_poses(path, poses)
    lines = path.read_text().splitlines()
    assert len(lines) == 20 and all(len(line.split()) == 12 for line in lines)
    back = read_kitti_poses(path)
    assert back.shape == (20, 4, 4)
    np.testing.assert_allclose(back, poses, rtol=0, atol=1e-9)
    assert [p.name for p in path.parent.iterdir()] == ["poses.txt"]  # no temporary file left


def test_kitti_accepts_3x4_and_skips_blank_and_comment_lines(tmp_path):
    poses = _random_poses(3, seed=1)
    write_kitti_poses(tmp_path / "a.txt", poses[:, :3, :])
    text = "# header\n" + (tmp_path / "a.txt").read_text().replace("\n", "\n\n", 1)
    (tmp_path / "b.txt").write_text(text)
    np.testing.assert_allclose(read_kitti_poses(tmp_path / "b.txt"), poses, atol=1e-9)


def test_tum_round_trip(tmp_path):
    poses = _random_poses(15, seed=2)
    times = np.arange(15) * 0.1 + 1e9
    write_tum(tmp_path / "t.txt", times, poses)
    t_back, p_back = read_tum(tmp_path / "t.txt")
    np.testing.assert_allclose(t_back, times, rtol=0, atol=1e-6)
    np.testing.assert_allclose(p_back, poses, rtol=0, atol=1e-9)
    assert all(len(line.split()) == 8 for line in (tmp_path / "t.txt").read_text().splitlines())


def test_tum_quaternion_order_is_xyzw(tmp_path):
    # 90 degrees about z: q = (0, 0, sin 45, cos 45) in x, y, z, w order
    (tmp_path / "t.txt").write_text("0.0 1 2 3 0 0 0.7071067811865476 0.7071067811865476\n")
    _, poses = read_tum(tmp_path / "t.txt")
    np.testing.assert_allclose(poses[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(poses[0, :3, 3], [1, 2, 3])


def test_missing_file_named(tmp_path):
    with pytest.raises(TrajectoryError, match=r"nope\.txt: no such pose file"):
        read_kitti_poses(tmp_path / "nope.txt")
    with pytest.raises(TrajectoryError, match=r"nope\.txt"):
        read_tum(tmp_path / "nope.txt")


def test_wrong_column_count_names_file_and_line(tmp_path):
    good = " ".join(["0"] * 12)
    path = tmp_path / "bad.txt"
    path.write_text(f"{good}\n{good}\n{' '.join(['0'] * 11)}\n")
    with pytest.raises(TrajectoryError, match=r"bad\.txt:3: expected 12 numbers .* got 11"):
        read_kitti_poses(path)
    path.write_text("0 1 2 3 0 0 0\n")
    with pytest.raises(TrajectoryError, match=r"bad\.txt:1: expected 8 numbers .* got 7"):
        read_tum(path)


def test_non_number_names_file_line_and_token(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text(" ".join(["0"] * 12) + "\n" + " ".join(["0"] * 5 + ["abc"] + ["0"] * 6) + "\n")
    with pytest.raises(TrajectoryError, match=r"bad\.txt:2: not a number: 'abc'"):
        read_kitti_poses(path)


def test_nan_and_empty_file_rejected(tmp_path):
    path = tmp_path / "nan.txt"
    path.write_text(" ".join(["nan"] + ["0"] * 11) + "\n")
    with pytest.raises(TrajectoryError, match=r"nan\.txt:1: NaN"):
        read_kitti_poses(path)
    (tmp_path / "empty.txt").write_text("\n# nothing\n")
    with pytest.raises(TrajectoryError, match=r"empty\.txt: no poses"):
        read_kitti_poses(tmp_path / "empty.txt")


def test_failed_write_leaves_existing_file_untouched(tmp_path):
    path = tmp_path / "poses.txt"
    write_kitti_poses(path, _random_poses(2))
    before = path.read_text()
    bad = _random_poses(3)
    bad[1, 0, 3] = np.nan
    with pytest.raises(TrajectoryError, match="pose 1"):
        write_kitti_poses(path, bad)
    with pytest.raises(TrajectoryError, match="2 times for 3 poses"):
        write_tum(path, np.zeros(2), _random_poses(3))
    assert path.read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses.txt"]


def test_real_ground_truth_reads(kitti_root):
    poses = read_kitti_poses(kitti_root / "poses" / "04.txt")
    assert poses.shape == (271, 4, 4)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-6)  # world = cam0 of frame 0
    # rotation blocks are rotations to the precision of the file
    R = poses[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-5)
