"""KITTI loaders: real seq-04 frames with their calibration, fake odometry and raw layouts, bad-data errors."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from kitti_layout import BASELINE, FX, R_CAM_VELO, H, W, make_odometry, projection, row

import plvo.data.kitti as kitti_module
from plvo.data.dataset import Dataset, iter_frames
from plvo.data.kitti import KittiOdometry, KittiRaw
from plvo.data.registry import open_dataset, parse_frames
from plvo.data.trajectory import read_kitti_poses, write_kitti_poses
from plvo.errors import CalibrationError, DatasetError
from plvo.geometry import se3
from plvo.geometry.camera import in_image, project
from plvo.lidar.deskew import needs_deskew

# ---------------------------------------------------------------- real data


def test_real_seq04_loads_with_kitti_calibration(kitti_root):
    ds = open_dataset(kitti_root, "04")
    assert isinstance(ds, Dataset) and isinstance(ds, KittiOdometry)
    assert len(ds) == 51 and ds.frame_indices == tuple(range(51))
    assert (ds.calib.width, ds.calib.height) == (1226, 370)
    np.testing.assert_allclose(ds.calib.K, [[707.0912, 0, 601.8873], [0, 707.0912, 183.1104], [0, 0, 1]])
    np.testing.assert_array_equal(ds.calib.T_cam0_cam, np.eye(4))
    np.testing.assert_allclose(ds.calib.T_cam_velo[0, :], [-1.857739385241e-03, -9.999659513510e-01,
                                                          -8.039975204516e-03, -4.784029760483e-03])
    frame = ds[20]
    assert frame.index == 20 and frame.image.shape == (370, 1226) and frame.image.dtype == np.uint8
    assert frame.scan.ndim == 2 and frame.scan.shape[1] == 4 and frame.scan.dtype == np.float32
    assert len(frame.scan) > 100_000
    line21 = (kitti_root / "sequences" / "04" / "times.txt").read_text().splitlines()[20]
    assert frame.time == pytest.approx(float(line21), abs=1e-9)


def test_real_scan_projects_into_the_image(kitti_root):
    """Forward lidar points land inside the image with positive depth; rear points are behind the camera."""
    ds = open_dataset(kitti_root, "04", frames=slice(0, 1))
    frame = ds[0]
    xyz = frame.scan[:, :3].astype(np.float64)
    rng_xy = np.hypot(xyz[:, 0], xyz[:, 1])
    azimuth = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
    elevation = np.degrees(np.arctan2(xyz[:, 2], rng_xy))
    # well inside the camera's field of view (about +-40 deg horizontally, +-14 deg vertically)
    forward = (xyz[:, 0] > 5.0) & (np.abs(azimuth) < 30.0) & (np.abs(elevation) < 8.0)
    assert forward.sum() > 5000, forward.sum()
    pts_cam = se3.transform_points(frame.calib.T_cam_velo, xyz)
    uv, depth = project(frame.calib.K, pts_cam[forward])
    inside = in_image(uv, frame.calib.width, frame.calib.height) & (depth > 0)
    assert inside.mean() > 0.99, inside.mean()
    # depth along the optical axis is close to the lidar's forward distance (the frames are 0.27 m apart)
    np.testing.assert_allclose(depth, xyz[forward, 0] - 0.27, atol=0.5)
    rear = xyz[:, 0] < -5.0
    assert rear.sum() > 1000 and np.all(pts_cam[rear, 2] < 0)


def test_real_frame_range_ground_truth_and_times(kitti_root):
    ds = open_dataset(kitti_root, "04", frames=parse_frames("10:20"))
    assert ds.frame_indices == tuple(range(10, 20)) and len(ds) == 10
    poses = read_kitti_poses(kitti_root / "poses" / "04.txt")
    np.testing.assert_allclose(ds.gt_T_world_cam, poses[10:20])
    times = np.loadtxt(kitti_root / "sequences" / "04" / "times.txt")
    np.testing.assert_allclose(ds.times, times[10:20])
    frame = ds[3]
    assert frame.index == 13 and frame.time == pytest.approx(times[13])
    np.testing.assert_allclose(frame.gt_T_world_cam, poses[13])
    assert ds[-1].index == 19
    with pytest.raises(IndexError):
        ds[10]
    assert [f.index for f in iter_frames(open_dataset(kitti_root, "04", frames=range(48, 51)))] == [48, 49, 50]


def test_real_out_of_range_and_missing_camera(kitti_root):
    with pytest.raises(DatasetError, match=r"frames 40:60: out of range.*0\.\.50"):
        open_dataset(kitti_root, "04", frames=slice(40, 60))
    with pytest.raises(DatasetError, match=r"frame 51 out of range"):
        open_dataset(kitti_root, "04", frames=range(49, 52))
    with pytest.raises(DatasetError, match=r"image_1: no images"):
        open_dataset(kitti_root, "04", camera=1)


def test_images_and_scans_are_read_lazily(kitti_root, monkeypatch):
    calls = []
    utils = kitti_module._pykitti().utils
    real_image, real_scan = kitti_module._gray8_png, utils.load_velo_scan
    monkeypatch.setattr(kitti_module, "_gray8_png", lambda *a: calls.append(a) or real_image(*a))
    monkeypatch.setattr(utils, "load_velo_scan", lambda *a: calls.append(a) or real_scan(*a))
    ds = open_dataset(kitti_root, "04")
    assert calls == []
    ds[5]
    assert [Path(c[0]).name for c in calls] == ["000005.png", "000005.bin"]


# ---------------------------------------------------------------- registry


def test_registry_tells_layout_and_uses_env(tmp_path, monkeypatch):
    make_odometry(tmp_path)
    monkeypatch.setenv("KITTI_ROOT", str(tmp_path))
    ds = open_dataset(None, "07")
    assert ds.name == "kitti_odometry" and ds.sequence == "07" and len(ds) == 5
    assert len(open_dataset(tmp_path / "sequences", "07")) == 5  # root one level too deep is accepted
    monkeypatch.delenv("KITTI_ROOT")
    with pytest.raises(DatasetError, match=r"\$KITTI_ROOT is not set"):
        open_dataset(None, "07")
    with pytest.raises(DatasetError, match=r"kitti_odometry '09' not found: looked for .*sequences/09"):
        open_dataset(tmp_path, "09")
    with pytest.raises(DatasetError, match=r"kitti_raw '2011_09_26_drive_0009' not found: looked for "
                                           r".*2011_09_26/2011_09_26_drive_0009_sync"):
        open_dataset(tmp_path, "2011_09_26_drive_0009")
    with pytest.raises(DatasetError, match=r"'town': not found under .* of no known form, expected .*'04'.*"
                                           r"2011_09_26_drive_0009"):
        open_dataset(tmp_path, "town")
    make_odometry(tmp_path / "named", seq="town")  # a sequence directory under the root decides the layout
    assert open_dataset(tmp_path / "named", "town").name == "kitti_odometry"
    with pytest.raises(DatasetError, match=r"no such directory"):
        open_dataset(tmp_path / "absent", "07")


@pytest.mark.parametrize(
    ("text", "expected"),
    [("0:50", slice(0, 50)), ("10:", slice(10, None)), (":5", slice(None, 5)), ("0:50:2", slice(0, 50, 2))],
)
def test_parse_frames(text, expected):
    assert parse_frames(text) == expected


@pytest.mark.parametrize(
    ("text", "message"),
    [("5", "expected A:B"), ("a:5", "start 'a' is not an integer"), ("5:5", "end 5 must be greater"),
     ("-1:5", "start must be >= 0"), ("0:5:0", "step must be > 0"), ("1:2:3:4", "expected A:B")],
)
def test_parse_frames_errors(text, message):
    with pytest.raises(DatasetError, match=message):
        parse_frames(text)


# ---------------------------------------------------------------- fake odometry: cameras and bad data


def test_fake_odometry_cameras(tmp_path):
    make_odometry(tmp_path)
    left, right, colour = (KittiOdometry(tmp_path, "07", camera=c) for c in (0, 1, 2))
    assert (left.calib.width, left.calib.height) == (W, H)
    assert int(left[3].image[0, 0]) == 30 and int(right[3].image[0, 0]) == 31 and int(colour[3].image[0, 0]) == 32
    assert colour[3].image.shape == (H, W)  # colour converted to gray
    # cam1 sits BASELINE to the right of cam0: T_cam0_cam1 translates by +BASELINE along x
    np.testing.assert_allclose(right.calib.T_cam0_cam, se3.from_rt(np.eye(3), [BASELINE, 0, 0]), atol=1e-12)
    np.testing.assert_allclose(right.calib.T_cam_velo, se3.from_rt(np.eye(3), [-BASELINE, 0, 0])
                               @ left.calib.T_cam_velo, atol=1e-12)
    np.testing.assert_allclose(right.gt_T_world_cam[2, :3, 3], [BASELINE, 0.0, 2.0], atol=1e-12)
    np.testing.assert_allclose(left.gt_T_world_cam[2, :3, 3], [0.0, 0.0, 2.0], atol=1e-12)
    # KITTI's HDL-64E elevation error is corrected in registration; the synthetic town's marker turns it off
    assert left.calib.lidar_elevation_offset_deg == pytest.approx(0.205)
    (tmp_path / "sequences" / "07" / "gt").mkdir()
    (tmp_path / "sequences" / "07" / "gt" / "scene.json").write_text("{}")
    assert KittiOdometry(tmp_path, "07").calib.lidar_elevation_offset_deg == 0.0


def test_no_ground_truth_when_poses_file_absent(tmp_path):
    make_odometry(tmp_path)
    (tmp_path / "poses" / "07.txt").unlink()
    ds = KittiOdometry(tmp_path, "07")
    assert ds.gt_T_world_cam is None and ds[0].gt_T_world_cam is None


def test_missing_tr_names_calib_file(tmp_path):
    make_odometry(tmp_path, with_tr=False)
    with pytest.raises(CalibrationError, match=r"sequences/07/calib\.txt: no 'Tr' matrix"):
        KittiOdometry(tmp_path, "07")


def test_scan_size_not_multiple_of_16(tmp_path):
    seq = make_odometry(tmp_path)
    with open(seq / "velodyne" / "000003.bin", "ab") as f:
        f.write(b"\0" * 8)
    with pytest.raises(DatasetError, match=r"velodyne/000003\.bin: 1608 bytes is not a multiple of 16"):
        KittiOdometry(tmp_path, "07")
    assert len(KittiOdometry(tmp_path, "07", frames=slice(0, 3))) == 3  # the bad scan is not selected


def test_missing_image_named(tmp_path):
    seq = make_odometry(tmp_path)
    (seq / "image_0" / "000002.png").unlink()
    (seq / "velodyne" / "000002.bin").unlink()
    with pytest.raises(DatasetError, match=r"image_0/000002\.png: missing image \(frame 2\)"):
        KittiOdometry(tmp_path, "07")


def test_mismatched_image_and_scan_counts(tmp_path):
    seq = make_odometry(tmp_path)
    (seq / "velodyne" / "000004.bin").unlink()
    with pytest.raises(DatasetError, match=r"5 images in .*image_0 but 4 scans in .*velodyne: "
                                           r".*velodyne/000004\.bin: missing scan \(frame 4\)"):
        KittiOdometry(tmp_path, "07")


def test_image_deleted_after_construction(tmp_path):
    seq = make_odometry(tmp_path)
    ds = KittiOdometry(tmp_path, "07")
    (seq / "image_0" / "000001.png").unlink()
    with pytest.raises(DatasetError, match=r"000001\.png: missing image \(frame 1\)"):
        ds[1]


def test_nan_in_scan_names_frame(tmp_path):
    seq = make_odometry(tmp_path)
    scan = np.fromfile(seq / "velodyne" / "000003.bin", dtype=np.float32).reshape(-1, 4)
    scan[7, 1], scan[9, 3] = np.nan, np.inf
    scan.tofile(seq / "velodyne" / "000003.bin")
    ds = KittiOdometry(tmp_path, "07")
    ds[2]
    with pytest.raises(DatasetError, match=r"000003\.bin: 2 of 100 points have NaN or infinite values \(frame 3\)"):
        ds[3]


@pytest.mark.parametrize("kind", ["gray8", "gray16", "rgb", "palette", "gray1"])
def test_every_png_kind_reads_as_pil_converts_it(tmp_path, kind):
    """8-bit greyscale PNGs take OpenCV's decoder (faster); every other kind but 16-bit grey PIL's conversion: the
    grey image the pipeline gets is PIL's "L" image of the file. 16-bit grey is scaled to its high byte."""
    from PIL import Image

    seq = make_odometry(tmp_path)
    rng = np.random.default_rng(1)
    path = seq / "image_0" / "000002.png"
    if kind == "gray8":
        Image.fromarray(rng.integers(0, 256, (H, W), np.uint8)).save(path)
    elif kind == "gray16":
        cv2.imwrite(str(path), rng.integers(0, 65536, (H, W), np.uint16))
    elif kind == "rgb":
        Image.fromarray(rng.integers(0, 256, (H, W, 3), np.uint8)).save(path)
    elif kind == "palette":
        Image.fromarray(rng.integers(0, 256, (H, W, 3), np.uint8)).convert("P").save(path)
    else:
        Image.fromarray(rng.integers(0, 2, (H, W), np.uint8) * 255).convert("1").save(path)
    expected = np.asarray(Image.open(path).convert("L"))
    if kind == "gray16":  # scaled on purpose, the high byte (as a ROS mono16 image), not PIL's clip to white
        expected = (cv2.imread(str(path), cv2.IMREAD_UNCHANGED) >> 8).astype(np.uint8)
    assert (kitti_module._gray8_png(path) is not None) == (kind == "gray8")
    got = KittiOdometry(tmp_path, "07")[2].image
    assert got.dtype == np.uint8 and got.shape == (H, W)
    np.testing.assert_array_equal(got, expected)


