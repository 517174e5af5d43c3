"""Run a worker core's `process(job)` over jobs in submission order: inline, in a thread, or in a worker process.

The back end, the loop closer and, in the deployed mode, the feature extraction are cores
(plvo.backend.worker.BackendCore, plvo.loop.worker.LoopCore, plvo.features.worker.FeaturesCore): objects whose
outputs depend only on the jobs they were given, in order. `OrderedWorker` runs one and hands its outputs
back in the same order (`take`, which waits); the System decides at which frame it takes each, so where and how fast
the core ran changes the frames a second, never the result.

Where it runs (`mode`):
- "inline": at `submit`, in the caller's thread (what `backend.concurrent = false` gives);
- "thread": a thread of this process. It shares the GIL with the tracker: the numpy, scipy and open3d calls release
  it only in parts, so on two cores the tracker slows while the back end runs;
- "process": a spawned worker process, jobs and outputs pickled through multiprocessing queues (whose feeder
  threads do the pickling off the caller's path). No GIL is shared; each job ships its window (a few hundred kB)
  and each keyframe's scan (about 2 MB) once. Log records of the worker are sent back with each output and logged
  again in this process when the output is taken, so they reach the recorders in a fixed order.

A failure in the core comes back as `plvo.errors.WorkerError` from `take`, one line naming the worker and the job.
"""

from __future__ import annotations

import collections
import logging
import multiprocessing
import os
import queue
import sys
import threading
import traceback
from collections.abc import Callable
from typing import Any

from plvo.errors import WorkerError
from plvo.heap import keep_freed_memory
from plvo.priority import lower_priority

log = logging.getLogger(__name__)

MODES = ("inline", "thread", "process")
_STOP = None
_READY = "ready"  # a worker process's first message: its core is made (its imports done)


def _describe(job: Any) -> str:
    kf, frame = getattr(job, "kf_id", None), getattr(job, "frame_index", None)
    parts = [f"keyframe {kf}" if kf is not None else type(job).__name__, f"frame {frame}" if frame is not None else ""]
    return " at ".join(p for p in parts if p)


class _Failure:
    """What a worker sends back instead of an output when its core raised."""

    def __init__(self, job: Any, exc: BaseException):
        self.where = _describe(job)
        self.message = f"{type(exc).__name__}: {exc}".splitlines()[0]
        self.trace = traceback.format_exc()


