"""Where a result file's figures come from: revision, date, machine, load and command (one block for every file).

`start()` when the work begins (the load then), `finish(block)` when its result is written (the load then, and
the end date): a figure read from a shared machine can only be judged with the load it ran under beside it.
"""

from __future__ import annotations

import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
SCHEMA = "plvo.provenance/1"  # the files' format name, kept from the module's first home


def utc_now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def git_state() -> dict[str, Any]:
    """{"revision": full hash or None (not a git checkout), "dirty": tracked files changed (None if unknown)}."""
    rev = _git("rev-parse", "HEAD") if (REPO / ".git").exists() else None
    if rev is None:
        return {"revision": None, "dirty": None}
    status = _git("status", "--porcelain", "--untracked-files=no")
    return {"revision": rev, "dirty": None if status is None else bool(status)}


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict[str, Any]:
    """CPU model, cores (all, and those this process may use), memory, OS, Python."""
    try:
        mem_mb = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**20)
    except (ValueError, OSError, AttributeError):
        mem_mb = None
    return {"cpu_model": cpu_model(), "cpu_count": os.cpu_count(),
            "cpu_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
            "mem_total_mb": mem_mb, "os": platform.platform(), "hostname": platform.node(),
            "python": platform.python_version()}


def plvo_version() -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("plvo")
    except PackageNotFoundError:
        return None


def load() -> list[float]:
    """The 1, 5 and 15 minute load averages, rounded."""
    return [round(x, 2) for x in os.getloadavg()]


def start(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """The block at the start of a piece of work; argv: the command line (default sys.argv)."""
    return {"schema": SCHEMA, **git_state(), "plvo_version": plvo_version(), "started_utc": utc_now(),
            "command_line": shlex.join(sys.argv if argv is None else argv), "machine": machine(),
            "load_start": load()}


def finish(block: dict[str, Any]) -> dict[str, Any]:
    """A copy of a start() block with the end's date and load."""
    return {**block, "finished_utc": utc_now(), "load_end": load()}
