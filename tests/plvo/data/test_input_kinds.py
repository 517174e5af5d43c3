"""Inputs of the wrong numeric kind converted on purpose or refused with one line (a 16-bit PNG scaled, a float64
scan refused), and a run whose camera froze says so in its last line and timings.json."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from faults_table import fault, one_error_line

from plvo.data.pointcloud import read_scan_file
from plvo.data.registry import open_dataset
from plvo.errors import DatasetError
from plvo_eval.kitti_variants import variant

SEQ = "04"


def _viz(args, capsys):
    from plvo_app.cli import main_viz

    status = main_viz(args)
    return status, capsys.readouterr().err


def _copy_frames(kitti_root, tmp_path, n: int):
    """A root whose first n frames are real files (not links), to be changed in place."""
    root = variant(kitti_root, SEQ, tmp_path / "kitti", n)
    for sub in ("image_0", "velodyne"):
        for path in (root / "sequences" / SEQ / sub).iterdir():
            data = path.read_bytes()
            path.unlink()
            path.write_bytes(data)
    return root


def test_16_bit_png_is_scaled_not_clipped(kitti_root, tmp_path):
    """A 16-bit grey PNG (as a machine-vision camera writes) reads as its high byte, the grey a ROS mono16 image
    gets, not as PIL's all-white clip."""
    root = _copy_frames(kitti_root, tmp_path, 2)
    path = root / "sequences" / SEQ / "image_0" / "000001.png"
    grey = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), grey.astype(np.uint16) * 257)  # the full 16-bit range
    frame = open_dataset(root, SEQ)[1]
    assert frame.image.dtype == np.uint8
    np.testing.assert_array_equal(frame.image, grey)


def test_float64_scan_is_refused_naming_the_file(kitti_root, tmp_path, capsys):
    row = fault("scan-wrong-kind")
    root = _copy_frames(kitti_root, tmp_path, 4)
    path = root / "sequences" / SEQ / "velodyne" / "000002.bin"
    np.fromfile(path, np.float32).astype(np.float64).tofile(path)  # 32 bytes a point: still a multiple of 16
    with pytest.raises(DatasetError, match=r"000002\.bin: .* not a scan in metres; is it float64\?.*\(frame 2\)"):
        open_dataset(root, SEQ)[2]
    with pytest.raises(DatasetError, match="not a scan in metres"):
        read_scan_file(path, 2)  # the plain-folder reader likewise
    status, err = _viz(["--root", str(root), "--seq", SEQ, "--no-serve", "--out", str(tmp_path / "out"),
                        "--rrd", str(tmp_path / "run.rrd")], capsys)
    line = one_error_line(err)
    assert status == row.exit and row.message in line and "000002.bin" in line, line
    timings = json.loads((tmp_path / "out" / "timings.json").read_text())
    assert timings["status"] == "failed" and "000002.bin" in timings["reason"]
    assert not (tmp_path / "out" / "poses.txt").exists()


@pytest.mark.parametrize(("far_share", "intensity", "refused"), [
    (0.0, 65535.0, False),  # 16-bit intensities beside metres: the quick test fails, the exact one passes
    (0.005, 1.0, False),  # a few stray returns
    (0.02, 1.0, True),  # a scan's worth: not metres
])
def test_scan_values_plausible_or_refused(far_share, intensity, refused):
    from plvo.data.pointcloud import check_scan_values

    rng = np.random.default_rng(0)
    scan = np.column_stack([rng.uniform(-80, 80, (10000, 3)), np.full(10000, intensity)]).astype(np.float32)
    scan[: int(far_share * len(scan)), 0] = 3.7e19
    if refused:
        with pytest.raises(DatasetError, match="beyond 10000 m"):
            check_scan_values(scan, "x.bin", 7)
    else:
        check_scan_values(scan, "x.bin", 7)


def test_frozen_camera_run_says_so(kitti_root, tmp_path, capsys, caplog):
    row = fault("camera-frozen")
    root = variant(kitti_root, SEQ, tmp_path / "frozen", 20, image_of=lambda i: 9 if 10 <= i <= 12 else i)
    status, err = _viz(["--root", str(root), "--seq", SEQ, "--no-serve", "--out", str(tmp_path / "out"),
                        "--rrd", str(tmp_path / "run.rrd")], capsys)
    assert status == row.exit, err[-2000:]
    warnings = [r.getMessage() for r in caplog.records if row.message in r.getMessage() and r.levelname == "WARNING"]
    assert len(warnings) == 1 and "frames 10-12" in warnings[0], err[-3000:]
    last = err.strip().splitlines()[-1]
    assert last.startswith("complete: 20 frames") and "17 by the camera, 3 by the lidar alone" in last, last
    timings = json.loads((tmp_path / "out" / "timings.json").read_text())
    assert timings["frames_by_source"]["lidar"] == 3
    assert [(e["kind"], e["frames"]) for e in timings["episodes"]] == [("frozen image", [10, 12])]


def test_run_with_lost_frames_is_degraded(kitti_root, tmp_path, capsys):
    """Frames 20-21 black and their scans a handful of returns: neither sensor can place them. The run completes
    with their poses the motion model's guess, and says so: status degraded, exit 3, the frames named."""
    row = fault("degraded")
    root = variant(kitti_root, SEQ, tmp_path / "kitti", 30)
    seq = root / "sequences" / SEQ
    for k in (20, 21):
        image = seq / "image_0" / f"{k:06d}.png"
        shape = cv2.imread(str(image), cv2.IMREAD_UNCHANGED).shape
        image.unlink()
        cv2.imwrite(str(image), np.zeros(shape, np.uint8))
        scan = seq / "velodyne" / f"{k:06d}.bin"
        scan.unlink()
        np.array([[5.0, 0, -1.7, 0], [5.0, 1, -1.7, 0], [6.0, 0, -1.7, 0]], np.float32).tofile(scan)
    status, err = _viz(["--root", str(root), "--seq", SEQ, "--no-serve", "--out", str(tmp_path / "out"),
                        "--rrd", str(tmp_path / "run.rrd")], capsys)
    assert status == row.exit, err[-3000:]
    last = err.strip().splitlines()[-1]
    assert last.startswith(row.message) and "lost (motion model)" in last, last
    timings = json.loads((tmp_path / "out" / "timings.json").read_text())
    assert timings["status"] == "degraded" and timings["frames_by_source"]["motion model"] >= 2
    lost = [e for e in timings["episodes"] if e["kind"] == "tracking lost"]
    assert lost and lost[0]["frames"][0] == 20, timings["episodes"]
    assert (tmp_path / "out" / "poses.txt").exists()  # whole in length: every frame has a pose, some guessed