def test_truncated_png_names_the_file(tmp_path):
    seq = make_odometry(tmp_path)
    path = seq / "image_0" / "000001.png"
    path.write_bytes(path.read_bytes()[:60])  # the header says 8-bit grey; the pixels are cut off
    ds = KittiOdometry(tmp_path, "07")
    with pytest.raises(DatasetError, match=r"image_0/000001\.png: unreadable image \(frame 1\)"):
        ds[1]


def test_image_size_contradicting_first_frame(tmp_path):
    seq = make_odometry(tmp_path)
    cv2.imwrite(str(seq / "image_0" / "000004.png"), np.zeros((H + 2, W), np.uint8))
    ds = KittiOdometry(tmp_path, "07")
    with pytest.raises(DatasetError, match=rf"000004\.png: image is {W}x{H + 2}, but the first frame's is {W}x{H}"):
        ds[4]


def test_short_times_and_poses_files(tmp_path):
    seq = make_odometry(tmp_path)
    (seq / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(DatasetError, match=r"times\.txt: 2 timestamps for 5 frames"):
        KittiOdometry(tmp_path, "07")
    seq = make_odometry(tmp_path / "b")
    write_kitti_poses(tmp_path / "b" / "poses" / "07.txt", np.tile(np.eye(4), (3, 1, 1)))
    with pytest.raises(DatasetError, match=r"07\.txt: 3 poses, but frame 4 is selected"):
        KittiOdometry(tmp_path / "b", "07")
    assert len(KittiOdometry(tmp_path / "b", "07", frames=slice(0, 3))) == 3


def test_bad_camera_rejected(tmp_path):
    make_odometry(tmp_path)
    with pytest.raises(DatasetError, match="camera 5"):
        KittiOdometry(tmp_path, "07", camera=5)


# ---------------------------------------------------------------- fake raw drive

DATE, DRIVE = "2011_09_26", "0009"
EARTH_RADIUS = 6378137.0
LAT0, LON0, ALT0 = 49.0, 8.4, 110.0


def _oxts_line(east: float, north: float, up: float, yaw: float) -> str:
    """An oxts record at a metric offset from (LAT0, LON0, ALT0), inverting pykitti's Mercator projection."""
    scale = math.cos(math.radians(LAT0))
    lon = LON0 + east * 180.0 / (scale * math.pi * EARTH_RADIUS)
    ty0 = scale * EARTH_RADIUS * math.log(math.tan(math.radians(90.0 + LAT0) / 2.0))
    lat = math.degrees(2.0 * math.atan(math.exp((ty0 + north) / (scale * EARTH_RADIUS)))) - 90.0
    values = [lat, lon, ALT0 + up, 0.0, 0.0, yaw] + [0.0] * 19 + [4, 10, 4, 4, 4]
    return " ".join(repr(v) for v in values) + "\n"


FORWARD_NS = (13 * 3600 + 2 * 60 + 25) * 10**9 + 123  # frame 0 faces forward at 13:02:25.000000123
SWEEP_NS = 103_500_000  # frame k's sweep: 0.1035 s + k * 0.2 ms


def _stamp(ns: int) -> str:
    s, frac = divmod(ns, 10**9)
    return f"2011-09-26 {s // 3600:02d}:{s // 60 % 60:02d}:{s % 60:02d}.{frac:09d}\n"


def write_velodyne_stamps(drive_dir: Path, n: int) -> None:
    """velodyne_points/timestamps{_start,,_end}.txt: frame k faces forward 0.1 s after frame k-1, mid-sweep."""
    rows = []
    for k in range(n):
        forward, half = FORWARD_NS + k * 100_000_000, (SWEEP_NS + k * 200_000) // 2
        rows.append((_stamp(forward - half), _stamp(forward), _stamp(forward + half)))
    for name, column in zip(("timestamps_start.txt", "timestamps.txt", "timestamps_end.txt"), zip(*rows)):
        (drive_dir / "velodyne_points" / name).write_text("".join(column))


def make_raw(root: Path, motion, oxts_lag_ns=None) -> Path:
    """A tiny raw drive; motion = [(east, north, up, yaw), ...] of the IMU, one per frame; oxts_lag_ns: how long
    after each frame's forward instant its oxts record was taken (default: at it)."""
    date_dir = root / DATE
    drive_dir = date_dir / f"{DATE}_drive_{DRIVE}_sync"
    date_dir.mkdir(parents=True)
    (date_dir / "calib_imu_to_velo.txt").write_text(f"calib_time: 25-May-2012\nR: {row(np.eye(3))}\nT: 0 0 0\n")
    (date_dir / "calib_velo_to_cam.txt").write_text(f"calib_time: x\nR: {row(R_CAM_VELO)}\nT: 0 0 0\n")
    cam = [f"P_rect_0{c}: {row(projection(-FX * BASELINE if c == 1 else 0.0))}\nR_rect_0{c}: {row(np.eye(3))}"
           for c in range(4)]
    (date_dir / "calib_cam_to_cam.txt").write_text("calib_time: 09-Jan-2012 13:57:47\n" + "\n".join(cam) + "\n")
    for sub in ("image_00/data", "velodyne_points/data", "oxts/data"):
        (drive_dir / sub).mkdir(parents=True)
    stamps = []
    for k, (east, north, up, yaw) in enumerate(motion):
        cv2.imwrite(str(drive_dir / "image_00" / "data" / f"{k:010d}.png"), np.full((H, W), k, np.uint8))
        np.ones((10, 4), np.float32).tofile(drive_dir / "velodyne_points" / "data" / f"{k:010d}.bin")
        (drive_dir / "oxts" / "data" / f"{k:010d}.txt").write_text(_oxts_line(east, north, up, yaw))
        stamps.append(_stamp(FORWARD_NS + k * 100_000_000 + (0 if oxts_lag_ns is None else oxts_lag_ns[k])))
    (drive_dir / "oxts" / "timestamps.txt").write_text("".join(stamps))
    write_velodyne_stamps(drive_dir, len(motion))
    return drive_dir


MOTION = [(0.0, 0.0, 0.0, 0.0), (2.0, 0.0, 0.0, 0.0), (2.0, 3.0, 0.5, math.pi / 2), (2.0, 5.0, 0.5, math.pi / 2)]


def test_raw_drive_ground_truth_from_oxts(tmp_path):
    make_raw(tmp_path, MOTION)
    ds = open_dataset(tmp_path, f"{DATE}_drive_{DRIVE}")
    assert isinstance(ds, KittiRaw) and ds.name == "kitti_raw" and ds.sequence == f"{DATE}_drive_{DRIVE}"
    assert len(ds) == 4 and (ds.calib.width, ds.calib.height) == (W, H)
    assert ds.calib.lidar_elevation_offset_deg == pytest.approx(0.205)
    np.testing.assert_allclose(ds.calib.T_cam_velo[:3, :3], R_CAM_VELO, atol=1e-12)
    np.testing.assert_allclose(ds.times, [0.0, 0.1, 0.2, 0.3], atol=1e-6)
    gt = ds.gt_T_world_cam
    # at frame 0 the IMU looks east; camera of frame 0: x = south, y = down, z = east
    np.testing.assert_allclose(gt[0], np.eye(4), atol=1e-9)
    np.testing.assert_allclose(gt[1, :3, 3], [0.0, 0.0, 2.0], atol=1e-6)
    np.testing.assert_allclose(gt[1, :3, :3], np.eye(3), atol=1e-9)
    np.testing.assert_allclose(gt[2, :3, 3], [-3.0, -0.5, 2.0], atol=1e-6)  # 3 m north, 0.5 m up
    np.testing.assert_allclose(gt[2, :3, 2], [-1.0, 0.0, 0.0], atol=1e-9)  # now looking north
    np.testing.assert_allclose(gt[3, :3, 3], [-5.0, -0.5, 2.0], atol=1e-6)
    frame = ds[2]
    assert frame.index == 2 and int(frame.image[0, 0]) == 2 and frame.scan.shape == (10, 4)


def test_raw_truth_is_read_at_each_frames_own_time(tmp_path):
    """A synced drive's oxts record is the GPS/INS sample nearest the image, 11-38 ms after the frame's forward
    instant in a three-frame pattern (drive 0009); the truth is the motion at the frame's time, not at the record's."""
    lag_ns = [12_000_000, 19_000_000, 15_000_000] * 3
    speed = 10.0  # m/s east, the IMU looking east
    motion = [(speed * (0.1 * k + 1e-9 * lag_ns[k]), 0.0, 0.0, 0.0) for k in range(9)]
    make_raw(tmp_path, motion, lag_ns)
    gt = KittiRaw(tmp_path, f"{DATE}_drive_{DRIVE}").gt_T_world_cam
    steps = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, 1.0, atol=1e-4)  # read at the records' times: 1.07, 0.96, 0.97, ...
    part = KittiRaw(tmp_path, f"{DATE}_drive_{DRIVE}", frames=slice(4, 9))  # a window reads the same truth
    np.testing.assert_allclose(part.gt_T_world_cam, gt[4:], atol=1e-9)


