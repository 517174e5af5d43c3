"""A keyframe consumer that runs inline or in its own thread (the back end and the loop closer are two).

Results are queued as (frame_index, result) pairs and handed to the System's thread by `poll`, so recorders are
only ever called from the tracking thread. A failure in the worker is re-raised in the tracking thread at the
next `submit` or `flush`, never swallowed.
"""

from __future__ import annotations

import logging
import queue
import threading
from typing import Any

log = logging.getLogger(__name__)


class KeyframeWorker:
    """Subclasses implement `process(kf)` and call `emit` / `add_timing`; `threaded` picks the mode."""

    name = "worker"

    def __init__(self, threaded: bool):
        self._pending: list[tuple[int, Any]] = []
        self._timings: dict[str, list[float]] = {}
        self._lock = threading.Lock()
        self._queue: queue.Queue[Any] = queue.Queue()
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        if threaded:
            self._thread = threading.Thread(target=self._run, name=f"plvo-{self.name}", daemon=True)
            self._thread.start()

    @property
    def threaded(self) -> bool:
        return self._thread is not None

    def process(self, kf: Any) -> None:
        raise NotImplementedError

    def submit(self, kf: Any) -> None:
        """Process now (inline) or queue for the thread."""
        self._raise_if_failed()
        if self._thread is None:
            self.process(kf)
        else:
            self._queue.put(kf)

    def poll(self) -> list[tuple[int, Any]]:
        """Results produced since the last poll, as (frame_index, result) pairs."""
        with self._lock:
            out, self._pending = self._pending, []
        return out

    def drain_timings(self) -> dict[str, list[float]]:
        """Seconds per stage since the last call, one entry a keyframe."""
        with self._lock:
            out, self._timings = self._timings, {}
        return out

    def flush(self) -> None:
        """Wait until every submitted keyframe is processed."""
        if self._thread is not None:
            self._queue.join()
        self._raise_if_failed()

    def close(self) -> None:
        """Stop the thread; keyframes still queued are dropped (after Ctrl-C nobody waits for them)."""
        if self._thread is not None and self._thread.is_alive():
            while True:
                try:
                    self._queue.get_nowait()
                except queue.Empty:
                    break
                self._queue.task_done()
            self._queue.put(None)
            self._thread.join(timeout=60)

    def emit(self, frame_index: int, *results: Any) -> None:
        with self._lock:
            self._pending.extend((frame_index, r) for r in results)

    def add_timing(self, seconds: dict[str, float]) -> None:
        with self._lock:
            for name, value in seconds.items():
                self._timings.setdefault(name, []).append(value)

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise RuntimeError(f"the {self.name} worker failed") from self._error

    def _run(self) -> None:
        while True:
            kf = self._queue.get()
            try:
                if kf is None:
                    return
                if self._error is None:
                    self.process(kf)
            except BaseException as exc:  # noqa: BLE001 - re-raised in the tracking thread
                log.exception("%s failed on keyframe %s", self.name, getattr(kf, "kf_id", "?"))
                self._error = exc
            finally:
                self._queue.task_done()
