"""Faults during a plvo-viz run on the synthetic town: each stops with one line, the exit status of its row in
docs/faults.md, and outputs that say what they are (status, reason, share tracked; the .rrd readable)."""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from faults_table import break_tracker_at, fault, one_error_line, viz_env

from plvo_app.rrd_reader import read_rrd
from plvo_eval.kitti_variants import variant

_env = viz_env


@pytest.fixture
def town(synth_seq, tmp_path, monkeypatch):
    """(args running frames 0:6 of the 20-frame synthetic town without the viewer, in tmp_path)"""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("KITTI_ROOT", raising=False)
    return ["--root", str(synth_seq), "--seq", "00", "--frames", "0:6", "--no-serve"]


def _viz(args, capsys):
    from plvo_app.cli import main_viz

    status = main_viz(args)
    return status, capsys.readouterr().err


def _timings(out: Path) -> dict:
    return json.loads((out / "timings.json").read_text())


@pytest.fixture
def tmpfs(tmp_path):
    """A 2 MB tmpfs at tmp_path/disk (root only); skipped with the reason where mounting is not allowed (the
    writer made to fail, test_failed_recording_write_stops_the_run, covers the same path then)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(disk)], capture_output=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.decode().strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


# ---- arguments and outputs, refused before the run ---------------------------------------------------------------

@pytest.mark.parametrize("port", ["0", "70000", "-1"])
def test_port_out_of_range_is_one_line(town, tmp_path, capsys, port):
    row = fault("port-range")
    status, err = _viz([*town[:-1], "--port", port], capsys)
    line = one_error_line(err)
    assert status == row.exit and row.message in line and f"--port {port}" in line
    assert not (tmp_path / "recordings").exists() and not (tmp_path / "results").exists()


def test_busy_port_is_refused(town, tmp_path, capsys):
    row = fault("port-busy")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        status, err = _viz([*town[:-1], "--port", str(port)], capsys)
    line = one_error_line(err)
    assert status == row.exit and row.message in line and str(port) in line
    assert not (tmp_path / "recordings").exists() and not (tmp_path / "results").exists()


def test_out_naming_a_file_is_one_line(town, tmp_path, capsys):
    row = fault("out-file")
    (tmp_path / "taken").write_text("mine\n")
    status, err = _viz([*town, "--out", "taken"], capsys)
    line = one_error_line(err)
    assert status == row.exit and row.message in line and "taken" in line
    assert (tmp_path / "taken").read_text() == "mine\n"
    assert not (tmp_path / "recordings").exists()


def test_unwritable_output_is_refused_before_the_run(town, tmp_path, capsys):
    """A read-only file system under --out (root ignores permission bits, so a read-only tmpfs where one can be
    mounted; else a folder without write permission for an ordinary user)."""
    row = fault("out-unwritable")
    disk = tmp_path / "ro"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(disk)],
                             capture_output=True).returncode == 0
    if not mounted:
        if os.geteuid() == 0:
            pytest.skip("root without mount: no way to make a folder unwritable")
        disk.chmod(0o500)
    try:
        status, err = _viz([*town, "--out", str(disk / "out")], capsys)
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False) if mounted else disk.chmod(0o700)
    line = one_error_line(err)
    assert status == row.exit and row.message in line and str(disk / "out") in line
    assert not (tmp_path / "recordings").exists() and not (tmp_path / "results").exists()


def test_no_room_is_refused_before_the_run(town, tmp_path, capsys, monkeypatch, request):
    """20 frames need about 2.2 MB of recording and results: refused on a 2 MB tmpfs (or, where none can be
    mounted, a disk that reports 1 MB free), before anything is written; the folders made for it are removed."""
    row = fault("no-room")
    try:
        disk = request.getfixturevalue("tmpfs")
    except pytest.skip.Exception:
        disk = tmp_path / "disk"
        from plvo_app import run_outputs

        monkeypatch.setattr(run_outputs.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(2e6, 1e6, 1e6))
    args = [*town[:4], "--frames", "0:20", "--no-serve", "--rrd", str(disk / "rec" / "run.rrd"), "--out",
            str(disk / "out")]
    status, err = _viz(args, capsys)
    line = one_error_line(err)
    assert status == row.exit and row.message in line and "20 frames" in line
    assert not (disk / "rec").exists() and not (disk / "out").exists()


# ---- failed writes during the run ----------------------------------------------------------------------------------

def _fill(disk: Path) -> None:
    with open(disk / "filler", "wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * 65536)
        except OSError as exc:
            assert exc.errno == errno.ENOSPC


def test_disk_full_during_the_run(synth_seq, tmpfs, tmp_path):
    """A real full disk: another process fills the tmpfs under the recording while the run goes."""
    row = fault("disk-full")
    cmd = ["--root", str(synth_seq), "--seq", "00", "--frames", "0:15", "--no-serve", "--record", "full", "--rrd",
           str(tmpfs / "run.rrd"), "--out", "out"]  # full: every frame's image, so the file fills the disk early
    # Each frame made to take 0.25 s: the recorder hands chunks over every 2 s, and a quick machine would finish
    # these frames before the first of them reached the disk.
    slow = ("import sys, time; from plvo.runtime.system import System; step = System.step; "
            "System.step = lambda self, f: (time.sleep(0.25), step(self, f))[1]; "
            "from plvo_app.cli import main_viz; sys.exit(main_viz())")
    p = subprocess.Popen([sys.executable, "-c", slow] + cmd, cwd=tmp_path, env=_env(), stderr=subprocess.PIPE,
                         text=True)
    t0 = time.time()  # frames are on disk (the stream is written every 2 s): then the disk fills up
    while not ((tmpfs / "run.rrd").is_file() and (tmpfs / "run.rrd").stat().st_size > 200_000) \
            and time.time() - t0 < 120 and p.poll() is None:
        time.sleep(0.05)
    _fill(tmpfs)
    err = p.stderr.read()
    assert p.wait(timeout=120) == row.exit, err
    line = one_error_line(err)
    assert row.message in line and "No space left on device" in line and str(tmpfs / "run.rrd") in line
    timings = _timings(tmp_path / "out")
    assert timings["status"] == "failed" and "No space left" in timings["reason"]
    assert not (tmp_path / "out" / "poses.txt").exists()  # (the failure may come at a step or at the close)
    (tmpfs / "filler").unlink()
    data = read_rrd(tmpfs / "run.rrd")  # what was written stays readable
    assert data.properties["plvo:sequence"] == "00" and "/world" in data.static
    assert data.frames("/world/camera/image")[:2] == [0, 1]


def test_failed_recording_write_stops_the_run(town, tmp_path, capsys, monkeypatch):
    """A writer made to fail (EIO once 200 kB are written): the run stops there; the file holds what was written."""
    row = fault("write-fails")
    from plvo_app import rrd_sink

    kept, real = [], rrd_sink.RrdFileSink._write

    def failing(self, chunk, ends):
        if self.written > 200_000:
            kept.append(self.written)
            self._fail(OSError(errno.EIO, "Input/output error"))
        real(self, chunk, ends)

    monkeypatch.setattr(rrd_sink.RrdFileSink, "_write", failing)
    # The recorder hands chunks over every 2 s: a run shorter than that writes once, at the close. Each frame is
    # made to take 0.25 s, so that the file is written during the run and the failing write comes after one that
    # succeeded, whatever the machine's speed.
    from plvo.runtime.system import System

    step = System.step

    def slow_step(self, frame):
        time.sleep(0.25)
        return step(self, frame)

    monkeypatch.setattr(System, "step", slow_step)
    # full: every frame's image, so that 200 kB are written within the first frames
    status, err = _viz([*town, "--frames", "0:20", "--record", "full", "--rrd", "run.rrd", "--out", "out"], capsys)
    line = one_error_line(err)
    assert status == row.exit and row.message in line and "Input/output error" in line
    timings = _timings(tmp_path / "out")
    assert timings["status"] == "failed" and "Input/output error" in timings["reason"]
    assert not (tmp_path / "out" / "poses.txt").exists()
    assert (tmp_path / "run.rrd").stat().st_size == kept[0]
    data = read_rrd(tmp_path / "run.rrd")
    assert "/world" in data.static and data.frames("/world/camera/image")[:2] == [0, 1]


def test_failed_results_write_is_one_line(town, tmp_path, capsys, monkeypatch):
    row = fault("results-fail")
    import plvo.data.trajectory as trajectory

    def full(path, poses):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(trajectory, "write_kitti_poses", full)
    status, err = _viz([*town, "--rrd", "run.rrd", "--out", "out"], capsys)
    line = one_error_line(err)
    assert status == row.exit and row.message in line and "poses.txt" in line
    assert _timings(tmp_path / "out")["status"] == "failed"
    assert read_rrd(tmp_path / "run.rrd").properties["plvo_run:status"] == "failed"


# ---- runs that go wrong ------------------------------------------------------------------------------------------

@pytest.fixture
def no_lidar(synth_seq, tmp_path) -> Path:
    """The town's images with scans of one far point each: no usable lidar."""
    root = tmp_path / "nolidar"
    seq = root / "sequences" / "00"
    (seq / "velodyne").mkdir(parents=True)
    shutil.copytree(synth_seq / "poses", root / "poses")
    for item in (synth_seq / "sequences" / "00").iterdir():
        if item.name != "velodyne":
            (seq / item.name).symlink_to(item, target_is_directory=item.is_dir())
    for k in range(20):
        np.array([[500.0, 0, 0, 0]], np.float32).tofile(seq / "velodyne" / f"{k:06d}.bin")
    return root


