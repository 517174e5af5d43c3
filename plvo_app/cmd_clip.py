"""Cut a recording down to a window of frames, for an attachment: `plvo clip FILE.rrd --frames A:B --out OUT.rrd`.

Static data (calibration, ground truth, the recording's properties) is kept, with a `plvo_clip` property saying
what was cut. Each entity's last row before A (the map, the trajectory, the graph as they stood) is carried to
frame A, so the window opens on the scene as it was rather than an empty one; time series and the log are cut
without carry. The chunks are compacted as `rerun rrd optimize` would (Rerun's live profile).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from plvo.errors import RecordingError
from plvo_app.recording_levels import parse_window

if TYPE_CHECKING:
    import pyarrow as pa

# Rerun and pyarrow are imported by the functions that read and write recordings: `plvo clip --help` answers at once.
NO_CARRY = ("/metrics", "/log", "/inputs")  # a value of these belongs to its frame, not to the frames after it


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", type=Path, metavar="FILE.rrd", help="a recording written by plvo-viz")
    p.add_argument("--frames", required=True, metavar="A:B", help="keep frames A to B-1")
    p.add_argument("--out", type=Path, required=True, metavar="OUT.rrd", help="the clipped recording (new file)")


def _frame_range(batch: pa.RecordBatch) -> pa.Array | None:
    return batch.column("frame") if "frame" in batch.schema.names else None


def _held_window(src: Path, chunks: list, batches: list, a: int, b: int) -> tuple[int, int]:
    """The part of frames [a, b) that the recording holds; RecordingError when it holds none of them (a clip of
    nothing, labelled with frames it does not hold, would "reproduce" anything)."""
    import pyarrow.compute as pc

    lo, hi = None, None
    for chunk, batch in zip(chunks, batches):
        frames = None if chunk.is_static else _frame_range(batch)
        if frames is None or len(frames) == 0:
            continue
        f0, f1 = pc.min(frames).as_py(), pc.max(frames).as_py()
        if f0 is not None:
            lo, hi = f0 if lo is None else min(lo, f0), f1 if hi is None else max(hi, f1)
    if lo is None:
        raise RecordingError(f"{src}: holds no frames to clip")
    if b <= lo or a > hi:
        raise RecordingError(f"--frames {a}:{b}: outside the recording, which holds frames {lo}..{hi} ({src})")
    return max(a, lo), min(b, hi + 1)


def clip(src: Path, a: int, b: int, out: Path) -> tuple[int, int, int]:
    """Write frames [a, b) of `src` (and its static data) to `out`, the window cut to the frames the recording
    holds -> (rows kept, the window's first frame, its end)."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import rerun as rr

    from plvo_app.rrd_compact import write_chunks
    from plvo_app.rrd_reader import open_rrd

    if not src.is_file():
        raise RecordingError(f"{src}: no such recording file")
    if out.exists():
        raise RecordingError(f"{out}: already exists; plvo clip never overwrites a file")
    try:
        chunks = list(open_rrd(src).stream())
    except Exception as exc:  # noqa: BLE001 - the bindings raise several types for a bad file
        raise RecordingError(f"{src}: not a readable Rerun recording ({exc})") from None
    batches = [chunk.to_record_batch() for chunk in chunks]  # each chunk's table, made once
    a, b = _held_window(src, chunks, batches, a, b)
    # the last row before `a` of each entity that carries over: (frame, chunk index, row)
    last: dict[str, tuple[int, int, int]] = {}
    for ci, chunk in enumerate(chunks):
        if chunk.is_static or chunk.entity_path.startswith(NO_CARRY):
            continue
        frames = _frame_range(batches[ci])
        if frames is None:
            continue
        for row, f in enumerate(frames.to_pylist()):
            if f is not None and f < a and f >= last.get(chunk.entity_path, (-1, 0, 0))[0]:
                last[chunk.entity_path] = (f, ci, row)
    carry = {(ci, row) for _, ci, row in last.values()}
    kept: list[rr.chunk.Chunk] = []
    n_rows = 0
    for ci, chunk in enumerate(chunks):
        batch = batches[ci]
        frames = _frame_range(batch)
        if chunk.is_static or frames is None:
            kept.append(chunk)
            continue
        inside = pc.and_(pc.greater_equal(frames, a), pc.less(frames, b))
        rows = [r for r, ok in enumerate(inside.to_pylist()) if ok or (ci, r) in carry]
        if not rows:
            continue
        sub = batch.take(pa.array(rows))
        i = sub.schema.get_field_index("frame")
        moved = pa.array([max(int(f), a) for f in sub.column(i).to_pylist()], type=sub.schema.field(i).type)
        sub = sub.set_column(i, sub.schema.field(i), moved)
        kept += rr.chunk.Chunk.from_record_batch(sub)  # keeps the row ids: their order settles same-frame rows
        n_rows += len(rows)
    kept.append(rr.chunk.Chunk.from_property("plvo_clip", rr.AnyValues(source=str(src), frames=f"{a}:{b}")))
    out.parent.mkdir(parents=True, exist_ok=True)
    write_chunks(out, kept, recording_id=f"{src.stem}_{a}_{b}")
    return n_rows, a, b


def run(args: argparse.Namespace) -> int:
    a, b = parse_window(args.frames)
    n, a, b = clip(args.file, a, b, args.out)
    print(f"{args.out}: frames {a}..{b - 1} of {args.file} ({n} rows, {args.out.stat().st_size / 1e6:.1f} MB)",
          file=sys.stderr)
    return 0
