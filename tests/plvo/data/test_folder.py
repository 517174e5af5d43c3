"""Plain folder layout: images/ + scans/ (.bin, .pcd, .ply) + calib.yaml + times.txt + poses.txt (KITTI
or TUM) read back the frames and ground truth of the KITTI layout they were made from; distorted images are
rectified; bad folders get one line."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from bag_writer import distort_image

from plvo.data.calib_yaml import read_calib_yaml, write_calib_yaml
from plvo.data.camera_model import CameraModel
from plvo.data.folder import FolderDataset
from plvo.data.kitti import KittiOdometry
from plvo.data.pointcloud import write_pcd
from plvo.data.registry import open_dataset
from plvo.data.trajectory import write_kitti_poses, write_tum
from plvo.errors import CalibrationError, DatasetError

N = 6


@pytest.fixture(scope="module")
def town(synth_seq):
    return KittiOdometry(synth_seq, "00", frames=slice(2, 2 + N))  # not from frame 0: ground truth is re-based


def _write_folder(root, ds, scan_kind: str = "mixed", gt: str = "kitti"):
    (root / "images").mkdir(parents=True)
    (root / "scans").mkdir()
    for i in range(len(ds)):
        f = ds[i]
        cv2.imwrite(str(root / "images" / f"frame_{i:04d}.png"), f.image)
        kind = ["bin", "pcd", "ply"][i % 3] if scan_kind == "mixed" else scan_kind
        path = root / "scans" / f"frame_{i:04d}.{kind}"
        if kind == "bin":
            f.scan.astype(np.float32).tofile(path)
        elif kind == "pcd":
            write_pcd(path, f.scan)
        else:
            import open3d as o3d

            cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(f.scan[:, :3]))
            cloud.point.intensity = o3d.core.Tensor(f.scan[:, 3:4])
            o3d.t.io.write_point_cloud(str(path), cloud)
    c = ds.calib
    write_calib_yaml(root / "calib.yaml", CameraModel(c.width, c.height, c.K), c.T_cam_velo)
    times = 1000.0 + ds.times
    (root / "times.txt").write_text("".join(f"{t:.6f}\n" for t in times))
    if gt == "kitti":
        write_kitti_poses(root / "poses.txt", ds.gt_T_world_cam)
    elif gt == "tum":
        write_tum(root / "poses.txt", times + 0.003, ds.gt_T_world_cam)  # stamps a few ms off, as recorded
    return root


@pytest.mark.parametrize("gt", ["kitti", "tum"])
def test_folder_frames_and_ground_truth_equal_kitti(town, tmp_path, gt):
    root = _write_folder(tmp_path / "run", town, gt=gt)
    ds = open_dataset(root, None)  # as `plvo-viz --root run/` does
    assert isinstance(ds, FolderDataset) and len(ds) == N and ds.sequence == "run"
    np.testing.assert_allclose(ds.calib.K, town.calib.K, atol=1e-9)
    np.testing.assert_allclose(ds.calib.T_cam_velo, town.calib.T_cam_velo, atol=1e-9)
    np.testing.assert_allclose(ds.times, 1000.0 + town.times, atol=1e-6)
    want_gt = np.linalg.inv(town.gt_T_world_cam[0]) @ town.gt_T_world_cam  # world = first frame's camera
    np.testing.assert_allclose(ds.gt_T_world_cam, want_gt, atol=1e-6)
    for i in range(N):  # .bin, .pcd and .ply scans
        got, want = ds[i], town[i]
        np.testing.assert_array_equal(got.image, want.image)
        np.testing.assert_allclose(np.unique(got.scan, axis=0), np.unique(want.scan, axis=0), atol=1e-6)


def test_folder_without_times_or_poses(town, tmp_path):
    root = _write_folder(tmp_path / "bare", town, scan_kind="bin", gt="none")
    (root / "times.txt").unlink()
    ds = FolderDataset(root, frames=slice(1, 4))
    assert ds.gt_T_world_cam is None and ds.frame_indices == (1, 2, 3)
    np.testing.assert_allclose(ds.times, [0.1, 0.2, 0.3])


def test_bad_folders_one_line(town, tmp_path):
    root = _write_folder(tmp_path / "bad", town, scan_kind="bin")
    (root / "scans" / "frame_0003.bin").unlink()
    with pytest.raises(DatasetError, match=r"6 images in images/ but 5 scans in scans/"):
        FolderDataset(root)
    root = _write_folder(tmp_path / "nocal", town, scan_kind="bin")
    (root / "calib.yaml").unlink()
    with pytest.raises(CalibrationError, match=r"nocal/calib.yaml: calibration file not found"):
        FolderDataset(root)
    (root / "calib.yaml").write_text("image_width: 10\nimage_height: 5\ncamera_matrix: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n")
    with pytest.raises(CalibrationError, match=r"no 'T_cam_lidar'"):
        FolderDataset(root)
    root = _write_folder(tmp_path / "tum", town, scan_kind="bin", gt="tum")
    (root / "times.txt").write_text("".join(f"{5000 + 0.1 * k:.3f}\n" for k in range(N)))
    with pytest.raises(DatasetError, match=r"poses.txt: no pose within 0.01 s of frame 0"):
        FolderDataset(root)


def test_distorted_images_are_rectified(town, tmp_path):
    c = town.calib
    D = np.array([-0.30, 0.10, 0.0005, -0.0003, 0.0])
    root = _write_folder(tmp_path / "lens", town, scan_kind="bin")
    for i in range(N):
        cv2.imwrite(str(root / "images" / f"frame_{i:04d}.png"), distort_image(town[i].image, c.K, D))
    write_calib_yaml(root / "calib.yaml", CameraModel(c.width, c.height, c.K, D=D, P=c.K), c.T_cam_velo)
    cf = read_calib_yaml(root / "calib.yaml")
    assert cf.camera.distorted and cf.camera.needs_rectification
    ds = FolderDataset(root)
    np.testing.assert_allclose(ds.calib.K, c.K)  # the projection matrix given is the rectified camera
    ideal, raw = town[3].image.astype(float), cv2.imread(str(root / "images" / "frame_0003.png"), 0).astype(float)
    got = ds[3].image.astype(float)
    inner = (slice(40, c.height - 40), slice(120, c.width - 120))  # away from the borders the lens cut off
    err_rectified = np.abs(got - ideal)[inner].mean()
    err_raw = np.abs(raw - ideal)[inner].mean()
    print(f"mean abs grey error: rectified {err_rectified:.2f}, raw {err_raw:.2f}")
    assert err_rectified < 4.0 and err_rectified < 0.3 * err_raw, (err_rectified, err_raw)


def test_readme_calibration_example_is_kitti_04(kitti_root, tmp_path):
    """The README's calibration YAML reads, and is sequence 04's calibration."""
    import re
    from pathlib import Path

    readme = Path(__file__).resolve().parents[3] / "README.md"
    block = re.search(r"```yaml\n(.*?)```", readme.read_text(), re.S).group(1)
    (tmp_path / "c.yaml").write_text(block)
    cf = read_calib_yaml(tmp_path / "c.yaml")
    ref = KittiOdometry(kitti_root, "04", frames=slice(0, 1)).calib
    np.testing.assert_allclose(cf.camera.K, ref.K, atol=1e-9)
    np.testing.assert_allclose(cf.T_cam_lidar, ref.T_cam_velo, atol=1e-6)
