"""Real signals to a real plvo-viz process on the synthetic town: SIGTERM is handled like Ctrl-C, a second Ctrl-C
during the clean-up loses nothing, and quitting the viewer after a complete run is not "interrupted"."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
from pathlib import Path

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
    p = _start(synth_seq, tmp_path, "--no-serve")
    seen = read_stderr_until(p, "frame 3: keyframe")
    p.send_signal(signal.SIGTERM)
    err = seen + p.stderr.read()
    assert p.wait(timeout=120) == row.exit, err
    assert row.message in err
    _check_interrupted(tmp_path, err, "SIGTERM")


def test_sigint_twice_keeps_the_results(synth_seq, tmp_path):
    """The second Ctrl-C arrives while the recording is closed and the results written: it is noted, not obeyed."""
    row = fault("sigint")
    p = _start(synth_seq, tmp_path, "--no-serve")
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
