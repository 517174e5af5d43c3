"""plvo reproduce and plvo clip on a short synthetic run recorded by plvo-viz (back end inline, so the run is
deterministic): the rerun reproduces from the dataset and from the inputs embedded in the recording alone; one
config value changed gives a departure (frame and stage); a changed input file is named; clip keeps only the
window and its static data."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import xxhash
from faults_table import break_tracker_at, fault

from plvo.data.registry import open_dataset
from plvo.errors import RecordingError
from plvo_app.cli import main_viz
from plvo_app.cmd_clip import clip
from plvo_app.reproduce import _check_hashes, reproduce
from plvo_app.rrd_reader import read_rrd
from plvo_app.run_identity import file_digest, input_files

N = 8


@pytest.fixture(scope="module")
def run(synth_sequence_factory, tmp_path_factory):
    root = synth_sequence_factory(12, seed=0)
    tmp = tmp_path_factory.mktemp("repro")
    cfg = tmp / "det.toml"
    cfg.write_text("[backend]\nconcurrent = false\n")
    rrd = tmp / "run.rrd"
    code = main_viz(["--root", str(root), "--seq", "00", "--frames", f"0:{N}", "--config", str(cfg), "--no-serve",
                     "--rrd", str(rrd), "--out", str(tmp / "out"), "--embed-inputs", f"0:{N}"])
    assert code == 0
    return root, rrd


def test_recording_names_its_inputs_and_machine(run):
    root, rrd = run
    props = read_rrd(rrd, content=["/log"]).properties
    assert props["plvo_dataset:sequence"] == "00" and props["plvo_dataset:layout"] == "kitti_odometry"
    assert props["plvo_dataset:frames"] == str(list(range(N)))
    assert len(props["plvo_inputs:scan_hash"]) == N and props["plvo_machine:cpus"]
    assert "concurrent = false" in props["plvo:config"]
    hashed = props["plvo_inputs:hash"]
    assert (hashed if isinstance(hashed, str) else hashed[0]) == "xxh3_128"
    scan = root / "sequences" / "00" / "velodyne" / "000003.bin"
    assert props["plvo_inputs:scan_hash"][3] == file_digest(scan)[:24]
    assert xxhash.xxh3_128(scan.read_bytes()).hexdigest() == file_digest(scan)


def test_a_recording_of_sha256_prefixes_is_still_checked(run, tmp_path):
    """Recordings made before the digests were named hold sha256 prefixes under image_sha256 / scan_sha256."""
    root, _ = run
    ds = open_dataset(root, "00", frames=range(N))
    files = input_files(ds)
    old = {"plvo_inputs:frames": json.dumps(sorted(files)),
           "plvo_inputs:image_sha256": [hashlib.sha256(Path(files[f][0]).read_bytes()).hexdigest()[:24]
                                        for f in sorted(files)],
           "plvo_inputs:scan_sha256": [hashlib.sha256(Path(files[f][1]).read_bytes()).hexdigest()[:24]
                                       for f in sorted(files)]}
    matched = _check_hashes(ds, SimpleNamespace(properties=old))
    assert matched == [f"inputs: all {2 * N} files match the recorded hashes"]
    old["plvo_inputs:scan_sha256"][2] = "0" * 24
    assert _check_hashes(ds, SimpleNamespace(properties=old)) == [
        f"frame 2: scan file {files[2][1]} differs from the one recorded"]


def test_reproduces_from_the_dataset(run):
    root, rrd = run
    report = reproduce(rrd, root)
    assert report.reproduces, report.lines(0.01, 0.1)
    assert report.frames == list(range(N)) and report.max_diff[0] < 1e-6
    assert f"inputs: all {2 * N} files match the recorded hashes" in report.notes


def test_one_config_value_changed_departs_with_frame_and_stage(run):
    root, rrd = run
    report = reproduce(rrd, root, {"orb.n_features": 600})
    assert not report.reproduces
    assert report.stage_frame == 0 and report.stage.startswith("features/points 1000 -> 600"), report.stage
    assert report.pose_frame is not None and report.pose_diff[0] > 0.01
    text = "\n".join(report.lines(0.01, 0.1))
    assert f"departs at frame {report.pose_frame}" in text and "first changed stage result: frame 0" in text


def test_reproduces_from_the_recording_alone(run):
    _, rrd = run
    report = reproduce(rrd)  # no root: the embedded PNG and scan bytes
    assert report.source == "the inputs embedded in the recording"
    assert report.reproduces, report.lines(0.01, 0.1)


def test_a_changed_input_file_is_named(run, tmp_path):
    root, rrd = run
    copy = tmp_path / "root"
    shutil.copytree(root, copy)
    scan = copy / "sequences" / "00" / "velodyne" / "000005.bin"
    pts = np.fromfile(scan, np.float32)
    pts[0] += 1.0
    pts.tofile(scan)
    report = reproduce(rrd, copy)
    assert report.notes[1] == f"frame 5: scan file {scan} differs from the one recorded"


def test_a_changed_calibration_is_named(run, tmp_path):
    """The frames' files all match their hashes, the calibration file does not: it used to read "all files match
    the recorded hashes", then the run departed with no word of the calibration."""
    root, rrd = run
    copy = tmp_path / "root"
    shutil.copytree(root, copy)
    calib = copy / "sequences" / "00" / "calib.txt"
    lines = calib.read_text().splitlines()
    p0 = lines[0].split()
    p0[1] = f"{float(p0[1]) * 1.01:.6e}"  # fx 1 % larger
    calib.write_text("\n".join([" ".join(p0), *lines[1:]]) + "\n")
    report = reproduce(rrd, copy)
    row = fault("reproduce-calibration")
    assert report.notes[0].startswith(f"{row.message} (K (largest change"), report.notes
    assert report.notes[1].startswith("inputs: all") and not report.reproduces
    assert reproduce(rrd, root).notes[0] == "calibration: as recorded"


