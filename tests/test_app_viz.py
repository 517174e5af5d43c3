"""plvo-viz end to end: the .rrd holds every entity the pipeline has so far, Ctrl-C keeps a readable recording,
bad input is a one-line error, and the library imports no viewer."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from plvo_app.rrd_reader import read_rrd

REPO = Path(__file__).resolve().parents[1]
VIZ = [sys.executable, "-c", "import sys; from plvo_app.cli import main_viz; sys.exit(main_viz())"]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("KITTI_ROOT", None)
    env["PYTHONPATH"] = f"{REPO}{os.pathsep}{env.get('PYTHONPATH', '')}"
    return env


def viz(args: list[str], cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(VIZ + args, cwd=cwd, env=_env(), capture_output=True, text=True, timeout=timeout)


def _only(folder: Path, pattern: str) -> Path:
    found = sorted(folder.glob(pattern))
    assert len(found) == 1, found
    return found[0]


@pytest.fixture(scope="module")
def kitti_run(kitti_root, tmp_path_factory):
    cwd = tmp_path_factory.mktemp("viz")
    proc = viz(["--root", str(kitti_root), "--seq", "04", "--frames", "3:10", "--no-serve"], cwd)
    assert proc.returncode == 0, proc.stderr
    return cwd, proc


def test_recording_holds_every_stage_so_far(kitti_run):
    from plvo.system import default_stages

    cwd, _ = kitti_run
    data = read_rrd(_only(cwd / "recordings", "04_*.rrd"))
    frames, keyframes = list(range(3, 10)), [3, 6, 9]
    expect = {"/world/camera": frames, "/world/camera/image": frames, "/metrics/time/total": frames,
              "/world/lidar/scan": keyframes, "/world/camera/image/lidar": keyframes, "/world/keyframes": keyframes}
    stages = default_stages()
    if stages.extract_features is not None:
        expect.update({e: frames for e in ("/world/camera/image/orb", "/world/camera/image/lsd_raw",
                                           "/world/camera/image/lsd_merged", "/metrics/time/features")})
    if stages.extract_depth is not None:
        expect.update({"/world/depth/lines": keyframes, "/metrics/time/depth": keyframes})
    for entity, want in expect.items():
        assert data.frames(entity) == want, entity
    assert {"/world", "/world/camera/image", "/world/trajectory/gt"} <= set(data.static)
    props = data.properties
    assert props["plvo_run:status"] == "complete" and props["plvo_run:frames_done"] == 7
    assert "--frames 3:10" in props["plvo:command_line"] and "[orb]" in props["plvo:config"]
    assert props["plvo:git_revision"] and props["plvo:version"]


def test_results_folder(kitti_run):
    cwd, proc = kitti_run
    out = _only(cwd / "results", "04_*")
    assert (out / "config.toml").read_text().startswith("[orb]")
    timings = json.loads((out / "timings.json").read_text())
    assert timings["status"] == "complete" and timings["frames_done"] == 7
    assert timings["stages"]["total"]["runs"] == 7 and timings["frames_per_second"] > 0
    # without a tracker there is no estimate, and ground truth is never written in its place
    assert not (out / "poses.txt").exists()
    assert "odometry is not implemented yet" in proc.stderr
    assert "frame/s" in proc.stderr  # the progress bar


def test_second_run_never_overwrites(kitti_root, tmp_path):
    for _ in range(2):
        proc = viz(["--root", str(kitti_root), "--seq", "04", "--frames", "0:2", "--no-serve"], tmp_path)
        assert proc.returncode == 0, proc.stderr
    assert len(list((tmp_path / "recordings").glob("04_*.rrd"))) == 2
    assert len(list((tmp_path / "results").glob("04_*"))) == 2
    rrd = next((tmp_path / "recordings").glob("*.rrd"))
    proc = viz(["--root", str(kitti_root), "--seq", "04", "--frames", "0:2", "--no-serve", "--rrd", str(rrd)],
               tmp_path)
    assert proc.returncode == 2 and "already exists" in proc.stderr


def test_ctrl_c_keeps_a_readable_recording(kitti_root, tmp_path):
    cmd = ["--root", str(kitti_root), "--seq", "04", "--no-serve", "--rrd", "cut.rrd", "--out", "out"]
    p = subprocess.Popen(VIZ + cmd, cwd=tmp_path, env=_env(), stderr=subprocess.PIPE, text=True)
    seen = ""
    t0 = time.time()
    while "4/51" not in seen and time.time() - t0 < 60:  # wait until a few frames are in
        seen += p.stderr.read(1)
    p.send_signal(signal.SIGINT)
    err = seen + p.stderr.read()
    assert p.wait(timeout=60) == 130, err
    data = read_rrd(tmp_path / "cut.rrd")
    done = data.properties["plvo_run:frames_done"]
    assert data.properties["plvo_run:status"] == "interrupted" and 4 <= done < 51
    assert data.frames("/world/camera/image")[:4] == [0, 1, 2, 3]
    timings = json.loads((tmp_path / "out" / "timings.json").read_text())
    assert timings["status"] == "interrupted" and timings["frames_done"] == done
    assert not (tmp_path / "out" / "poses.txt").exists()
    assert not list(tmp_path.rglob("*.part"))  # no half-written file left behind
    assert "interrupted after" in err


@pytest.mark.parametrize("args, message", [
    (["--root", "/nonexistent/kitti", "--seq", "04"], "/nonexistent/kitti"),
    (["--seq", "04", "--frames", "5:2"], "frames '5:2'"),
    (["--seq", "04", "--frames", "x:3"], "frames 'x:3'"),
    (["--seq", "04", "--config", "missing.toml"], "missing.toml"),
    (["--seq", "04", "--ablation", "nonsense"], "unknown ablation"),
])
def test_bad_input_one_line_error(kitti_root, tmp_path, args, message):
    if "--root" not in args:
        args = ["--root", str(kitti_root), *args]
    proc = viz([*args, "--no-serve"], tmp_path, timeout=60)
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if not ln.startswith("INFO")]
    assert len(lines) == 1 and lines[0].startswith("error:") and message in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "recordings").exists() and not (tmp_path / "results").exists()


def test_library_imports_no_viewer():
    code = ("import sys, plvo.system, plvo.recording, plvo.results; "
            "s = plvo.system.System(__import__('plvo.config').config.SystemConfig()); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('rerun', 'viser')))")
    out = subprocess.run([sys.executable, "-c", code], env=_env(), capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