class _Capture(logging.Handler):
    """Collects the log records of a worker process, to be logged again in the parent."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[tuple[str, int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append((record.name, record.levelno, record.getMessage()))


def _open3d_single_threaded() -> None:
    """Limit open3d (imported by the worker's core) to the calling thread. A worker process shares the machine with
    the tracker and the other workers, so a second TBB thread finds no idle core: it adds CPU, not speed. Measured on
    KITTI 04's keyframe scans (registration alone, on an idle 2-core machine): 60 ms wall and 88 ms CPU a
    registration with open3d's default two threads, 76 and 76 with one; the deployed run is CPU-bound."""
    o3d = sys.modules.get("open3d")
    if o3d is not None and hasattr(o3d.utility, "set_max_threads"):
        o3d.utility.set_max_threads(1)


def _serve(jobs, outputs, factory: Callable, args: tuple, level: int, niceness: int = 0) -> None:
    """A worker process's main loop."""
    if sys.platform.startswith("linux"):  # end with the parent (a killed run leaves no worker behind)
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    keep_freed_memory()  # a keyframe's scan arrays reused, not faulted in again each time (plvo.heap)
    capture = _Capture()
    root = logging.getLogger()
    root.handlers[:] = [capture]
    root.setLevel(level)
    try:
        core = factory(*args)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent
        outputs.put((_Failure(None, exc), capture.records))
        return
    lower_priority(niceness)  # after the imports, which the caller waits for; threads made later inherit it
    _open3d_single_threaded()
    outputs.put((_READY, capture.records))
    capture.records = []
    while True:
        job = jobs.get()
        if job is _STOP:
            # Every output is in the pipe once the queue's feeder thread is joined; then exit at once: the
            # interpreter's teardown of open3d, gtsam, OpenCV and the rest took ~0.5 s a worker, which every run
            # (and plvo-viz's user) waited for at its end. Nothing else is left: the logs go back with the outputs,
            # and on Linux the loop closer's keyframe file was unlinked when it was opened.
            outputs.close()
            outputs.join_thread()
            if not sys.platform.startswith("linux"):
                return
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(0)
        try:
            out: Any = core.process(job)
        except BaseException as exc:  # noqa: BLE001 - reported to the parent
            out = _Failure(job, exc)
        records, capture.records = capture.records, []
        outputs.put((out, records))


class OrderedWorker:
    """One core, run `mode` (MODES); `submit(job)` in order, `take()` returns the outputs in the same order."""

    def __init__(self, name: str, factory: Callable, args: tuple, mode: str = "inline", niceness: int = 0):
        """niceness: the worker process's (`lower_priority`) once its core is made; not applied inline or in a
        thread, which run in the caller's thread or share its process."""
        if mode not in MODES:
            raise ValueError(f"worker mode must be one of {MODES}, got {mode!r}")
        self.name = name
        self.mode = mode
        self._outstanding: collections.deque[Any] = collections.deque()  # jobs submitted, output not taken
        self._done: collections.deque[Any] = collections.deque()  # inline outputs
        self._core = None
        self._thread: threading.Thread | None = None
        self._proc = None
        self._failed: str = ""
        self._ready = mode != "process"
        if mode == "inline":
            self._core = factory(*args)
        elif mode == "thread":
            self._core = factory(*args)
            self._jobs: Any = queue.Queue()
            self._outputs: Any = queue.Queue()
            self._thread = threading.Thread(target=self._run_thread, name=f"plvo-{name}", daemon=True)
            self._thread.start()
        else:
            ctx = multiprocessing.get_context("spawn")
            self._jobs, self._outputs = ctx.Queue(), ctx.Queue()
            level = logging.getLogger("plvo").getEffectiveLevel()
            self._proc = ctx.Process(target=_serve, name=f"plvo-{name}", daemon=True,
                                     args=(self._jobs, self._outputs, factory, args, level, niceness))
            self._proc.start()

    def wait_ready(self) -> None:
        """Wait until the core is made: a worker process has imported its libraries (a second or two of the first
        job's time otherwise) and made its core, or failed to (WorkerError, one line)."""
        while not self._ready:
            out, records = self._next("its start")
            self._relog(records)
            if isinstance(out, _Failure):
                raise self._failure(f"the {self.name} failed to start: {out.message}", out.trace)
            if not (isinstance(out, str) and out == _READY):  # e.g. a worker of another plvo version
                raise self._failure(f"the {self.name} worker sent an output ({type(out).__name__}) before saying it "
                                    "was ready")
            self._ready = True

    @property
    def pid(self) -> int | None:
        """The worker process's id (None inline, in a thread, or once closed)."""
        return self._proc.pid if self._proc is not None else None

    @property
    def pending(self) -> int:
        """Jobs submitted whose output has not been taken."""
        return len(self._outstanding)

    def submit(self, job: Any) -> None:
        if self._failed:
            raise WorkerError(self._failed)
        self._outstanding.append(job)
        if self.mode == "inline":
            try:
                self._done.append(self._core.process(job))
            except Exception as exc:
                self._failed = f"the {self.name} failed on {_describe(job)}: {type(exc).__name__}: {exc}"
                log.debug("%s", traceback.format_exc())
                raise WorkerError(self._failed.splitlines()[0]) from exc
        else:
            self._jobs.put(job)

    def take(self) -> Any:
        """The output of the oldest job not yet taken, waiting for it; WorkerError when the core failed."""
        if not self._outstanding:
            raise RuntimeError(f"{self.name}: nothing submitted to take")
        job = self._outstanding.popleft()
        if self.mode == "inline":
            return self._done.popleft()
        self.wait_ready()
        out, records = self._next(_describe(job))
        self._relog(records)
        if isinstance(out, _Failure):
            raise self._failure(f"the {self.name} failed on {out.where or _describe(job)}: {out.message}", out.trace)
        return out

    def _failure(self, message: str, trace: str = "") -> WorkerError:
        """Mark the worker failed for good (later calls raise the same line) -> the error to raise."""
        self._failed = message
        if trace:
            log.debug("%s worker traceback:\n%s", self.name, trace)
        return WorkerError(message)

    @staticmethod
    def _relog(records: list) -> None:
        for name, level, msg in records:
            logging.getLogger(name).log(level, "%s", msg)

    def _next(self, what: str) -> tuple[Any, list]:
        """The worker's next message; WorkerError when it ended before `what`."""
        if self._failed:
            raise WorkerError(self._failed)
        while True:
            try:
                return self._outputs.get(timeout=1.0)
            except queue.Empty:
                if self._proc is not None and not self._proc.is_alive():
                    raise self._failure(f"the {self.name} worker process ended (exit code {self._proc.exitcode}) "
                                        f"before {what}") from None
                if self._thread is not None and not self._thread.is_alive():
                    raise self._failure(f"the {self.name} thread ended before {what}") from None

    def _run_thread(self) -> None:
        while True:
            job = self._jobs.get()
            if job is _STOP:
                return
            try:
                out: Any = self._core.process(job)
            except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread by take()
                out = _Failure(job, exc)
            self._outputs.put((out, []))

    def close(self) -> None:
        """Stop the worker; outputs not taken are dropped (after Ctrl-C nobody waits for them)."""
        self._outstanding.clear()
        if self._thread is not None and self._thread.is_alive():
            self._jobs.put(_STOP)
            self._thread.join(timeout=60)
        if self._proc is not None:
            if self._proc.is_alive():
                self._jobs.put(_STOP)
                self._proc.join(timeout=10)
            if self._proc.is_alive():
                self._proc.kill()
                self._proc.join(timeout=5)
            for q in (self._jobs, self._outputs):
                q.cancel_join_thread()
                q.close()
            self._proc = None
