"""Frames read ahead of the tracker: loading and decoding the next frames in a thread while the current one is
tracked (PNG decoding and reading a scan release the GIL), so that reading from disk is off the tracker's path.

`prefetched(dataset, prepare=f)` yields f(dataset[0]), f(dataset[1]), ... in order, f run in the same thread (the
System's feature extraction, `System.prepare`, whose OpenCV calls release the GIL too); at most `depth` frames
wait in memory (a KITTI frame is about 2.5 MB). With `finish`, the preparation is done elsewhere (the System's
features process): prepare(frame) starts it and finish(frame, started) collects it, one frame later, so that the
next frame is read and its preparation queued while the one before is still being prepared. A loading or
preparation error is raised in the consumer, at the frame it belongs to; with `timeout_s`, a frame that takes
longer than that to arrive (a read or a preparation that hangs) is a RunFailed naming it, so the run never waits
for ever on the reading thread.
"""

from __future__ import annotations

import collections
import contextlib
import queue
import threading
import time
from collections.abc import Callable, Generator
from typing import TYPE_CHECKING, Any

from plvo.errors import RunFailed
from plvo.priority import lower_priority
from plvo.types import Frame

if TYPE_CHECKING:
    from plvo.data.dataset import Dataset

_END = object()
_POLL_S = 0.5
READ_TIMEOUT_S = 60.0  # one frame's files (a few MB) read in milliseconds; a minute is a path that blocks


def prefetched(dataset: Dataset, depth: int = 2, prepare: Callable[[Frame], Any] | None = None,
               niceness: int = 0, finish: Callable[[Frame, Any], Frame] | None = None,
               timeout_s: float | None = None) -> Generator[Frame, None, None]:
    """The dataset's frames in order, each loaded (and prepared) while the previous ones are processed; the
    reading thread runs at `niceness` (plvo.priority.lower_priority). finish, timeout_s: see the module doc."""
    if prepare is None:
        prepare = _as_is
    if depth <= 0:
        for i in range(len(dataset)):
            frame = dataset[i]
            yield prepare(frame) if finish is None else finish(frame, prepare(frame))
        return
    ready: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    reading = [-1, 0.0]  # the position whose files the thread is reading, since when (-1: not reading)

    def hand_over(item: Any) -> bool:
        while not stop.is_set():
            try:
                ready.put(item, timeout=0.2)
                return True
            except queue.Full:
                continue
        return False

    def load() -> None:
        lower_priority(niceness)
        started: collections.deque = collections.deque()  # with finish: (frame, what prepare returned)
        at = [0]  # the position being read or prepared

        def finish_first() -> Frame:
            frame, pending = started.popleft()
            at[0] = frame_position(frame)
            return finish(frame, pending)  # type: ignore[misc]

        try:
            for i in range(len(dataset)):
                at[0] = i
                reading[:] = [i, time.monotonic()]
                frame = dataset[i]
                reading[:] = [-1, 0.0]
                if finish is None:
                    if not hand_over(prepare(frame)):
                        return
                    continue
                started.append((frame, prepare(frame)))
                if len(started) > 1 and not hand_over(finish_first()):
                    return
            while started and finish is not None:  # started is empty without finish
                if not hand_over(finish_first()):
                    return
        except BaseException as exc:  # noqa: BLE001 - re-raised in the consumer
            # the frame it came from, which the consumer has not reached yet: an error names that frame, not the
            # one being tracked when it surfaces (up to `depth` frames earlier)
            with contextlib.suppress(AttributeError, TypeError):  # an exception type that takes no attribute
                exc.plvo_frame = frame_number(at[0])  # type: ignore[attr-defined]
            hand_over(exc)
            return
        hand_over(_END)

    numbers = getattr(dataset, "frame_indices", None)
    position_of = {int(f): k for k, f in enumerate(numbers)} if numbers is not None else {}

    def frame_number(position: int) -> int:
        return int(numbers[position]) if numbers is not None and position < len(numbers) else position

    def frame_position(frame: Frame) -> int:
        return position_of.get(int(frame.index), 0)

    thread = threading.Thread(target=load, name="plvo-prefetch", daemon=True)
    thread.start()
    stuck = False
    try:
        for position in range(len(dataset) + 1):
            try:
                item = _next_ready(ready, thread, timeout_s, dataset, position, reading)
            except RunFailed:
                stuck = True
                raise
            if item is _END:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        thread.join(timeout=0 if stuck else 5)  # a stuck thread is not waited for


def _next_ready(ready: queue.Queue, thread: threading.Thread, timeout_s: float | None, dataset: Dataset,
                position: int, reading: list) -> Any:
    """The reading thread's next item; RunFailed when it takes over timeout_s, when one frame's files take over
    READ_TIMEOUT_S to read (naming them), or when the thread ended without one."""
    t0 = time.monotonic()
    while True:
        try:
            return ready.get(timeout=_POLL_S)
        except queue.Empty:
            if not thread.is_alive() and ready.empty():
                raise RunFailed(f"the frame-reading thread ended before frame {_frame_name(dataset, position)}") \
                    from None
            stuck_at, since = reading
            if stuck_at >= 0 and time.monotonic() - since >= READ_TIMEOUT_S:
                raise RunFailed(f"frame {_frame_name(dataset, stuck_at)}: its files were not read within "
                                f"{READ_TIMEOUT_S:.0f} s ({_files(dataset, stuck_at)}): a path that blocks (a pipe, a "
                                "hung network mount)?") from None
            waited = time.monotonic() - t0
            if timeout_s is not None and waited >= timeout_s:
                raise RunFailed(f"frame {_frame_name(dataset, position)} was not read and prepared within "
                                f"{waited:.0f} s (a read or the features process is stuck)") from None


def _files(dataset: Dataset, position: int) -> str:
    """The files a file-based dataset reads for a frame (KITTI layouts, the folder layout), else what it is."""
    names = [str(files[position]) for files in (getattr(dataset, "_images", None), getattr(dataset, "_scans", None))
             if files is not None and position < len(files)]
    return ", ".join(names) or type(dataset).__name__


def _frame_name(dataset: Dataset, position: int) -> str:
    indices = getattr(dataset, "frame_indices", None)
    return str(indices[position]) if indices is not None and position < len(indices) else f"#{position}"


def _as_is(frame: Frame) -> Frame:
    return frame
