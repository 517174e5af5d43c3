"""Worker processes that die or stop answering during a plvo-viz run (the deployed mode: back end, loop closer and
features each in a process of its own): the run ends within seconds with one line naming the worker, the job and
what ended it, exit 1, timings.json `failed` with that reason, no poses.txt, the recording readable and stamped
`failed`, and no zombie left. Each run has a hard time limit, so a hang fails the test instead of the suite.

The kills are real signals sent to the real worker processes, told apart by their process names (plvo.runtime.workers
names each after its core)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import psutil
import pytest
from faults_table import VIZ, fault, one_error_line, read_stderr_until, viz_env

from plvo_app.rrd_reader import read_rrd

pytestmark = pytest.mark.timeout(180)

WORKERS = {"back end": "plvo-backend", "loop closer": "plvo-loopcloser", "features": "plvo-features"}


@pytest.fixture
def town(synth_seq, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("KITTI_ROOT", raising=False)
    return ["--root", str(synth_seq), "--seq", "00", "--frames", "0:14", "--no-serve", "--rrd", "run.rrd",
            "--out", "out"]


def _worker(name: str, timeout_s: float = 60.0) -> psutil.Process:
    """This process's worker child of that name, once it has one."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        for child in psutil.Process().children():
            try:
                if child.name() == WORKERS[name]:
                    return child
            except psutil.NoSuchProcess:
                continue
        time.sleep(0.005)
    raise AssertionError(f"no {name} worker process appeared")


def _at_frame(monkeypatch, frame: int, act) -> None:
    """Call act() when the tracker starts frame `frame` (before its step)."""
    from plvo.runtime.system import System

    step = System.step

    def stepping(self, f):
        if f.index == frame:
            act()
            time.sleep(0.3)  # the death reaches the parent's pipe
        return step(self, f)

    monkeypatch.setattr(System, "step", stepping)


def _run(args, capsys) -> tuple[int, str]:
    from plvo_app.cli import main_viz

    status = main_viz(args)
    return status, capsys.readouterr().err


def _assert_failed_run(tmp_path: Path, status: int, err: str, row, must: str) -> str:
    line = one_error_line(err)
    assert status == row.exit == 1, err[-2000:]
    assert row.message in line and must in line, line
    timings = json.loads((tmp_path / "out" / "timings.json").read_text())
    assert timings["status"] == "failed" and must in timings["reason"], timings
    assert not (tmp_path / "out" / "poses.txt").exists()
    data = read_rrd(tmp_path / "run.rrd")
    assert data.properties["plvo_run:status"] == "failed"
    done = timings["frames_done"]
    assert data.frames()[:done] == list(range(done))  # every frame run is in the recording
    pid = int(line.split("(pid ")[1].split(")")[0])  # the worker the line names is reaped
    assert not psutil.pid_exists(pid) or psutil.Process(pid).status() != psutil.STATUS_ZOMBIE, pid
    return line


@pytest.mark.parametrize("name", list(WORKERS))
def test_a_worker_killed_at_start_up_ends_the_run(name, town, tmp_path, capsys):
    killer = threading.Thread(target=lambda: os.kill(_worker(name).pid, signal.SIGKILL), daemon=True)
    killer.start()
    t0 = time.monotonic()
    status, err = _run(town, capsys)
    assert time.monotonic() - t0 < 60
    line = _assert_failed_run(tmp_path, status, err, fault("worker-killed"), f"the {name} worker process (pid ")
    assert "was killed by SIGKILL before" in line


