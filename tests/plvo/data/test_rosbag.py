"""ROS 1 / ROS 2 bags: bags written with rosbags' writers from a synthetic town sequence and from the
real 04 frames read back equal to the KITTI layout they came from; a short pipeline run on a bag gives the KITTI
run's trajectory; bad bags get one line naming the bag, topic or field.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from bag_writer import BASE_S, SCAN_LAG_S, BagSpec, distort_image, write_bag

from plvo.config import SystemConfig, merge
from plvo.data.calib_yaml import write_calib_yaml
from plvo.data.camera_model import CameraModel
from plvo.data.dataset import SourceOptions
from plvo.data.kitti import KittiOdometry
from plvo.data.registry import open_dataset
from plvo.data.rosbag import RosbagDataset
from plvo.errors import CalibrationError, DatasetError

TOWN_FRAMES = 12

# (id, spec, calibration by file): ROS 1 and 2, sqlite3 and mcap, raw and PNG-compressed images, clouds with and
# without per-point time, calibration by CameraInfo + /tf_static and by YAML
VARIANTS = [
    ("ros1_raw_xyzi_info", BagSpec(ros=1), False),
    ("ros1_png_ouster_yaml", BagSpec(ros=1, compressed=True, cloud_layout="ouster", camera_info=False, tf=False), True),
    ("ros2_raw_time_info", BagSpec(ros=2, cloud_layout="padded_time"), False),
    ("ros2_png_xyzi_yaml", BagSpec(ros=2, compressed=True, camera_info=False, tf=False), True),
    ("mcap_png_time_info", BagSpec(ros=2, storage="mcap", compressed=True, cloud_layout="padded_time"), False),
]


@pytest.fixture(scope="module")
def town(synth_seq):
    return KittiOdometry(synth_seq, "00", frames=slice(0, TOWN_FRAMES))


def _calib_file(tmp_path, dataset) -> str:
    c = dataset.calib
    path = tmp_path / "calib.yaml"
    write_calib_yaml(path, CameraModel(c.width, c.height, c.K), c.T_cam_velo, c.lidar_elevation_offset_deg)
    return str(path)


def _bag_path(tmp_path, name: str, spec: BagSpec):
    return tmp_path / (f"{name}.bag" if spec.ros == 1 else name)


def _open_variant(tmp_path, dataset, name, spec, by_file) -> RosbagDataset:
    bag = write_bag(_bag_path(tmp_path, name, spec), dataset, spec)
    opts = SourceOptions(calib=_calib_file(tmp_path, dataset) if by_file else None)
    return open_dataset(bag, None, options=opts)  # through the registry, as `plvo-viz --root BAG` does


def point_set(scan: np.ndarray) -> np.ndarray:
    """Rows in lexicographic order: two scans are equal as point sets when these are equal."""
    return scan[np.lexsort(scan.T[::-1])]


def _assert_same_frames(bag: RosbagDataset, ref: KittiOdometry, has_time: bool, offset_deg: float) -> None:
    assert len(bag) == len(ref)
    np.testing.assert_allclose(bag.calib.K, ref.calib.K, atol=1e-6)
    np.testing.assert_allclose(bag.calib.T_cam_velo, ref.calib.T_cam_velo, atol=1e-6)
    assert (bag.calib.width, bag.calib.height) == (ref.calib.width, ref.calib.height)
    assert bag.calib.lidar_elevation_offset_deg == pytest.approx(offset_deg)
    np.testing.assert_allclose(bag.times, BASE_S + ref.times, atol=1e-6)
    for i in range(len(ref)):
        got, want = bag[i], ref[i]
        assert got.index == i
        np.testing.assert_array_equal(got.image, want.image)
        assert got.scan.shape == want.scan.shape
        np.testing.assert_array_equal(point_set(got.scan), point_set(want.scan))
        if has_time:
            assert got.scan_time is not None and len(got.scan_time) == len(got.scan)
            sweep = got.scan_time - SCAN_LAG_S  # relative to the frame's (image's) time; the scan is stamped later
            assert sweep.min() >= -1e-6 and sweep.max() <= 0.1 + 1e-6  # one 10 Hz sweep
            assert np.ptp(got.scan_time) > 0.09
            assert not got.scan_compensated  # each return at its own time: registration deskews it
        else:
            assert got.scan_time is None and got.scan_compensated


@pytest.mark.parametrize("name, spec, by_file", VARIANTS, ids=[v[0] for v in VARIANTS])
def test_town_bag_frames_equal_kitti_layout(town, tmp_path, name, spec, by_file):
    ref = KittiOdometry(town_root(town), "00", frames=slice(0, 6))
    bag = _open_variant(tmp_path, ref, name, spec, by_file)
    assert bag.name == "rosbag" and bag.image_topic == spec.image_topic and bag.cloud_topic == spec.cloud_topic
    _assert_same_frames(bag, ref, spec.cloud_layout != "xyzi", 0.0)


@pytest.mark.kitti
@pytest.mark.parametrize("name, spec, by_file", [VARIANTS[0], VARIANTS[3], VARIANTS[4]],
                         ids=[VARIANTS[k][0] for k in (0, 3, 4)])
def test_real_04_bag_frames_equal_kitti_layout(kitti_root, tmp_path, name, spec, by_file):
    ref = KittiOdometry(kitti_root, "04", frames=slice(0, 4))
    bag = _open_variant(tmp_path, ref, name, spec, by_file)
    # the HDL-64E's elevation offset travels in the YAML; CameraInfo + TF cannot carry it
    _assert_same_frames(bag, ref, spec.cloud_layout != "xyzi", ref.calib.lidar_elevation_offset_deg if by_file else 0)


def test_frame_selection_and_pickling(town, tmp_path):
    import pickle

    bag = write_bag(tmp_path / "b.bag", town, BagSpec(ros=1))
    ds = RosbagDataset(bag, frames=slice(3, 9, 2))
    assert ds.frame_indices == (3, 5, 7) and len(ds) == 3
    again = pickle.loads(pickle.dumps(ds))  # the reader is reopened where the dataset is used (eval workers)
    np.testing.assert_array_equal(again[1].image, town[5].image)
    with pytest.raises(IndexError):
        ds[3]


def _compare_runs(ref, bag, bound_m: float = 0.01) -> float:
    from plvo.runtime.run import run_dataset

    # the town's scans are taken at one instant; the bag's sweep times are there to test their fields, so the bag's
    # scans are not deskewed either (they would be by default: a bag with per-point times is a raw sweep)
    cfg = merge(SystemConfig(), {"backend": {"concurrent": False}, "registration": {"deskew": "off"}})
    ref_run, bag_run = run_dataset(ref, cfg), run_dataset(bag, cfg)
    assert ref_run.n_keyframes >= 2 and ref_run.n_lost == 0
    drift = np.linalg.norm(ref_run.poses[-1, :3, 3] - ref.gt_T_world_cam[-1, :3, 3])
    assert drift < 1.0  # the run itself is sane
    gap = np.linalg.norm(bag_run.poses[:, :3, 3] - ref_run.poses[:, :3, 3], axis=1).max()
    assert gap < bound_m, f"bag run differs from the KITTI-layout run by up to {gap:.4f} m"
    return gap


@pytest.mark.slow
@pytest.mark.parametrize("name, spec, by_file", [VARIANTS[1], VARIANTS[4]], ids=[VARIANTS[k][0] for k in (1, 4)])
def test_pipeline_on_town_bag_matches_kitti_layout_run(town, tmp_path, name, spec, by_file):
    _compare_runs(town, _open_variant(tmp_path, town, name, spec, by_file))


@pytest.mark.slow
@pytest.mark.kitti
@pytest.mark.parametrize("name, spec, by_file", [VARIANTS[0], VARIANTS[3]], ids=[VARIANTS[k][0] for k in (0, 3)])
def test_pipeline_on_real_04_bag_matches_kitti_layout_run(kitti_root, tmp_path, name, spec, by_file):
    ref = KittiOdometry(kitti_root, "04", frames=slice(0, TOWN_FRAMES))
    bag = write_bag(_bag_path(tmp_path, name, spec), ref, spec)
    # CameraInfo + TF cannot carry the HDL-64E's elevation offset: the user gives it (--lidar-elevation-offset)
    opts = SourceOptions(calib=_calib_file(tmp_path, ref) if by_file else None,
                         lidar_elevation_offset_deg=None if by_file else ref.calib.lidar_elevation_offset_deg)
    # A calibration file gives the KITTI run's numbers to the bit (measured gap 0); CameraInfo and TF carry them in
    # their own rounding, which moves the 12 frames' trajectory by millimetres (5.6 mm at 254ee23, 10.3 mm at 0af3d75,
    # whose rotation weight follows the lidar's heading more closely).
    _compare_runs(ref, RosbagDataset(bag, options=opts), 0.001 if by_file else 0.025)


# --- bad bags: one line each, naming the bag, topic or field --------------------------------------------------

BAD = [
    ("no_image", BagSpec(ros=2, images=False), {}, DatasetError, r"no image topic .*topics: /velodyne_points"),
    ("two_images", BagSpec(ros=1, extra_image_topic="/camera2/image_raw"), {}, DatasetError,
     r"2 image topics \(/camera/image_raw, /camera2/image_raw\): choose one with --image-topic"),
    ("no_calib", BagSpec(ros=2, camera_info=False, tf=False), {}, CalibrationError,
     r"no calibration: no CameraInfo topic for /camera/image_raw .*--calib"),
    ("no_tf", BagSpec(ros=1, tf=False), {}, CalibrationError,
     r"no static transform between camera frame 'camera' and lidar frame 'velodyne'"),
    ("never_pair", BagSpec(ros=2, scan_lag_s=0.5), {}, DatasetError,
     r"no image on /camera/image_raw has a scan on /velodyne_points within 0.05 s: closest pair is image stamp "
     r"\d+\.\d+ s and scan stamp \d+\.\d+ s"),
    ("bad_layout", BagSpec(ros=2, cloud_layout="no_xyz"), {}, DatasetError,
     r"/velodyne_points at stamp \d+\.\d+ s \(frame 0\): unknown point layout, no field y, z \(fields: x@0:7"),
    ("wrong_topic", BagSpec(ros=1), {"image_topic": "/cam/left"}, DatasetError,
     r"no topic '/cam/left' \(--image-topic\)"),
]


@pytest.mark.parametrize("name, spec, opts, error, message", BAD, ids=[b[0] for b in BAD])
def test_bad_bag_one_line(town, tmp_path, name, spec, opts, error, message):
    short = KittiOdometry(town_root(town), "00", frames=slice(0, 2))
    bag = write_bag(_bag_path(tmp_path, name, spec), short, spec)
    with pytest.raises(error, match=message) as info:
        RosbagDataset(bag, options=SourceOptions(**opts))[0]
    text = str(info.value)
    assert "\n" not in text and str(bag) in text


def town_root(town: KittiOdometry):
    return town._scans[0].parents[3]


def test_nearest_scan_pairing_and_dropouts(town, tmp_path, caplog):
    """Each image takes the scan nearest in stamp (not the next one); an image whose scan is missing (the
    neighbours are 0.1 s away, beyond 0.05 s) is skipped with a warning, the others kept."""
    lag = 0.04  # the own scan is 0.04 s after the image, the previous one 0.06 s before
    bag = RosbagDataset(write_bag(tmp_path / "lag", town, BagSpec(ros=2, scan_lag_s=lag, drop_scans=(3, 7))))
    kept = [k for k in range(len(town)) if k not in (3, 7)]
    assert len(bag) == len(kept)
    np.testing.assert_allclose(bag.times, BASE_S + town.times[kept], atol=1e-6)
    for pos in (2, 3, 6):
        np.testing.assert_array_equal(point_set(bag[pos].scan), point_set(town[kept[pos]].scan))
        np.testing.assert_array_equal(bag[pos].image, town[kept[pos]].image)
    assert "2 of 12 images have no scan within 0.05 s" in caplog.text


def test_cli_bad_bag_exit_2(town, tmp_path, monkeypatch, capsys):
    from plvo_app.cli import main_viz

    short = KittiOdometry(town_root(town), "00", frames=slice(0, 2))
    bag = write_bag(tmp_path / "two.bag", short, BagSpec(ros=1, extra_image_topic="/camera2/image_raw"))
    monkeypatch.chdir(tmp_path)
    assert main_viz(["--root", str(bag), "--no-serve"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "choose one with --image-topic" in err[0] and str(bag) in err[0]
    assert not (tmp_path / "results").exists() and not (tmp_path / "recordings").exists()


class _Distorted:
    """The town frames as a lens with distortion D would have taken them (same K)."""

    def __init__(self, dataset, D) -> None:
        self.calib, self._ds, self._D = dataset.calib, dataset, D

    def __len__(self) -> int:
        return 3

    def __getitem__(self, i):
        f = self._ds[i]
        return replace(f, image=distort_image(f.image, self.calib.K, self._D))


def test_distorted_bag_is_rectified_with_camera_info(town, tmp_path):
    D = (-0.28, 0.09, 0.0004, -0.0002, 0.0)
    bag = RosbagDataset(write_bag(tmp_path / "lens", _Distorted(town, np.array(D)), BagSpec(ros=2, distortion=D)))
    np.testing.assert_allclose(bag.calib.K, town.calib.K)  # CameraInfo's P: the rectified camera is K
    inner = (slice(40, town.calib.height - 40), slice(120, town.calib.width - 120))
    got, ideal = bag[1].image.astype(float), town[1].image.astype(float)
    raw = _Distorted(town, np.array(D))[1].image.astype(float)
    err, err_raw = np.abs(got - ideal)[inner].mean(), np.abs(raw - ideal)[inner].mean()
    assert err < 4.0 and err < 0.3 * err_raw, (err, err_raw)


@pytest.mark.slow
def test_viz_runs_on_a_ros2_bag_folder(town, tmp_path, monkeypatch):
    """`plvo-viz --root my_ros2_bag_folder` just works: a complete run, poses in TUM with the bag's stamps."""
    from evo.tools import file_interface

    from plvo_app.cli import main_viz

    short = KittiOdometry(town_root(town), "00", frames=slice(0, 5))
    bag = write_bag(tmp_path / "my_ros2_bag", short, BagSpec(ros=2, compressed=True))
    monkeypatch.chdir(tmp_path)
    assert main_viz(["--root", str(bag), "--no-serve", "--format", "tum", "--out", "res", "--rrd", "r.rrd"]) == 0
    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "res" / "poses.txt"))
    np.testing.assert_allclose(traj.timestamps, BASE_S + short.times, atol=1e-6)
    assert (tmp_path / "r.rrd").stat().st_size > 0


def test_eval_run_takes_a_bag_as_root(town, tmp_path):
    import argparse

    from plvo_app import eval_run

    short = KittiOdometry(town_root(town), "00", frames=slice(0, 3))
    bag = write_bag(tmp_path / "drive.bag", short, BagSpec(ros=1, extra_image_topic="/camera2/image_raw"))
    p = argparse.ArgumentParser()
    eval_run.add_run_arguments(p)
    args = p.parse_args(["--root", str(bag), "--image-topic", "/camera2/image_raw", "--beams", "32"])
    (source,) = eval_run.gather_sources(args)
    assert source.name == "drive" and source.image_topic == "/camera2/image_raw" and source.beams == 32
    ds = source.open()  # what an eval worker does, with the topic and beams carried in the task spec
    assert len(ds) == 3 and len(ds[0].scan) == pytest.approx(len(short[0].scan) / 2, rel=0.05)