def test_a_failed_run_reproduces_on_what_it_wrote(run, tmp_path, monkeypatch):
    """A run that failed at frame 7 (an injected tracker bug) never wrote some stage results of its last frames
    (the map's counts of frame 6): rerun on the same data, that used to read "a stage result changed: frame 6:
    map/lines absent -> 63". Only what the recorded run wrote is compared now."""
    row = fault("reproduce-partial")
    root, _ = run
    break_tracker_at(monkeypatch, 7)
    cfg = tmp_path / "det.toml"
    cfg.write_text('[backend]\nconcurrent = false\nexecutor = "thread"\n')
    rrd = tmp_path / "failed.rrd"
    assert main_viz(["--root", str(root), "--seq", "00", "--frames", f"0:{N}", "--config", str(cfg), "--no-serve",
                     "--rrd", str(rrd), "--out", str(tmp_path / "out")]) == 1
    monkeypatch.undo()  # the rerun's tracker is the real one
    report = reproduce(rrd, root)
    assert report.frames == list(range(7)) and report.reproduces, report.lines(0.01, 0.1)
    assert any(row.message in n for n in report.notes), report.notes


def test_a_changed_frame_time_is_named(run, tmp_path):
    """The frames' times are input too (the motion model, the gap check and deskewing read them): a times.txt
    changed at frame 5, every file unchanged, used to pass as "all files match"."""
    root, rrd = run
    copy = tmp_path / "root"
    shutil.copytree(root, copy)
    times = copy / "sequences" / "00" / "times.txt"
    values = times.read_text().split()
    values[5] = f"{float(values[5]) + 0.05:.6e}"
    times.write_text("\n".join(values) + "\n")
    report = reproduce(rrd, copy)
    assert report.notes[1].startswith("frame 5: its time "), report.notes
    assert reproduce(rrd, root).notes[1].startswith("inputs: all")


def test_clip_keeps_only_the_window_and_static_data(run, tmp_path):
    _, rrd = run
    out = tmp_path / "clip.rrd"
    clip(rrd, 4, 7, out)
    data, whole = read_rrd(out), read_rrd(rrd)
    assert set(data.frames()) == {4, 5, 6}
    assert data.frames("/world/camera") == [4, 5, 6] and data.frames("/metrics/features/points") == [4, 5, 6]
    assert {"/world", "/world/camera/image"} <= set(data.static)  # calibration kept
    assert data.properties["plvo_clip:frames"] == "4:7" and data.properties["plvo_dataset:sequence"] == "00"
    # the map as it stood at frame 4 (made at an earlier keyframe) is carried to the window's first frame
    before = max(f for f in whole.frames("/world/map/points") if f < 4)
    assert 4 not in whole.frames("/world/map/points") and data.frames("/world/map/points")[0] == 4
    assert data.temporal["/world/map/points"][4] == whole.temporal["/world/map/points"][before]
    with pytest.raises(RecordingError, match="already exists"):
        clip(rrd, 4, 7, out)


def test_a_window_outside_the_recording_is_refused_and_one_partly_outside_is_cut(run, tmp_path):
    """A clip of frames the recording does not hold used to be an empty file labelled with those frames (exit 0),
    which `reproduce` then "reproduced"."""
    row = fault("clip-outside")
    _, rrd = run
    out = tmp_path / "none.rrd"
    with pytest.raises(RecordingError, match=row.message) as err:
        clip(rrd, N + 10, N + 20, out)
    assert f"holds frames 0..{N - 1}" in str(err.value) and not out.exists()
    n, a, b = clip(rrd, N - 2, N + 50, tmp_path / "end.rrd")
    data = read_rrd(tmp_path / "end.rrd")
    assert (a, b) == (N - 2, N) and data.properties["plvo_clip:frames"] == f"{N - 2}:{N}"
    assert set(data.frames()) == {N - 2, N - 1} and n > 0


def test_not_a_recording_is_a_one_line_error(tmp_path):
    bad = tmp_path / "bad.rrd"
    bad.write_bytes(b"nope")
    with pytest.raises(RecordingError, match="bad.rrd"):
        reproduce(bad)


def test_a_clip_reproduces_with_its_dataset(run, tmp_path):
    root, rrd = run
    out = tmp_path / "clip.rrd"
    clip(rrd, 3, 7, out)
    report = reproduce(out, root)  # the whole run again, compared on the clip's frames
    assert report.reproduces, report.lines(0.01, 0.1)