def test_run_that_tracked_nothing_is_failed(no_lidar, tmp_path, capsys, monkeypatch):
    row = fault("tracked-little")
    monkeypatch.chdir(tmp_path)
    args = ["--root", str(no_lidar), "--seq", "00", "--frames", "0:6", "--no-serve", "--ablation", "tracker_only",
            "--rrd", "run.rrd", "--out", "out"]
    status, err = _viz(args, capsys)
    line = one_error_line(err)
    assert status == row.exit and row.message in line and "of 6 frames" in line
    assert err.strip().splitlines()[-1] == line  # the last line says how much was tracked
    timings = _timings(tmp_path / "out")
    assert timings["status"] == "failed" and timings["frames_done"] == 6
    assert timings["frames_tracked"] <= 1 and timings["tracked_share"] < 0.5 and "tracked only" in timings["reason"]
    assert not (tmp_path / "out" / "poses.txt").exists()
    assert read_rrd(tmp_path / "run.rrd").properties["plvo_run:status"] == "failed"


def test_complete_run_says_how_much_was_tracked(town, tmp_path, capsys):
    status, err = _viz([*town, "--out", "out"], capsys)
    assert status == 0, err
    assert re.fullmatch(r"complete: 6 frames at [0-9.]+ frames/s, 6 tracked \(100%\)", err.strip().splitlines()[-1])
    timings = _timings(tmp_path / "out")
    assert timings["status"] == "complete" and timings["tracked_share"] == 1.0
    assert (tmp_path / "out" / "poses.txt").stat().st_mode & 0o777 == 0o644


