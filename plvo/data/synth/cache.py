"""The default town sequence that `plvo-viz` runs without a dataset: generated once, cached by its settings.

The cache lives under `$PLVO_CACHE/synth/<hash>` (or `~/.cache/plvo/synth/<hash>`). A run writes into a hidden
staging directory and renames it to `<hash>` only when every file is written, so an interrupted run never leaves
a cache that looks complete; a later call starts over.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

from plvo.data.synth.generate import GENERATOR_VERSION, SynthSettings, write_sequence

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


def cached_sequence_root(settings: SynthSettings = DEFAULT_SETTINGS, sequence: str = DEFAULT_SEQUENCE,
                         progress: Callable[[int, int], None] | None = None) -> Path:
    """Root (KITTI layout) of the cached sequence for these settings, generating it on first use."""
    settings.check()
    base = cache_dir()
    key = settings_hash(settings, sequence)
    final = base / key
    if (final / "sequences" / sequence / "calib.txt").is_file():
        return final
    base.mkdir(parents=True, exist_ok=True)
    _remove_stale_stages(base, key)
    stage = base / f".{key}.tmp-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    log.info("generating the synthetic town sequence (%d frames) into %s", settings.n_frames, final)
    try:
        write_sequence(stage, sequence, settings, progress)
        try:
            stage.rename(final)
        except OSError:
            if not (final / "sequences" / sequence / "calib.txt").is_file():
                raise  # not a concurrent run that finished first
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return final


def default_sequence_root(progress: Callable[[int, int], None] | None = None) -> Path:
    """Root of the default town sequence ('00', DEFAULT_SETTINGS), generated and cached on first use."""
    return cached_sequence_root(DEFAULT_SETTINGS, DEFAULT_SEQUENCE, progress)