def test_raw_frame_range_keeps_frame0_as_world(tmp_path):
    make_raw(tmp_path, MOTION)
    full = KittiRaw(tmp_path, f"{DATE}_drive_{DRIVE}")
    part = KittiRaw(tmp_path, f"{DATE}_drive_{DRIVE}_sync", frames=slice(2, 4))
    assert part.frame_indices == (2, 3)
    np.testing.assert_allclose(part.gt_T_world_cam, full.gt_T_world_cam[2:], atol=1e-9)
    np.testing.assert_allclose(part.times, [0.2, 0.3], atol=1e-6)


def test_raw_bad_data(tmp_path):
    drive = make_raw(tmp_path, MOTION)
    (drive / "oxts" / "data" / "0000000003.txt").unlink()
    with pytest.raises(DatasetError, match=r"oxts/data/0000000003\.txt: missing oxts record \(frame 3\)"):
        KittiRaw(tmp_path, f"{DATE}_drive_{DRIVE}")
    (drive / "oxts" / "data" / "0000000003.txt").write_text("1 2 3\n")
    with pytest.raises(DatasetError, match=r"0000000003\.txt: expected one line of 30 numbers, got 3"):
        KittiRaw(tmp_path, f"{DATE}_drive_{DRIVE}")
    (tmp_path / DATE / "calib_velo_to_cam.txt").write_text("R: 1 0 0 0 1 0 0 0 1\n")
    with pytest.raises(CalibrationError, match=r"calib_velo_to_cam\.txt: no 'T' matrix"):
        KittiRaw(tmp_path, f"{DATE}_drive_{DRIVE}")


