"""Rewrite a recording with its chunks merged as `rerun rrd optimize` would leave them (Rerun's live profile).

A run is logged as it goes, so its chunks are cut by the batcher's clock (each flush one chunk an entity: the
count grows with the run's duration, not its content). On 300 town frames at the default level, 451 chunks
became 92 and the file 12 % smaller. The recorder compacts the small levels on close; `plvo clip` writes through
the same function.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from pathlib import Path

import rerun as rr

from plvo_app.rrd_blueprint import blueprint
from plvo_app.rrd_reader import open_rrd

log = logging.getLogger(__name__)


def write_chunks(out: Path, chunks: Iterable[rr.chunk.Chunk] | rr.chunk.LazyChunkStream, recording_id: str,
                 application_id: str = "plvo") -> None:
    """Write `chunks`, compacted, with plvo's default blueprint, to `out` (which must not be in use)."""
    stream = chunks if isinstance(chunks, rr.chunk.LazyChunkStream) else rr.chunk.LazyChunkStream.from_iter(chunks)
    store = stream.collect(optimize=rr.chunk.OptimizationProfile.LIVE)
    rec = rr.RecordingStream(application_id, recording_id=recording_id)
    rec.save(out, default_blueprint=blueprint())
    rec.send_chunks(store)
    rec.flush()
    rec.disconnect()


def compact(path: Path) -> bool:
    """Replace `path` by its compacted copy once that is complete (an atomic rename); on any failure the file is
    left as it was written. Returns whether it was compacted."""
    tmp = path.with_name(f".{path.name}.compact-{os.getpid()}")
    try:
        reader = open_rrd(path)
        entry = reader.recordings()[0]
        write_chunks(tmp, reader.stream(), entry.recording_id, entry.application_id)
        os.replace(tmp, path)
        return True
    except Exception as exc:  # noqa: BLE001 - a recording that cannot be compacted stays as written
        log.warning("%s: not compacted (%s); kept as written", path, exc)
        return False
    finally:
        tmp.unlink(missing_ok=True)
