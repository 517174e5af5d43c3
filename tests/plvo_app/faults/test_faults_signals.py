"""Real signals to a real plvo-viz process on the synthetic town: SIGTERM is handled like Ctrl-C, a second Ctrl-C
during the clean-up loses nothing, and quitting the viewer after a complete run is not "interrupted"."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest
from faults_table import VIZ, fault, read_stderr_until, viz_env

from plvo_app.rrd_reader import read_rrd

_env = viz_env


def _start(synth_seq: Path, cwd: Path, *extra: str) -> subprocess.Popen:
    cmd = ["--root", str(synth_seq), "--seq", "00", "--rrd", "run.rrd", "--out", "out", *extra]
    return subprocess.Popen(VIZ + cmd, cwd=cwd, env=_env(), stderr=subprocess.PIPE, text=True)


def _check_interrupted(cwd: Path, err: str, reason: str) -> None:
    data = read_rrd(cwd / "run.rrd")
    done = data.properties["plvo_run:frames_done"]
    assert data.properties["plvo_run:status"] == "interrupted" and 3 <= done < 20, err
    assert data.frames("/metrics/time/total") == list(range(done))  # scalars flushed on close
    timings = json.loads((cwd / "out" / "timings.json").read_text())
    assert timings["status"] == "interrupted" and timings["reason"] == reason and timings["frames_done"] == done
    assert not (cwd / "out" / "poses.txt").exists()
    assert not list(cwd.rglob("*.part")) and "Traceback" not in err


def test_sigterm_is_handled_like_ctrl_c(synth_seq, tmp_path):
    row = fault("sigterm")
    p = _start(synth_seq, tmp_path, "--no-serve", "-v")  # -v: the INFO lines waited for are shown
    seen = read_stderr_until(p, "frame 3: keyframe")
    p.send_signal(signal.SIGTERM)
    err = seen + p.stderr.read()
    assert p.wait(timeout=120) == row.exit, err
    assert row.message in err
    _check_interrupted(tmp_path, err, "SIGTERM")


def test_sigint_twice_keeps_the_results(synth_seq, tmp_path):
    """The second Ctrl-C arrives while the recording is closed and the results written: it is noted, not obeyed."""
    row = fault("sigint")
    p = _start(synth_seq, tmp_path, "--no-serve", "-v")  # -v: the INFO lines waited for are shown
    seen = read_stderr_until(p, "frame 3: keyframe")
    p.send_signal(signal.SIGINT)
    seen += read_stderr_until(p, row.message)
    p.send_signal(signal.SIGINT)
    err = seen + p.stderr.read()
    assert p.wait(timeout=120) == row.exit, err
    assert "SIGINT: finishing writing the results first" in err
    _check_interrupted(tmp_path, err, "Ctrl-C")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_quitting_the_viewer_after_a_complete_run(synth_seq, tmp_path):
    row = fault("viewer-quit")
    p = _start(synth_seq, tmp_path, "--frames", "0:4", "--port", str(_free_port()))
    seen = read_stderr_until(p, "serving the run: http://127.0.0.1:")
    p.send_signal(signal.SIGINT)
    err = seen + p.stderr.read()
    assert p.wait(timeout=120) == row.exit, err
    assert row.message in err and "interrupted" not in err and "Traceback" not in err
    timings = json.loads((tmp_path / "out" / "timings.json").read_text())
    assert timings["status"] == "complete" and (tmp_path / "out" / "poses.txt").is_file()
    assert read_rrd(tmp_path / "run.rrd").properties["plvo_run:status"] == "complete"


def _start_own_group(synth_seq: Path, cwd: Path, *extra: str) -> subprocess.Popen:
    """plvo-viz as a terminal runs it: in a process group of its own, which the terminal's signals reach whole."""
    cmd = ["--root", str(synth_seq), "--seq", "00", "--rrd", "run.rrd", "--out", "out", "--no-serve", *extra]
    return subprocess.Popen(VIZ + cmd, cwd=cwd, env=_env(), stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


@pytest.mark.parametrize("signum,to_group", [(signal.SIGHUP, True), (signal.SIGQUIT, False)],
                         ids=["sighup-closed-terminal", "sigquit"])
def test_other_ending_signals_are_handled_like_ctrl_c(synth_seq, tmp_path, signum, to_group):
    """A closed terminal or ssh connection (SIGHUP to the whole process group, the worker processes too) and
    Ctrl-\\ (SIGQUIT) used to end the run with no word, its results "running" for ever and the recording without
    its footer: now they take Ctrl-C's path."""
    row = fault("signal-other")
    p = _start_own_group(synth_seq, tmp_path, "-v")  # -v: the INFO lines waited for are shown
    seen = read_stderr_until(p, "frame 3: keyframe")
    os.killpg(p.pid, signum) if to_group else p.send_signal(signum)
    err = seen + p.stderr.read()
    assert p.wait(timeout=120) == 128 + signum, err
    assert row.message in err
    _check_interrupted(tmp_path, err, signal.Signals(signum).name)


def test_ctrl_c_during_start_up_leaves_no_running_results(synth_seq, tmp_path):
    """Ctrl-C to the whole group while the worker processes start (their imports take a second or two): one line,
    exit 130, no worker's traceback, and no results folder left "running" (the start-up's files are removed, so
    the same --out can be given again; a signal that lands once the frames run leaves them "interrupted")."""
    row = fault("startup-interrupted")
    p = _start_own_group(synth_seq, tmp_path)
    timings = tmp_path / "out" / "timings.json"
    t0 = time.time()
    while not timings.exists() and p.poll() is None and time.time() - t0 < 120:
        time.sleep(0.005)  # the outputs are made: the worker processes are started next
    os.killpg(p.pid, signal.SIGINT)
    err = p.stderr.read()
    assert p.wait(timeout=120) == row.exit, err
    assert row.message in err and "Traceback" not in err and "Error" not in err, err
    if timings.exists():  # the signal came once the frames ran
        assert json.loads(timings.read_text())["status"] == "interrupted", err
        return
    assert not (tmp_path / "out").exists(), list((tmp_path / "out").iterdir())
    again = subprocess.run(VIZ + ["--root", str(synth_seq), "--seq", "00", "--out", "out", "--frames", "0:3",
                                  "--rrd", "again.rrd", "--no-serve"],
                           cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-2000:]


def test_a_closed_stderr_does_not_end_the_run(synth_seq, tmp_path):
    """`plvo-viz ... 2>&1 | head`: the reader of stderr leaves after the first lines; the run used to die as an
    unexpected error on its next log line. Now what nobody reads is dropped and the run completes."""
    row = fault("stderr-closed")
    p = _start_own_group(synth_seq, tmp_path, "--frames", "0:8", "-v")  # -v: the dataset's INFO line is shown
    read_stderr_until(p, "frames (0..")
    p.stderr.close()
    assert p.wait(timeout=300) == row.exit
    timings = json.loads((tmp_path / "out" / "timings.json").read_text())
    assert timings["status"] == "complete" and timings["frames_done"] == 8, timings
    assert (tmp_path / "out" / "poses.txt").read_text().count("\n") == 8
    assert read_rrd(tmp_path / "run.rrd").properties["plvo_run:status"] == "complete"


def test_too_few_open_files_is_one_line_naming_the_limit(synth_seq, tmp_path):
    """A start-up under `ulimit -n 20`: it used to end as "unexpected OSError" (and before that left its results
    folder "running"); now one line names the limit, and nothing is left."""
    import resource

    row = fault("limit-reached")

    def few_files() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (20, 20))

    p = subprocess.run(VIZ + ["--root", str(synth_seq), "--seq", "00", "--frames", "0:3", "--rrd", "run.rrd",
                              "--out", "out", "--no-serve"], cwd=tmp_path, env=_env(), capture_output=True, text=True,
                       timeout=300, preexec_fn=few_files)
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("error:")]
    assert p.returncode == row.exit and len(lines) == 1 and "Traceback" not in p.stderr, p.stderr[-2000:]
    assert row.message in lines[0] and "may open 20" in lines[0] and "unexpected" not in lines[0], lines
    timings = tmp_path / "out" / "timings.json"
    assert not timings.exists() or json.loads(timings.read_text())["status"] == "failed"


def test_limits_are_named_not_unexpected():
    import errno as e

    from plvo_app.guards import limit_reached

    assert "a thread could not be started" in limit_reached(RuntimeError("can't start new thread"))
    assert "out of memory" in limit_reached(MemoryError())
    assert "out of memory" in limit_reached(ImportError("x.so: failed to map segment from shared object"))
    assert "too many open files" in limit_reached(OSError(e.EMFILE, "Too many open files"))
    assert limit_reached(ValueError("a bug")) is None and limit_reached(OSError(e.ENOENT, "no such file")) is None
