"""The outputs of a run (recording, results folder): checked before the run, written with one-line errors.

Before the first frame: `--out` must not name a file, both folders must be writable and have room for a rough
estimate of what the run writes. The results folder gets config.toml and a timings.json marked "running" at once
(a first real write), then the final status (complete, interrupted or failed, with the share of frames tracked and
the reason) at the end. A failed write raises RunFailed naming the file; the run log (run.log in the results
folder) holds what went before and any traceback.
"""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from plvo.atomic import write_text_atomic
from plvo.errors import OutputError, PlvoError, RunFailed
from plvo_app.terminal import file_level

log = logging.getLogger(__name__)

# Rough bytes a frame: the recording (a frame's JPEG at quality 40 and its overlays, the scan on keyframes; measured
# 110 kB a frame on KITTI 04 frames 0:20) and the results (poses and timings, < 1 kB).
RRD_BYTES_PER_FRAME = 100_000
RESULTS_BYTES_PER_FRAME = 1_000
RESULTS_BYTES_FIXED = 200_000  # config.toml, timings.json, run.log
MIN_TRACKED_SHARE = 0.5  # a run that tracked less than this share of its frames is "failed", not "complete"

RunStatus = Literal["complete", "degraded", "interrupted", "failed"]  # timings.json's, summary.json's, the recording's


@dataclass
class RunEnd:
    """How a run ended, settled step by step from its frames to its files (docs/faults.md): the status, why (empty
    when complete), the error raised once the results are written (None: none) and the exit status."""

    status: RunStatus = "failed"
    reason: str = ""
    error: PlvoError | None = None
    exit_code: int = 0

    def fail(self, error: PlvoError) -> None:
        self.status, self.reason, self.error = "failed", str(error), error

    @property
    def whole(self) -> bool:
        """The run's trajectory was written: complete, or degraded (some frames the motion model's guess)."""
        return self.error is None and self.status in ("complete", "degraded")


@dataclass(frozen=True)
class Outputs:
    run: str
    rrd: Path
    out: Path


def check_outputs(outs: Outputs, n_frames: int, rrd_given: bool, out_given: bool) -> list[Path]:
    """Refuse (OutputError, one line) outputs that cannot be written; make the folders. Returns the folders made,
    for `remove_made` should the run not start."""
    if out_given and outs.out.exists() and not outs.out.is_dir():
        raise OutputError(f"--out {outs.out}: is a file, not a results folder")
    if rrd_given and outs.rrd.is_dir():
        raise OutputError(f"--rrd {outs.rrd}: is a folder; give the recording's file name (e.g. run.rrd)")
    made: list[Path] = []
    try:
        for folder in (outs.rrd.parent, outs.out):
            made += _make_folder(folder)
            _probe(folder)
        need = {outs.rrd.parent: RRD_BYTES_PER_FRAME * n_frames,
                outs.out: RESULTS_BYTES_FIXED + RESULTS_BYTES_PER_FRAME * n_frames}
        _check_room(need, n_frames)
    except OutputError:
        remove_made(made)
        raise
    return made


def _make_folder(folder: Path) -> list[Path]:
    missing = [p for p in (folder, *folder.parents) if not p.exists()][::-1]
    for p in (folder, *folder.parents):
        if p.exists() and not p.is_dir():
            raise OutputError(f"{p}: is a file, so the folder {folder} cannot be made")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{folder}: cannot make the folder ({exc.strerror or exc})") from None
    return missing


def _probe(folder: Path) -> None:
    try:
        with tempfile.TemporaryFile(dir=folder) as f:
            f.write(b"plvo")
            f.flush()
    except OSError as exc:
        raise OutputError(f"{folder}: cannot write there ({exc.strerror or exc})") from None


def _check_room(need: dict[Path, int], n_frames: int) -> None:
    by_device: dict[int, tuple[Path, int]] = {}
    for folder, nbytes in need.items():
        dev = folder.stat().st_dev
        first, total = by_device.get(dev, (folder, 0))
        by_device[dev] = (first, total + nbytes)
    for folder, nbytes in by_device.values():
        free = shutil.disk_usage(folder).free
        if free < nbytes:
            raise OutputError(f"{folder}: {free / 1e6:.1f} MB free, but a run of {n_frames} frames writes about "
                              f"{nbytes / 1e6:.1f} MB there; free some space or choose --rrd / --out elsewhere")


def refuse_existing(files: list[Path], command: str, hint: str) -> None:
    """The rule for what a command writes (docs/faults.md, "Outputs"): a file that exists is never replaced; the
    command refuses, naming it, before any work (OutputError, exit 2). `hint` says what to do instead."""
    for f in files:
        if f.exists():
            raise OutputError(f"{f}: already exists; {command} never replaces a file ({hint})")


def remove_made(made: list[Path]) -> None:
    """Remove the folders `check_outputs` made, deepest first, if still empty (nothing the user had is touched)."""
    for p in reversed(made):
        try:
            p.rmdir()
        except OSError:
            pass


class RunLog:
    """The run's log in the results folder (run.log): every INFO message (DEBUG too under -vv: plvo_app.terminal),
    whatever the terminal shows, and tracebacks written only there. While it is open the root logger lets its level
    through (a root left at logging's default WARNING, as by a program that calls the commands in-process, would
    keep the INFO lines from it); `close` puts the root's level back."""

    def __init__(self, path: Path):
        self.path = path
        self.handler = logging.FileHandler(path, encoding="utf-8", delay=False)
        self.handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        self.handler.setLevel(file_level())
        root = logging.getLogger()
        root.addHandler(self.handler)
        self._root_level: int | None = None
        if root.getEffectiveLevel() > self.handler.level:
            self._root_level = root.level
            root.setLevel(self.handler.level)
        self.crash = logging.getLogger("plvo_app.crash")  # not propagated: the terminal gets one line only
        self.crash.propagate = False
        self.crash.addHandler(self.handler)

    def traceback(self, message: str) -> None:
        try:
            self.crash.error(message, exc_info=True)
            self.handler.flush()
        except Exception:  # noqa: BLE001 - a full disk must not hide the error being reported
            pass

    def close(self) -> None:
        root = logging.getLogger()
        root.removeHandler(self.handler)
        if self._root_level is not None and root.level == self.handler.level:  # unless changed meanwhile
            root.setLevel(self._root_level)
        self.crash.removeHandler(self.handler)
        self.handler.close()


def tracked_summary(frames_done: int, n_lost: int) -> tuple[int, float]:
    tracked = max(0, frames_done - n_lost)
    return tracked, (tracked / frames_done if frames_done else 0.0)


def write_json(path: Path, data: dict[str, Any]) -> None:
    """Write atomically; a failure (disk full, permissions) is a RunFailed naming the file."""
    try:
        write_text_atomic(path, json.dumps(data, indent=1) + "\n")
    except OSError as exc:
        raise RunFailed(f"{path}: cannot write the results ({exc.strerror or exc})") from None
