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
- "process": a spawned worker process with a pipe each way (`_ProcessLink`). No GIL is shared; each job ships its
  window (a few hundred kB) and each keyframe's scan (about 2 MB) once. Between jobs, when none is waiting, the
  process lets its core work ahead for the next one (its `idle()`, where it has one: the back end downsamples the
  newest keyframe's scan for its next registration, which made each of its jobs ~35 ms longer on KITTI 04). Log
  records of the worker are sent back with each output and logged again in this process when the output is taken,
  so they reach the recorders in a fixed order.

Failures come back from `take` as `plvo.errors.WorkerError`, one line naming the worker and the job (keyframe and
frame), and the worker is then failed for good:
- the core raised: its exception's first line;
- the worker process ended (killed by a signal such as the OOM killer's SIGKILL, a segfault in a native library, an
  exit) at start-up, between jobs or while sending a result: the pipe from the worker has no other writer, so its
  end arrives as end-of-file however much of a message was sent; the process is then reaped;
- the worker sent nothing for `timeout_s` while a result was due (stopped, deadlocked, livelocked): it is killed.
No multiprocessing queue, lock or shared memory is used, so nothing depends on multiprocessing's resource tracker.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import multiprocessing
import os
import queue
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from multiprocessing.connection import Connection
from multiprocessing.reduction import ForkingPickler
from typing import Any

from plvo.allocator import c_library, keep_freed_memory
from plvo.errors import WorkerError
from plvo.priority import lower_priority

log = logging.getLogger(__name__)

MODES = ("inline", "thread", "process")
DEFAULT_TIMEOUT_S = 300.0  # config.BackendConfig.worker_timeout_s's default (the reason is given there)
_STOP = None
_CLOSE = object()  # to the sending thread alone: end without telling the worker
_READY = "ready"  # a worker process's first message: its core is made (its imports done)
_PR_SET_PDEATHSIG, _PR_SET_NAME = 1, 15  # linux/prctl.h
_POLL_S = 0.5  # how often a wait looks at the clock and at the worker's liveness
# A worker process's start is its imports (gtsam, open3d, OpenCV: 1-2 s on an idle 2-core machine, several times
# that on a loaded one): it is given at least this long, whatever shorter bound is set for the results
START_TIMEOUT_S = 120.0


def _describe(job: Any) -> str:
    """How a failure names a job: "keyframe 7 at frame 21", "frame 5 (FeaturesJob)", or the job's type."""
    kf, frame = getattr(job, "kf_id", None), getattr(job, "frame_index", None)
    if kf is None:
        return f"frame {frame} ({type(job).__name__})" if frame is not None else type(job).__name__
    return f"keyframe {kf} at frame {frame}" if frame is not None else f"keyframe {kf}"


def _how_it_ended(exitcode: int | None) -> str:
    if exitcode is None:
        return "ended"
    if exitcode < 0:
        try:
            return f"was killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"was killed by signal {-exitcode}"
    return f"ended (exit code {exitcode})"


class _Failure:
    """What a worker sends back instead of an output when its core raised."""

    def __init__(self, job: Any, exc: BaseException):
        self.where = _describe(job) if job is not None else ""
        self.message = f"{type(exc).__name__}: {exc}".splitlines()[0]
        self.trace = traceback.format_exc()


class _Ended:
    """What the reading thread hands over when the worker's pipe ends; `partial`: in the middle of a message."""

    def __init__(self, partial: bool):
        self.partial = partial


class _Capture(logging.Handler):
    """Collects the log records of a worker process, to be logged again in the parent."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[tuple[str, int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append((record.name, record.levelno, record.getMessage()))


def libraries_single_threaded() -> Callable[[], None]:
    """Limit open3d and OpenCV (those imported) to the calling thread -> a function that gives them back the
    threads they had once every limit taken in this process is given back. A worker process shares the machine
    with the tracker and the other workers, so a library's second thread finds no idle core: it adds CPU, not speed.
    Measured on KITTI 04 (alone, on an idle 2-core machine): a keyframe's registration 60 ms wall and 88 ms CPU with
    open3d's default two threads, 76 and 76 with one; a frame's feature extraction 37.5-38.9 ms CPU with OpenCV's
    two threads, 36.3-37.4 with one (the same features, bit for bit). The deployed run is CPU-bound. The tracker's
    own process, beside its worker processes, is limited alike for as long as a System runs there
    (plvo.runtime.system)."""
    with _LIMITS_LOCK:
        if not _LIMITS:
            o3d, cv2 = sys.modules.get("open3d"), sys.modules.get("cv2")
            if o3d is not None and hasattr(o3d.utility, "set_max_threads"):
                _THREADS_BEFORE["open3d"] = o3d.utility.get_max_threads()
                o3d.utility.set_max_threads(1)
            if cv2 is not None:
                _THREADS_BEFORE["cv2"] = cv2.getNumThreads()
                cv2.setNumThreads(1)
        token = object()
        _LIMITS.add(token)

    def give_back() -> None:
        with _LIMITS_LOCK:
            if token not in _LIMITS:
                return
            _LIMITS.discard(token)
            if _LIMITS:  # another System of this process still runs
                return
            if "open3d" in _THREADS_BEFORE:
                sys.modules["open3d"].utility.set_max_threads(_THREADS_BEFORE.pop("open3d"))
            if "cv2" in _THREADS_BEFORE:
                sys.modules["cv2"].setNumThreads(_THREADS_BEFORE.pop("cv2"))
    return give_back


_LIMITS: set[object] = set()  # the limits taken and not given back (one a running System)
_LIMITS_LOCK = threading.Lock()
_THREADS_BEFORE: dict[str, int] = {}


# The terminal's signals, sent to every process of its foreground group: Ctrl-C, Ctrl-\ and a closed terminal's
# SIGHUP. The parent stops its workers; a worker that obeyed them itself would end before the parent's clean-up.
_PARENTS_SIGNALS = (signal.SIGINT, signal.SIGHUP, signal.SIGQUIT)


@contextlib.contextmanager
def _terminal_signals_ignored_by_children() -> Iterator[None]:
    """Within: the terminal's signals ignored, so that a spawned worker starts with them ignored (an ignored
    disposition survives the spawn's exec, and Python keeps it): a Ctrl-C during a worker's imports (a second or
    two) no longer prints a KeyboardInterrupt's traceback from each worker. The parent's own signals are blocked
    meanwhile, not lost: they reach its handlers once these are back."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, _PARENTS_SIGNALS)
    previous = {s: signal.signal(s, signal.SIG_IGN) for s in _PARENTS_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            if handler is not None:
                signal.signal(s, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)


def _as_child(name: str) -> None:
    """A worker process ends with its parent (a killed run leaves no worker behind), leaves Ctrl-C to the parent,
    and is named after its core, so `ps`, `top` and a test can tell the workers apart."""
    for s in _PARENTS_SIGNALS:  # as they were at the spawn (_terminal_signals_ignored_by_children), for good
        signal.signal(s, signal.SIG_IGN)
    c = c_library()
    if c is None:
        return
    c.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    c.prctl(_PR_SET_NAME, f"plvo-{name.replace(' ', '')}"[:15].encode())


def _send(conn: Connection, obj: Any) -> None:
    conn.send_bytes(ForkingPickler.dumps(obj))


def _serve(jobs: Connection, outputs: Connection, name: str, factory: Callable, args: tuple, level: int,
           niceness: int = 0) -> None:
    """A worker process's main loop: jobs in from one pipe, (output, log records) out through the other."""
    _as_child(name)
    keep_freed_memory()  # a keyframe's scan arrays reused, not faulted in again each time (plvo.allocator)
    capture = _Capture()
    root = logging.getLogger()
    root.handlers[:] = [capture]
    root.setLevel(level)
    try:
        core = factory(*args)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent
        _send(outputs, (_Failure(None, exc), capture.records))
        os._exit(1)  # a start that failed is no clean exit: the parent names the failure it was sent
    lower_priority(niceness)  # after the imports, which the caller waits for; threads made later inherit it
    libraries_single_threaded()
    _send(outputs, (_READY, capture.records))
    capture.records = []
    while True:
        try:
            job = jobs.recv()
        except (EOFError, OSError):  # the parent closed its end (or ended): nobody wants the outputs
            job = _STOP
        if job is _STOP:
            # Every output was sent (the sends are synchronous); exit at once: the interpreter's teardown of
            # open3d, gtsam, OpenCV and the rest took ~0.5 s a worker, which every run (and plvo-viz's user) waited
            # for at its end. Nothing else is left: the logs go back with the outputs, and on Linux the loop
            # closer's keyframe file was unlinked when it was opened.
            outputs.close()
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
        try:
            _send(outputs, (out, records))
        except (OSError, ValueError):  # the parent is gone
            os._exit(1)
        except Exception as exc:  # noqa: BLE001 - e.g. an output that cannot be pickled: the parent is told
            _send(outputs, (_Failure(job, exc), records))
        _idle(core, jobs)


def _idle(core: Any, jobs: Connection) -> None:
    """Let the core do work of its next job ahead (its `idle()`, if it has one) when no job is waiting: the result
    was sent, so nobody waits for this, and the next job then takes that much less. Its outputs cannot change (a
    core's outputs depend on its jobs alone); if it fails, the job that needs the work does it again and fails there,
    named after that job, so the error is not reported here."""
    idle = getattr(core, "idle", None)
    if idle is None or jobs.poll():
        return
    try:
        idle()
    except Exception:  # noqa: BLE001 - see the docstring
        log.debug("worker's idle work failed; the next job does it", exc_info=True)


class _ProcessLink:
    """The parent's side of a worker process: a pipe each way, of which the parent keeps one end only, a thread
    that pickles and sends the jobs (off the caller's path; a job to a stopped worker blocks that thread, not the
    caller) and a thread that reads the outputs' bytes as they come (so a worker is never blocked sending, and a
    pipe that ends mid-message is seen as ended). The caller unpickles what it takes."""

    def __init__(self, name: str, factory: Callable, args: tuple, niceness: int):
        ctx = multiprocessing.get_context("spawn")
        job_r, job_w = ctx.Pipe(duplex=False)
        out_r, out_w = ctx.Pipe(duplex=False)
        level = logging.getLogger("plvo").getEffectiveLevel()
        self.proc = ctx.Process(target=_serve, name=f"plvo-{name}", daemon=True,
                                args=(job_r, out_w, name, factory, args, level, niceness))
        with _terminal_signals_ignored_by_children():
            self.proc.start()
        job_r.close()  # the worker's ends: with them closed here, the worker's death closes the pipes
        out_w.close()
        self._jobs, self._outputs = job_w, out_r
        self._outbox: queue.Queue = queue.Queue()
        self.inbox: queue.Queue = queue.Queue()
        self._sender = threading.Thread(target=self._send_loop, name=f"plvo-{name}-send", daemon=True)
        self._reader = threading.Thread(target=self._read_loop, name=f"plvo-{name}-read", daemon=True)
        self._sender.start()
        self._reader.start()

    def put(self, job: Any) -> None:
        self._outbox.put(job)

    def _send_loop(self) -> None:
        """Each thread closes its own end when it is done, so no end is closed under a read or write in progress."""
        try:
            while True:
                job = self._outbox.get()
                if job is _CLOSE:
                    return
                try:
                    _send(self._jobs, job)
                except (OSError, ValueError):  # the worker is gone (its end closed): take() reports how it ended
                    return
                except Exception as exc:  # noqa: BLE001 - e.g. a job that cannot be pickled: the caller is told
                    self.inbox.put(_Failure(job, exc))
                    return
                if job is _STOP:
                    return
        finally:
            self._jobs.close()

    def _read_loop(self) -> None:
        try:
            while True:
                self.inbox.put(self._outputs.recv_bytes())
        except EOFError:
            self.inbox.put(_Ended(partial=False))
        except OSError:  # "got end of file during message"
            self.inbox.put(_Ended(partial=True))
        except BaseException as exc:  # noqa: BLE001 - e.g. no memory for a large output: the caller is told
            self.inbox.put(_Failure(None, exc))
        finally:
            self._outputs.close()

    def ended(self, grace_s: float = 5.0) -> int | None:
        """Reap the worker process (it has ended or is ending) -> its exit code (None if it did not end)."""
        self.proc.join(timeout=grace_s)
        return self.proc.exitcode

    def kill(self) -> None:
        if self.proc.is_alive():
            self.proc.kill()  # also ends a stopped (SIGSTOP) process
        self.proc.join(timeout=5)

    def close(self, grace_s: float = 10.0) -> None:
        """Ask the worker to stop and give it `grace_s` (0: jobs still in flight are abandoned, so it is killed at
        once), then kill it and reap it; the threads end with the pipes (the reader at the worker's end)."""
        if self.proc.is_alive() and grace_s > 0 and self._sender.is_alive():
            self._outbox.put(_STOP)
            self.proc.join(timeout=grace_s)
        self.kill()
        self._outbox.put(_CLOSE)  # a sender still waiting for a job ends
        self._sender.join(timeout=5)
        self._reader.join(timeout=5)


class OrderedWorker:
    """One core, run `mode` (MODES); `submit(job)` in order, `take()` returns the outputs in the same order."""

    def __init__(self, name: str, factory: Callable, args: tuple, mode: str = "inline", niceness: int = 0,
                 timeout_s: float = DEFAULT_TIMEOUT_S):
        """niceness: the worker process's (`lower_priority`) once its core is made; not applied inline or in a
        thread, which run in the caller's thread or share its process. timeout_s: how long `take` waits without any
        message from the worker before the worker is failed (a process also ended; its start is given at least
        START_TIMEOUT_S)."""
        if mode not in MODES:
            raise ValueError(f"worker mode must be one of {MODES}, got {mode!r}")
        self.name = name
        self.mode = mode
        self.timeout_s = float(timeout_s)
        self._outstanding: collections.deque[Any] = collections.deque()  # jobs submitted, output not taken
        self._done: collections.deque[Any] = collections.deque()  # inline outputs
        self._core: Any = None
        self._thread: threading.Thread | None = None
        self._link: _ProcessLink | None = None
        self._failed: str = ""
        self._ready = mode != "process"
        # The features worker is taken from the reading thread while the tracker's thread checks that it lives
        self._lock = threading.RLock()
        if mode == "inline":
            self._core = factory(*args)
        elif mode == "thread":
            self._core = factory(*args)
            self._jobs: queue.Queue = queue.Queue()
            self._outputs: queue.Queue = queue.Queue()
            self._thread = threading.Thread(target=self._run_thread, name=f"plvo-{name}", daemon=True)
            self._thread.start()
        else:
            self._link = _ProcessLink(name, factory, args, niceness)
            self._outputs = self._link.inbox

    def wait_ready(self) -> None:
        """Wait until the core is made: a worker process has imported its libraries (a second or two of the first
        job's time otherwise) and made its core, or failed to (WorkerError, one line)."""
        while not self._ready:
            out, records = self._next("its start", max(self.timeout_s, START_TIMEOUT_S))
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
        return self._link.proc.pid if self._link is not None else None

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
        elif self._link is not None:
            self._link.put(job)
        else:
            self._jobs.put(job)

    def check_alive(self, now: str = "") -> None:
        """Raise the WorkerError `take` would, at once, when the worker process has ended: the run stops at the frame
        where it is seen instead of at the frame its next result was due (up to loop.max_lag_frames later).
        now: where the caller is (e.g. "frame 12"), named when no job is outstanding."""
        if self._failed:
            raise WorkerError(self._failed)
        link = self._link
        if link is None or link.proc.is_alive():
            return
        with self._lock:
            if self._failed:
                raise WorkerError(self._failed)
            what = _describe(self._outstanding[0]) if self._outstanding else (
                f"its next job (seen at {now})" if now else "its next job")
            # What it sent before it ended says more (a failure to start or in a job): _next reads it, or raises
            # the end (cut off mid-message or not) as take() would
            out, _ = self._next(what)
            if isinstance(out, _Failure):
                how = f"on {out.where}" if out.where else "to start"
                raise self._failure(f"the {self.name} failed {how}: {out.message}", out.trace)
            raise self._ended(what, False)

    def take(self) -> Any:
        """The output of the oldest job not yet taken, waiting for it; WorkerError when the core failed."""
        with self._lock:
            return self._take()

    def _take(self) -> Any:
        if not self._outstanding:
            raise RuntimeError(f"{self.name}: nothing submitted to take")
        job = self._outstanding[0]
        if self.mode == "inline":
            self._outstanding.popleft()
            return self._done.popleft()
        self.wait_ready()
        out, records = self._next(_describe(job))
        self._outstanding.popleft()
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

    def _next(self, what: str, bound_s: float | None = None) -> tuple[Any, list]:
        """The worker's next message; WorkerError when it ended before `what`, or sent nothing for bound_s
        (default timeout_s)."""
        bound_s = self.timeout_s if bound_s is None else bound_s
        if self._failed:
            raise WorkerError(self._failed)
        t0 = time.monotonic()
        dead_since: float | None = None
        while True:
            try:
                item = self._outputs.get(timeout=_POLL_S)
            except queue.Empty:
                waited = time.monotonic() - t0
                if self._link is not None and not self._link.proc.is_alive():
                    # its pipe's end follows at once, unless a process it made still holds the pipe open
                    dead_since = dead_since if dead_since is not None else time.monotonic()
                    if time.monotonic() - dead_since > 2.0:
                        raise self._ended(what, False) from None
                if self._thread is not None and not self._thread.is_alive():
                    raise self._failure(f"the {self.name} thread ended before {what}") from None
                if waited >= bound_s:
                    raise self._unanswered(what, bound_s) from None
                continue
            if isinstance(item, _Ended):
                raise self._ended(what, item.partial)
            if isinstance(item, _Failure):  # the sending thread's (a job that could not be sent) or the reading one's
                if not item.where:
                    raise self._failure(f"the {self.name} worker's output could not be read: {item.message}")
                raise self._failure(f"the {self.name} worker could not be sent {item.where}: {item.message}")
            return ForkingPickler.loads(item) if isinstance(item, bytes) else item

    def _ended(self, what: str, partial: bool) -> WorkerError:
        assert self._link is not None
        how = _how_it_ended(self._link.ended())
        pid = self._link.proc.pid
        while_ = " while sending its result" if partial else ""
        return self._failure(f"the {self.name} worker process (pid {pid}) {how}{while_} before {what}")

    def _unanswered(self, what: str, bound_s: float) -> WorkerError:
        if self._link is None:  # a thread cannot be ended: it is left to its core
            return self._failure(f"the {self.name} thread sent nothing for {bound_s:g} s while {what} was due "
                                 "(deadlocked? the bound is backend.worker_timeout_s)")
        err = self._failure(f"the {self.name} worker process (pid {self._link.proc.pid}) sent nothing for "
                            f"{bound_s:g} s while {what} was due (stopped or deadlocked; the bound is "
                            "backend.worker_timeout_s); ended it")
        self._link.kill()
        return err

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
        """Stop the worker; outputs not taken are dropped (after Ctrl-C nobody waits for them), and a worker process
        with jobs still in flight is ended at once rather than left to finish them."""
        abandoned = bool(self._outstanding)
        self._outstanding.clear()
        if self._thread is not None and self._thread.is_alive():
            self._jobs.put(_STOP)
            self._thread.join(timeout=1 if self._failed else 60)  # a hung core's thread cannot be joined
        if self._link is not None:
            self._link.close(grace_s=0.0 if abandoned or self._failed else 10.0)
            self._link = None
