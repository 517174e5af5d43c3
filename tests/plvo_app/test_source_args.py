"""`--root` without `--seq`: a dataset root's only sequence runs (said on stderr), several are listed on one line
(exit 2), none is said; a bag or a plain folder needs no --seq. Sequences are synthetic town sequences linked into
KITTI layouts; the raw root is the shared real drive (skipped with a reason when absent)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest
from bag_writer import BagSpec, write_bag
from faults_table import fault, one_error_line

from plvo.data.calib_yaml import write_calib_yaml
from plvo.data.camera_model import CameraModel
from plvo.data.kitti import KittiOdometry
from plvo.data.registry import describe_sequences, list_sequences, only_sequence
from plvo.errors import DatasetError
from plvo_app import cmd_viz
from plvo_app.cli import main_viz
from plvo_app.viz_options import VizOptions

RAW_ROOT = Path(__file__).resolve().parents[3] / "shared" / "data" / "kitti_raw"
DRIVE = "2011_09_26_drive_0009"


@pytest.fixture(scope="module")
def town(synth_sequence_factory) -> Path:
    return synth_sequence_factory(3, seed=0)


def _odometry_root(root: Path, town: Path, names: list[str], calib_only: tuple[str, ...] = ("05",)) -> Path:
    """root/sequences/<name> linked to the town's sequence 00, plus sequences with a calib.txt only (as KITTI's
    calibration download leaves all 22 of them)."""
    (root / "sequences").mkdir(parents=True)
    for name in names:
        (root / "sequences" / name).symlink_to(town / "sequences" / "00", target_is_directory=True)
    for name in calib_only:
        (root / "sequences" / name).mkdir()
        (root / "sequences" / name / "calib.txt").write_text((town / "sequences" / "00" / "calib.txt").read_text())
    return root


def _raw_drive(root: Path, drive: str) -> None:
    """A raw drive's folders with one scan and one image: enough to be listed (not to be opened)."""
    date = drive[:10]
    d = root / date / f"{drive}_sync"
    (d / "velodyne_points" / "data").mkdir(parents=True)
    (d / "velodyne_points" / "data" / "0000000000.bin").write_bytes(b"\0" * 16)
    (d / "image_00" / "data").mkdir(parents=True)
    (d / "image_00" / "data" / "0000000000.png").write_bytes(b"")


def _args(*argv: str) -> VizOptions:
    p = argparse.ArgumentParser()
    cmd_viz.add_arguments(p)
    return VizOptions.from_args(p.parse_args(list(argv)))


def test_several_are_listed_on_one_line(town, tmp_path, capsys, monkeypatch):
    row = fault("root-several")
    root = _odometry_root(tmp_path / "kitti", town, ["07", "00", "04"])
    _raw_drive(root, DRIVE)
    (root / "2011_09_26" / "2011_09_26_drive_0011_sync").mkdir()  # an empty drive folder: nothing to run
    found = list_sequences(root)
    assert [(lay.name, name) for lay, name in found] == [
        ("kitti_odometry", "00"), ("kitti_odometry", "04"), ("kitti_odometry", "07"), ("kitti_raw", DRIVE)]
    assert describe_sequences(found) == f"sequences 00, 04, 07 and drives {DRIVE}"
    expected = f"--root {root} holds sequences 00, 04, 07 and drives {DRIVE}; choose one with --seq"
    with pytest.raises(DatasetError) as exc:
        cmd_viz._open(_args("--root", str(root)))
    assert str(exc.value) == expected and row.message in expected and exc.value.exit_status == row.exit
    # the command: one line, exit 2, nothing written
    out = tmp_path / "results"
    monkeypatch.chdir(tmp_path)
    assert main_viz(["--root", str(root), "--no-serve", "--out", str(out)]) == 2
    assert one_error_line(capsys.readouterr().err) == f"error: {expected}"
    assert not out.exists() and not (tmp_path / "recordings").exists()
    # $KITTI_ROOT the same, named as such
    monkeypatch.setenv("KITTI_ROOT", str(root))
    with pytest.raises(DatasetError, match=r"^\$KITTI_ROOT .* holds sequences 00, 04, 07 and drives"):
        cmd_viz._open(_args())
    # --seq still chooses
    dataset, label, _ = cmd_viz._open(_args("--seq", "04", "--frames", "0:2"))
    assert label == "04" and len(dataset) == 2


def test_the_only_sequence_runs(town, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("KITTI_ROOT", raising=False)
    root = _odometry_root(tmp_path / "kitti", town, ["04"])
    dataset, label, _ = cmd_viz._open(_args("--root", str(root)))
    assert label == "04" and dataset.sequence == "04" and len(dataset) == 3
    assert f"--root {root}: running 04, the only sequence there" in capsys.readouterr().err
    # given one level too deep (root/sequences), as the registry opens it
    assert only_sequence(root / "sequences") == "04"
    dataset, _, _ = cmd_viz._open(_args("--root", str(root / "sequences")))
    assert dataset.sequence == "04"


def test_nothing_there_is_said(town, tmp_path):
    root = _odometry_root(tmp_path / "kitti", town, [], calib_only=("00", "01"))
    with pytest.raises(DatasetError) as exc:
        cmd_viz._open(_args("--root", str(root)))
    text = str(exc.value)
    assert text.startswith(f"--root {root} holds no sequence with scans and images") and "--seq" in text
    assert "plain folder" in text and "\n" not in text


def test_bag_and_folder_need_no_seq(town, tmp_path, capsys):
    ds = KittiOdometry(town, "00")
    bag = write_bag(tmp_path / "drive.bag", ds, BagSpec(ros=1))
    dataset, label, _ = cmd_viz._open(_args("--root", str(bag)))
    assert dataset.name == "rosbag" and label == "drive" and len(dataset) == 3
    folder = tmp_path / "my_run"
    (folder / "images").mkdir(parents=True)
    (folder / "scans").mkdir()
    seq = town / "sequences" / "00"
    for k in range(3):
        (folder / "images" / f"{k:06d}.png").symlink_to(seq / "image_0" / f"{k:06d}.png")
        (folder / "scans" / f"{k:06d}.bin").symlink_to(seq / "velodyne" / f"{k:06d}.bin")
    c = ds.calib
    write_calib_yaml(folder / "calib.yaml", CameraModel(c.width, c.height, c.K), c.T_cam_velo)
    dataset, label, _ = cmd_viz._open(_args("--root", str(folder)))
    assert dataset.name == "folder" and label == "my_run" and len(dataset) == 3
    assert "the only sequence" not in capsys.readouterr().err
    assert only_sequence(bag) is None and only_sequence(folder) is None


def test_raw_root_runs_its_drive(tmp_path, capsys):
    if not (RAW_ROOT / "2011_09_26" / f"{DRIVE}_sync").is_dir():
        pytest.skip(f"real KITTI raw drive not found at {RAW_ROOT} (see ../shared/data/README.md)")
    for root in (RAW_ROOT, RAW_ROOT / "2011_09_26"):  # the root, or the day's folder
        dataset, label, _ = cmd_viz._open(_args("--root", str(root), "--frames", "0:2"))
        assert label == DRIVE and dataset.name == "kitti_raw" and len(dataset) == 2
        assert f"--root {root}: running {DRIVE}, the only sequence there" in capsys.readouterr().err