@pytest.mark.parametrize("name, frame", [("back end", 4), ("loop closer", 7), ("features", 5)])
def test_a_worker_killed_mid_run_ends_the_run_at_once(name, frame, town, tmp_path, capsys, monkeypatch):
    """Killed while the run goes (the OOM killer's way): the run stops at the next frame, not when the worker's
    next result was due (the loop closer's, 20 frames later, is past this run's end)."""
    _at_frame(monkeypatch, frame, lambda: os.kill(_worker(name).pid, signal.SIGKILL))
    status, err = _run(town, capsys)
    line = _assert_failed_run(tmp_path, status, err, fault("worker-killed"), f"the {name} worker process (pid ")
    assert "was killed by SIGKILL before" in line
    timings = json.loads((tmp_path / "out" / "timings.json").read_text())
    assert timings["frames_done"] <= frame + 3, timings  # the features are read up to 3 frames ahead


@pytest.mark.parametrize("name", ["back end", "features"])
def test_a_stopped_worker_fails_the_run_after_the_bound(name, town, tmp_path, capsys, monkeypatch):
    (tmp_path / "bound.toml").write_text("[backend]\nworker_timeout_s = 2.0\n")
    stopped: list[psutil.Process] = []

    def stop():
        stopped.append(_worker(name))
        stopped[0].send_signal(signal.SIGSTOP)

    _at_frame(monkeypatch, 3, stop)
    t0 = time.monotonic()
    status, err = _run([*town, "--config", str(tmp_path / "bound.toml")], capsys)
    assert time.monotonic() - t0 < 60
    line = _assert_failed_run(tmp_path, status, err, fault("worker-stopped"), f"the {name} worker process (pid ")
    assert "sent nothing for 2 s while" in line
    assert not stopped[0].is_running() or stopped[0].status() != psutil.STATUS_STOPPED


def test_a_killed_resource_tracker_is_not_noticed(synth_seq, tmp_path):
    """multiprocessing's resource tracker (a process every spawning program has) killed mid-run: the run completes
    and says nothing of it (the workers register no semaphore or shared memory with it)."""
    p = subprocess.Popen([*VIZ, "-v", "--root", str(synth_seq), "--seq", "00", "--no-serve", "--out",
                          str(tmp_path / "out"), "--rrd", str(tmp_path / "run.rrd")], cwd=tmp_path, env=viz_env(),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        tracker = None
        t0 = time.monotonic()
        while tracker is None and time.monotonic() - t0 < 60:
            for child in psutil.Process(p.pid).children():
                try:
                    if any("resource_tracker" in part for part in child.cmdline()):
                        tracker = child
                except psutil.NoSuchProcess:
                    continue
            time.sleep(0.05)
        assert tracker is not None, "no resource tracker: the premise of this test"
        read_stderr_until(p, "keyframe 1")  # mid-run: every worker process was made (they need the tracker)
        assert p.poll() is None, "the run ended before the tracker was killed"
        tracker.kill()
        _, rest = p.communicate(timeout=120)
        err = rest
    finally:
        p.kill()
    row = fault("tracker-killed")
    assert p.returncode == row.exit == 0, err[-3000:]
    assert "Traceback" not in err and "resource_tracker." not in err and "resource_tracker:" not in err, err[-3000:]
    assert err.strip().splitlines()[-1].startswith(row.message)
    assert json.loads((tmp_path / "out" / "timings.json").read_text())["status"] == "complete"


def test_a_resource_tracker_lost_before_a_worker_starts_is_one_warning_line(tmp_path):
    """Killed before a worker process is spawned, the tracker is started again by multiprocessing, which warns:
    in plvo's commands that is one log line, not a warning followed by its source line."""
    script = ("import os, signal, time, multiprocessing as mp; from multiprocessing import resource_tracker as rt; "
              "from plvo_app.cli import _setup_logging; _setup_logging(False); rt.ensure_running(); "
              "os.kill(rt._resource_tracker._pid, signal.SIGKILL); time.sleep(0.2); "
              "p = mp.get_context('spawn').Process(target=time.sleep, args=(0,)); p.start(); p.join()")
    proc = subprocess.run([VIZ[0], "-c", script], cwd=tmp_path, env=viz_env(), capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("WARNING py.warnings: UserWarning: resource_tracker: "), lines
