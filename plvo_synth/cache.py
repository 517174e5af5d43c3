"""The default town sequence that `plvo-viz` runs without a dataset: generated once, cached by its settings.

The cache lives under `$PLVO_CACHE/synth/<hash>` (or `~/.cache/plvo/synth/<hash>`). The first call writes into a
hidden staging directory the text files, the ground truth and the frames it needs (all, or the first `stop`), and
renames it to `<hash>` only when they are written, so an interrupted run never leaves a cache that looks complete;
a later call starts over. A later call that needs more frames renders them in place, one process at a time, each
frame's image written last and whole, so a reader sees frames 0..n-1 complete (the same bits as in one go: every
frame has its own random stream).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import os
import shutil
from collections.abc import Callable, Iterator
from dataclasses import asdict
from pathlib import Path

from plvo_synth.generate import (
    GENERATOR_VERSION,
    SynthSettings,
    extend_sequence,
    rendered_frames,
    write_sequence,
)

log = logging.getLogger(__name__)

DEFAULT_SEQUENCE = "00"
# 300 frames at 10 m/s: 300 m, once around a block and 30+ m along the first street again (a loop closure).
DEFAULT_SETTINGS = SynthSettings(n_frames=300, seed=0, speed_mps=10.0, loop=True, stops=False)


def cache_dir() -> Path:
    """Directory holding cached synthetic sequences: $PLVO_CACHE/synth or ~/.cache/plvo/synth."""
    base = os.environ.get("PLVO_CACHE")
    return (Path(base) if base else Path.home() / ".cache" / "plvo") / "synth"


def settings_hash(settings: SynthSettings, sequence: str = DEFAULT_SEQUENCE) -> str:
    text = json.dumps({"v": GENERATOR_VERSION, "seq": sequence, **asdict(settings)}, sort_keys=True,
                      default=lambda v: v.item())
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _remove_stale_stages(base: Path, key: str) -> None:
    for stage in base.glob(f".{key}.tmp-*"):
        pid = stage.name.rsplit("-", 1)[-1]
        alive = True
        try:
            os.kill(int(pid), 0)
        except (ValueError, ProcessLookupError):
            alive = False
        except PermissionError:
            pass
        if not alive:
            shutil.rmtree(stage, ignore_errors=True)


def cached_frames(settings: SynthSettings = DEFAULT_SETTINGS, sequence: str = DEFAULT_SEQUENCE) -> int:
    """How many frames (from frame 0) of these settings' sequence the cache holds (0: none yet)."""
    seq_dir = cache_dir() / settings_hash(settings, sequence) / "sequences" / sequence
    return rendered_frames(seq_dir) if (seq_dir / "calib.txt").is_file() else 0


def cached_sequence_root(settings: SynthSettings = DEFAULT_SETTINGS, sequence: str = DEFAULT_SEQUENCE,
                         progress: Callable[[int, int], None] | None = None, stop: int | None = None) -> Path:
    """Root (KITTI layout) of the cached sequence for these settings, holding at least frames 0..stop-1 (all by
    default): generated on first use, extended when a later call wants more frames than it holds. A run of the
    first 120 frames waits for 120 frames, not for the whole sequence."""
    settings.check()
    stop = settings.n_frames if stop is None else max(1, min(stop, settings.n_frames))
    base = cache_dir()
    key = settings_hash(settings, sequence)
    final = base / key
    if (final / "sequences" / sequence / "calib.txt").is_file():
        if rendered_frames(final / "sequences" / sequence) < stop:
            with _locked(base / f".{key}.lock"):
                _tidy(final / "sequences" / sequence)
                log.info("extending the synthetic town sequence to %d frames in %s", stop, final)
                extend_sequence(final, sequence, settings, stop, progress)
        return final
    base.mkdir(parents=True, exist_ok=True)
    _remove_stale_stages(base, key)
    stage = base / f".{key}.tmp-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    log.info("generating the synthetic town sequence (%d of %d frames) into %s", stop, settings.n_frames, final)
    try:
        write_sequence(stage, sequence, settings, progress, stop)
        try:
            stage.rename(final)
        except OSError:
            if not (final / "sequences" / sequence / "calib.txt").is_file():
                raise  # not a concurrent run that finished first
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return final


def default_sequence_root(progress: Callable[[int, int], None] | None = None, stop: int | None = None) -> Path:
    """Root of the default town sequence ('00', DEFAULT_SETTINGS) with at least frames 0..stop-1 (all by default),
    generated and cached on first use, extended on later ones."""
    return cached_sequence_root(DEFAULT_SETTINGS, DEFAULT_SEQUENCE, progress, stop)


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """One process at a time extends a cached sequence (another waits, then finds the frames there)."""
    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _tidy(seq_dir: Path) -> None:
    """Remove what an interrupted extension left past the whole frames (a scan without its image, a hidden
    half-written file), so that the reader's listing holds frames 0..n-1 exactly."""
    n = rendered_frames(seq_dir)
    for sub, suffix in (("image_0", ".png"), ("velodyne", ".bin"), ("gt/depth", ".npy")):
        folder = seq_dir / sub
        if not folder.is_dir():
            continue
        for f in folder.iterdir():
            if f.name.startswith(".") or (f.stem.isdigit() and f.suffix == suffix and int(f.stem) >= n):
                f.unlink(missing_ok=True)