def test_worker_error_is_one_line(town, tmp_path, capsys, monkeypatch):
    row = fault("worker-error")
    from plvo.backend import worker

    def broken(self, job):
        raise RuntimeError("injected back-end fault")

    monkeypatch.setattr(worker.BackendCore, "process", broken)
    # a worker thread, so that the injected fault is in this process (a worker process runs the same core)
    (tmp_path / "thread.toml").write_text('[backend]\nexecutor = "thread"\n')
    status, err = _viz([*town, "--out", "out", "--config", str(tmp_path / "thread.toml")], capsys)
    line = one_error_line(err)
    assert status == row.exit and row.message in line
    timings = _timings(tmp_path / "out")
    assert timings["status"] == "failed" and not (tmp_path / "out" / "poses.txt").exists()
    assert "injected back-end fault" in (tmp_path / "out" / "run.log").read_text()


def test_unexpected_error_names_the_frame(town, tmp_path, capsys, monkeypatch):
    row = fault("unexpected")
    break_tracker_at(monkeypatch, 2)
    status, err = _viz([*town, "--out", "out"], capsys)
    line = one_error_line(err)
    assert status == row.exit and row.message in line
    assert line.startswith("error: frame 2: unexpected ValueError: injected tracker bug (see the log out/run.log)")
    log = (tmp_path / "out" / "run.log").read_text()
    assert "Traceback" in log and "ValueError: injected tracker bug" in log
    timings = _timings(tmp_path / "out")
    assert timings["status"] == "failed" and "frame 2" in timings["reason"] and timings["frames_done"] == 2


