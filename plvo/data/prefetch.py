"""Frames read ahead of the tracker: loading and decoding the next frames in a thread while the current one is
tracked (PNG decoding and reading a scan release the GIL), so that reading from disk is off the tracker's path.

`prefetched(dataset, prepare=f)` yields f(dataset[0]), f(dataset[1]), ... in order, f run in the same thread (the
System's feature extraction, `System.prepare`, whose OpenCV calls release the GIL too); at most `depth` frames
wait in memory (a KITTI frame is about 2.5 MB). A loading error is raised in the consumer, at the frame it belongs
to.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterator

from plvo.priority import lower_priority
from plvo.types import Frame

_END = object()


def prefetched(dataset, depth: int = 2, prepare: Callable[[Frame], Frame] | None = None,
               niceness: int = 0) -> Iterator[Frame]:
    """The dataset's frames in order, each loaded (and prepared) while the previous ones are processed; the
    reading thread runs at `niceness` (plvo.priority.lower_priority)."""
    if prepare is None:
        prepare = _as_is
    if depth <= 0:
        for i in range(len(dataset)):
            yield prepare(dataset[i])
        return
    ready: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def load() -> None:
        lower_priority(niceness)
        try:
            for i in range(len(dataset)):
                item = prepare(dataset[i])
                while not stop.is_set():
                    try:
                        ready.put(item, timeout=0.2)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
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