def _returns_at(azimuth_deg) -> np.ndarray:
    """(N,4) returns 10 m away at the given azimuths (deg, 0 forward, 90 left), 1 m below the lidar."""
    a = np.radians(np.asarray(azimuth_deg, dtype=np.float64))
    return np.c_[10 * np.cos(a), 10 * np.sin(a), -np.ones_like(a), np.zeros_like(a)].astype(np.float32)


def test_raw_returns_span_the_recorded_sweep_zero_facing_forward(tmp_path):
    """A raw drive's scans are raw sweeps: each return's time from its azimuth over its frame's sweep as the velodyne
    timestamps bound it (clockwise from behind, the frame's time when it faces forward)."""
    drive = make_raw(tmp_path, MOTION)
    azimuths = [0.0, 90.0, -90.0, 179.99, -179.99, 45.0]
    _returns_at(azimuths).tofile(drive / "velodyne_points" / "data" / "0000000002.bin")
    ds = KittiRaw(tmp_path, f"{DATE}_drive_{DRIVE}", frames=slice(1, 4))
    assert not ds.scans_compensated
    np.testing.assert_allclose(ds.times, [0.1, 0.2, 0.3], atol=1e-9)  # the forward instants since frame 0's
    frame = ds[1]  # frame 2, whose sweep is 0.1039 s
    sweep = (SWEEP_NS + 2 * 200_000) * 1e-9
    assert not frame.scan_compensated and frame.time == pytest.approx(0.2, abs=1e-9)
    # clockwise seen from above: the left (90 deg) a quarter sweep before facing forward, behind at either end
    want = -np.asarray(azimuths) / 360.0 * sweep
    np.testing.assert_allclose(frame.scan_time, want, atol=1e-7)  # float32 returns: azimuths to ~1e-5 deg
    assert np.ptp(frame.scan_time) == pytest.approx(sweep, rel=1e-3)  # the whole sweep, not a nominal 0.1 s
    scan, times = ds.load_timed_scan(1)
    np.testing.assert_array_equal(scan, frame.scan)
    np.testing.assert_array_equal(times, frame.scan_time)
    assert needs_deskew(frame, "auto")  # registration.deskew's default deskews it


