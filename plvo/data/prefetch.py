"""Frames read ahead of the tracker: loading and decoding the next frames in a thread while the current one is
tracked (PNG decoding and reading a scan release the GIL), so that reading from disk is off the tracker's path.

`prefetched(dataset, prepare=f)` yields f(dataset[0]), f(dataset[1]), ... in order, f run in the same thread (the
System's feature extraction, `System.prepare`, whose OpenCV calls release the GIL too); at most `depth` frames
wait in memory (a KITTI frame is about 2.5 MB). With `finish`, the preparation is done elsewhere (the System's
features process): prepare(frame) starts it and finish(frame, started) collects it, one frame later, so that the
next frame is read and its preparation queued while the one before is still being prepared. A loading or
preparation error is raised in the consumer, at the frame it belongs to.
"""

from __future__ import annotations

import collections
import queue
import threading
from collections.abc import Callable, Iterator
from typing import Any

from plvo.priority import lower_priority
from plvo.types import Frame

_END = object()


def prefetched(dataset, depth: int = 2, prepare: Callable[[Frame], Any] | None = None,
               niceness: int = 0, finish: Callable[[Frame, Any], Frame] | None = None) -> Iterator[Frame]:
    """The dataset's frames in order, each loaded (and prepared) while the previous ones are processed; the
    reading thread runs at `niceness` (plvo.priority.lower_priority). finish: see the module doc."""
    if prepare is None:
        prepare = _as_is
    if depth <= 0:
        for i in range(len(dataset)):
            frame = dataset[i]
            yield prepare(frame) if finish is None else finish(frame, prepare(frame))
        return
    ready: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def hand_over(item: Frame) -> bool:
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
        try:
            for i in range(len(dataset)):
                frame = dataset[i]
                if finish is None:
                    if not hand_over(prepare(frame)):
                        return
                    continue
                started.append((frame, prepare(frame)))
                if len(started) > 1 and not hand_over(finish(*started.popleft())):
                    return
            while started:
                if not hand_over(finish(*started.popleft())):
                    return
        except BaseException as exc:  # noqa: BLE001 - re-raised in the consumer
            ready.put(exc)
            return
        ready.put(_END)

    thread = threading.Thread(target=load, name="plvo-prefetch", daemon=True)
    thread.start()
    try:
        while True:
            item = ready.get()
            if item is _END:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        thread.join(timeout=5)


def _as_is(frame: Frame) -> Frame:
    return frame
