"""The table of docs/faults.md, parsed: tests look their row up by id and assert its exit status and message."""

from __future__ import annotations

import os
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path

DOC = Path(__file__).resolve().parents[2] / "docs" / "faults.md"


@dataclass(frozen=True)
class Fault:
    id: str
    fault: str
    message: str  # the text between backticks in the message column ("" when none)
    exit: int
    left: str
    test: str  # tests/file.py::test_name


def faults() -> dict[str, Fault]:
    rows = {}
    for line in DOC.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 6 or cells[0] in ("id", "---"):
            continue
        m = re.search(r"`([^`]*)`", cells[2])
        rows[cells[0]] = Fault(cells[0], cells[1], m.group(1) if m else "", int(cells[3]), cells[4], cells[5])
    return rows


def fault(fault_id: str) -> Fault:
    return faults()[fault_id]


def one_error_line(stderr: str) -> str:
    """The single `error:` line of stderr (asserting there is exactly one and no traceback)."""
    lines = [ln for ln in stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr[-3000:]
    return lines[0]


REPO = Path(__file__).resolve().parents[2]
# Ctrl-C as a user's terminal gives it: a test runner started in the background by a non-interactive shell has
# SIGINT ignored, and Python keeps an inherited SIG_IGN, so the signal tests would see no Ctrl-C at all.
VIZ = [sys.executable, "-c", "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
       "from plvo_app.cli import main_viz; sys.exit(main_viz())"]


def read_stderr_until(p, text: str, timeout: float = 120) -> str:
    """What a subprocess wrote to stderr up to `text` (a log line: tqdm may skip drawing any count on a fast run)."""
    seen, t0 = "", time.time()
    while text not in seen and time.time() - t0 < timeout:
        ch = p.stderr.read(1)
        if not ch:
            break
        seen += ch
    assert text in seen, seen[-2000:]
    return seen


def viz_env() -> dict[str, str]:
    """The environment for a plvo-viz subprocess of this checkout (no $KITTI_ROOT)."""
    env = dict(os.environ)
    env.pop("KITTI_ROOT", None)
    env["PYTHONPATH"] = f"{REPO}{os.pathsep}{env.get('PYTHONPATH', '')}"
    return env


def break_tracker_at(monkeypatch, frame_index: int) -> None:
    """A bug in the tracker: Frontend.track raises ValueError("injected tracker bug") at that frame."""
    from plvo.tracking.frontend import Frontend

    real = Frontend.track

    def track(self, frame):
        if frame.index == frame_index:
            raise ValueError("injected tracker bug")
        return real(self, frame)

    monkeypatch.setattr(Frontend, "track", track)