def _rewrite_line(path: Path, frame: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[frame] = text
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("name, frame, text, message", [
    ("timestamps_start.txt", None, None, r"velodyne_points/timestamps_start\.txt: timestamps file not found"),
    ("timestamps.txt", 2, "", r"velodyne_points/timestamps\.txt:3: no timestamp \(frame 2\)"),
    ("timestamps_end.txt", 3, "2011-09-26 13:02:25.4x", r"timestamps_end\.txt:4: not a timestamp: '2011-09-26 "
     r"13:02:25\.4x' \(frame 3\)"),
    ("timestamps.txt", 1, "2011-09-26 25:02:25.1", r"timestamps\.txt:2: not a timestamp: .* \(frame 1\)"),
    ("timestamps_end.txt", 1, "2011-09-26 13:02:25.0", r"timestamps_end\.txt:2: the sweep of frame 1 ends "
     r"-0\.048150 s after it starts \(timestamps_start\.txt\), expected 0-1 s"),
    ("timestamps.txt", 1, "2011-09-26 13:02:25.9", r"timestamps\.txt:2: frame 1 faces forward outside its sweep"),
    ("timestamps_start.txt", 0, "2011-09-26 13:02:23.9", r"timestamps_end\.txt:1: the sweep of frame 0 ends 1\.15"),
])
def test_raw_bad_velodyne_timestamps_name_file_and_frame(tmp_path, name, frame, text, message):
    drive = make_raw(tmp_path, MOTION)
    path = drive / "velodyne_points" / name
    if frame is None:
        path.unlink()
    else:
        _rewrite_line(path, frame, text)
    with pytest.raises(DatasetError, match=message):
        KittiRaw(tmp_path, f"{DATE}_drive_{DRIVE}")


def test_raw_velodyne_timestamps_short_unordered_or_blank_outside_the_selection(tmp_path):
    drive = make_raw(tmp_path, MOTION)
    stamps = drive / "velodyne_points" / "timestamps.txt"
    full = stamps.read_text()
    stamps.write_text("".join(full.splitlines(keepends=True)[:3]))
    with pytest.raises(DatasetError, match=r"timestamps\.txt: no timestamp for frame 3 \(3 lines\)"):
        KittiRaw(tmp_path, f"{DATE}_drive_{DRIVE}")
    # drive 0009 has blank velodyne stamps where its frames 177-180 have no scan: frames outside them still read
    stamps.write_text(full)
    for name in ("timestamps_start.txt", "timestamps.txt", "timestamps_end.txt"):
        _rewrite_line(drive / "velodyne_points" / name, 3, "")
    assert len(KittiRaw(tmp_path, f"{DATE}_drive_{DRIVE}", frames=slice(0, 3))) == 3
    write_velodyne_stamps(drive, len(MOTION))
    for name in ("timestamps_start.txt", "timestamps.txt", "timestamps_end.txt"):  # frame 2 as frame 1
        path = drive / "velodyne_points" / name
        _rewrite_line(path, 2, path.read_text().splitlines()[1])
    with pytest.raises(DatasetError, match=r"timestamps\.txt:3: frame 2 is not after frame 1"):
        KittiRaw(tmp_path, f"{DATE}_drive_{DRIVE}")


def test_registry_hook_for_other_layouts(tmp_path, monkeypatch):
    """A layout registered later (e.g. the synthetic town) is found first and may need no root."""
    import plvo.data.registry as registry

    monkeypatch.setattr(registry, "_LAYOUTS", list(registry._LAYOUTS))
    monkeypatch.delenv("KITTI_ROOT", raising=False)
    make_odometry(tmp_path)
    opened = []

    def open_town(root, seq, frames, camera):
        opened.append((root, seq, frames, camera))
        return KittiOdometry(tmp_path, "07", frames=frames, camera=camera)

    registry.register_layout(registry.Layout(
        name="synthetic", description="'town' (the synthetic town)", matches=lambda s: s == "town",
        open=open_town, needs_root=False))
    ds = open_dataset(None, "town", frames=slice(1, 3))
    assert opened == [(None, "town", slice(1, 3), 0)] and ds.frame_indices == (1, 2)
    assert [lay.name for lay in registry.layouts()] == ["synthetic", "kitti_odometry", "kitti_raw"]