def test_a_read_ahead_frame_is_named_by_its_own_number(synth_seq, tmp_path, capsys, monkeypatch):
    """The frames are read ahead of the tracker: an unreadable scan of frame 4 (a folder in its place) used to be
    "frame 2: unexpected IsADirectoryError", and an unexpected error while reading named the frame being tracked.
    Now the scan is one line naming the file and its frame, and any other reading error names the frame read."""
    row = fault("scan-unreadable")
    monkeypatch.chdir(tmp_path)
    root = variant(synth_seq, "00", tmp_path / "v", 8)
    scan = root / "sequences" / "00" / "velodyne" / "000004.bin"
    scan.unlink()
    scan.mkdir()
    status, err = _viz(["--root", str(root), "--seq", "00", "--no-serve", "--out", "out"], capsys)
    line = one_error_line(err)
    assert status == row.exit and row.message in line and f"{scan}: unreadable scan (frame 4)" in line, line
    assert _timings(tmp_path / "out")["status"] == "failed"

    from plvo.data.kitti import KittiOdometry

    real = KittiOdometry.__getitem__

    def reading_bug(self, i):
        if self.frame_indices[i] == 5:
            raise ValueError("injected reading bug")
        return real(self, i)

    monkeypatch.setattr(KittiOdometry, "__getitem__", reading_bug)
    status, err = _viz(["--root", str(synth_seq), "--seq", "00", "--frames", "0:8", "--no-serve", "--out", "out2"],
                       capsys)
    line = one_error_line(err)
    assert status == 1 and line.startswith("error: frame 5: unexpected ValueError: injected reading bug"), line


def test_a_file_that_blocks_is_named_within_a_bound(synth_seq, tmp_path, capsys, monkeypatch):
    """An image path that blocks (a pipe nobody writes, a hung network mount) was waited on for minutes (the
    worker timeout) and then named by the frame before it, without the file. Now a frame's files that take over
    READ_TIMEOUT_S (60 s; 2 s here) to read are one line naming them."""
    row = fault("read-blocks")
    from plvo.runtime import prefetch

    monkeypatch.setattr(prefetch, "READ_TIMEOUT_S", 2.0)
    monkeypatch.chdir(tmp_path)
    root = variant(synth_seq, "00", tmp_path / "v", 8)
    image = root / "sequences" / "00" / "image_0" / "000004.png"
    image.unlink()
    os.mkfifo(image)
    try:
        t0 = time.monotonic()
        status, err = _viz(["--root", str(root), "--seq", "00", "--no-serve", "--out", "out"], capsys)
        line = one_error_line(err)
        assert status == row.exit and row.message in line and line.startswith("error: frame 4: ") \
            and str(image) in line, line
        assert time.monotonic() - t0 < 120 and _timings(tmp_path / "out")["status"] == "failed"
    finally:
        try:  # lets the reading thread's open return and the thread end
            os.close(os.open(image, os.O_WRONLY | os.O_NONBLOCK))
        except OSError:  # no reader waits on it (ENXIO)
            pass


def test_recording_cut_mid_message_is_read(tmp_path, caplog):
    """A .rrd cut mid-message (SIGKILL while writing): `plvo view` reads what is complete and says so."""
    import rerun as rr

    from plvo_app.cmd_view import view
    from plvo_app.rrd_sink import RrdFileSink, complete_prefix

    row = fault("rrd-cut")
    rec = rr.RecordingStream("plvo")
    sink = RrdFileSink(rec, tmp_path / "full.rrd")
    for f in range(6):
        rec.set_time("frame", sequence=f)
        rec.log("world/camera/image", rr.Points2D(np.random.default_rng(f).random((50, 2))))
        rec.flush()
        sink._write_pending()  # one message batch per frame
    sink.close()
    raw = (tmp_path / "full.rrd").read_bytes()
    cut = tmp_path / "cut.rrd"
    cut.write_bytes(raw[:len(raw) - 40])
    assert 0 < complete_prefix(cut) < cut.stat().st_size
    data = read_rrd(cut)
    assert data.frames("/world/camera/image") == [0, 1, 2, 3, 4]  # the last frame's message was cut
    assert row.message in caplog.text
    assert view(cut, serve=False) == row.exit
