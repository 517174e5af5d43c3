"""The progress bar and one line a twin that `plvo synth --twins/--follow` and `plvo eval run --twins` show while
plvo_synth.twin.batch.ensure_twins generates (or keeps) KITTI twins."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TextIO

from tqdm import tqdm


def describe(done) -> str:
    """A TwinDone -> what happened to that twin, for its line."""
    if done.cached:
        return "kept (current)"
    if done.error:
        return f"FAILED: {done.error}"
    return f"{done.frames} frames in {done.seconds:.1f} s, {done.fps:.2f} frames/s"


@contextmanager
def twin_progress(desc: str, bar: bool = True, lines: TextIO | None = None
                  ) -> Iterator[tuple[Callable[[int, int], None], Callable[[object], None]]]:
    """(progress(frames done, frames total), on_done(TwinDone)) for ensure_twins: a frame bar on stderr (none when
    bar is False) and a line a twin on `lines` (default stdout), closed at the end."""
    out = lines if lines is not None else sys.stdout
    shown = tqdm(total=0, unit="frame", desc=desc, file=sys.stderr) if bar else None

    def progress(done: int, total: int) -> None:
        if shown is not None:
            shown.total = total
            shown.update(done - shown.n)

    def on_done(d) -> None:
        line = f"twin {d.sequence}: {describe(d)}"
        if shown is not None:
            shown.write(line, file=out)
        else:
            print(line, file=out)

    try:
        yield progress, on_done
    finally:
        if shown is not None:
            shown.close()
