"""Any KITTI camera: a colour-only, SemanticKITTI-style sequence (image_2, poses.txt inside the
sequence) runs through --camera 2; the pipeline gets grey, the viewers the colour image; a bag of colour images
reads back the same frames; the no-root error says what to download and what runs without it."""

from __future__ import annotations

import argparse
import shutil

import cv2
import numpy as np
import pytest
from bag_writer import BagSpec, write_bag

from plvo.data.images import to_gray
from plvo.data.kitti import KittiOdometry
from plvo.data.registry import open_dataset
from plvo.data.rosbag import RosbagDataset
from plvo.data.trajectory import read_kitti_poses
from plvo.errors import DatasetError

N = 5


def _colourise(gray: np.ndarray) -> np.ndarray:
    g = gray.astype(np.int32)
    return np.stack([g, 255 - g, g // 2], axis=-1).astype(np.uint8)


@pytest.fixture(scope="module")
def colour_only(synth_seq, tmp_path_factory):
    """SemanticKITTI-style copy of the town's first N frames: sequences/00/{image_2, velodyne, calib.txt,
    times.txt, poses.txt}, no image_0 and no root/poses."""
    root = tmp_path_factory.mktemp("semkitti")
    src, dst = synth_seq / "sequences" / "00", root / "sequences" / "00"
    (dst / "image_2").mkdir(parents=True)
    (dst / "velodyne").mkdir()
    for k in range(N):
        gray = cv2.imread(str(src / "image_0" / f"{k:06d}.png"), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(dst / "image_2" / f"{k:06d}.png"), cv2.cvtColor(_colourise(gray), cv2.COLOR_RGB2BGR))
        shutil.copy(src / "velodyne" / f"{k:06d}.bin", dst / "velodyne")
    shutil.copy(src / "calib.txt", dst)
    (dst / "times.txt").write_text("\n".join((src / "times.txt").read_text().splitlines()[:N]) + "\n")
    (dst / "poses.txt").write_text("\n".join((synth_seq / "poses" / "00.txt").read_text().splitlines()[:N]) + "\n")
    return root


def test_colour_only_sequence_names_the_camera_to_choose(colour_only):
    with pytest.raises(DatasetError, match=r"image_0: no images \(\*\.png\); this sequence has camera 2: "
                                           r"give --camera 2"):
        KittiOdometry(colour_only, "00")


def test_camera_2_grey_for_pipeline_colour_for_viewers(colour_only, synth_seq):
    ds = open_dataset(colour_only, "00", camera=2)
    ref = KittiOdometry(synth_seq, "00", frames=slice(0, N))
    assert len(ds) == N
    for i in (0, N - 1):
        f = ds[i]
        rgb = _colourise(ref[i].image)
        np.testing.assert_array_equal(f.color, rgb)
        np.testing.assert_array_equal(f.image, to_gray(rgb))
        assert f.image.shape == ref[i].image.shape and f.image.dtype == np.uint8
    P2 = np.array([float(v) for v in (colour_only / "sequences/00/calib.txt").read_text().splitlines()[2]
                   .split()[1:]]).reshape(3, 4)
    np.testing.assert_allclose(ds.calib.K, P2[:, :3], atol=1e-9)
    np.testing.assert_allclose(ds.calib.T_cam0_cam[0, 3], -P2[0, 3] / P2[0, 0], atol=1e-9)
    # SemanticKITTI's poses.txt (cam0 poses) inside the sequence is the ground truth, moved to camera 2
    gt0 = read_kitti_poses(colour_only / "sequences/00/poses.txt")
    np.testing.assert_allclose(ds.gt_T_world_cam, gt0 @ ds.calib.T_cam0_cam, atol=1e-9)


def test_grey_camera_has_no_colour(synth_seq):
    f = KittiOdometry(synth_seq, "00", frames=slice(0, 1))[0]
    assert f.color is None and f.image.ndim == 2


def test_viz_camera_option_opens_camera_2(colour_only):
    from plvo_app import cmd_viz
    from plvo_app.viz_options import VizOptions

    parser = argparse.ArgumentParser()
    cmd_viz.add_arguments(parser)
    dataset, label, _ = cmd_viz._open(VizOptions.from_args(
        parser.parse_args(["--root", str(colour_only), "--seq", "00", "--camera", "2"])))
    assert label == "00" and dataset[0].color is not None


def test_eval_run_and_bench_take_camera(colour_only):
    from plvo_app import cmd_bench, eval_run

    p = argparse.ArgumentParser()
    eval_run.add_run_arguments(p)
    sources = eval_run.gather_sources(p.parse_args(["--root", str(colour_only), "--seq", "00", "--camera", "2"]))
    assert sources[0].camera == 2 and sources[0].open()[0].color is not None
    p = argparse.ArgumentParser()
    cmd_bench.add_arguments(p)
    dataset, _ = cmd_bench._open(p.parse_args(["--root", str(colour_only), "--seq", "00", "--camera", "2"]))
    assert dataset.calib.T_cam0_cam[0, 3] != 0


def test_colour_bag_reads_back_colour(colour_only, tmp_path):
    ds = KittiOdometry(colour_only, "00", camera=2)
    for compressed in (False, True):
        bag = RosbagDataset(write_bag(tmp_path / f"c{int(compressed)}", ds, BagSpec(ros=2, compressed=compressed),
                                      color=True))
        f, want = bag[2], ds[2]
        np.testing.assert_array_equal(f.color, want.color)
        np.testing.assert_array_equal(f.image, want.image)


def test_no_root_says_what_to_download_and_what_runs_without(monkeypatch, capsys, tmp_path):
    from plvo_app.cli import main_viz

    monkeypatch.delenv("KITTI_ROOT", raising=False)
    monkeypatch.chdir(tmp_path)
    assert main_viz(["--seq", "00", "--no-serve"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    line = err[0]
    for needed in ("kitti_odometry '00'", "cvlibs.net/datasets/kitti/eval_odometry.php", "velodyne",
                   "calibration", "--root DIR", "$KITTI_ROOT", "synthetic town", "plvo synth", "--follow"):
        assert needed in line, needed
