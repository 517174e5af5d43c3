"""OrderedWorker: the same outputs in the same order inline, in a thread and in a worker process; a failure in
the worker comes back as one WorkerError line naming the worker and the job; worker logs reach this process."""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from plvo.errors import WorkerError
from plvo.runtime.workers import OrderedWorker


@dataclass(frozen=True)
class Job:
    kf_id: int
    frame_index: int


class RunningSum:
    """A stateful core: each output depends on every job before it, in order."""

    def __init__(self, start: int):
        self.total = start

    def process(self, job: Job) -> int:
        if job.kf_id < 0:
            raise ValueError(f"negative keyframe {job.kf_id}")
        self.total += job.kf_id
        logging.getLogger("plvo.test_core").info("keyframe %d summed", job.kf_id)
        return self.total


@pytest.mark.parametrize("mode", ["inline", "thread", "process"])
def test_outputs_in_submission_order(mode):
    w = OrderedWorker("summer", RunningSum, (100,), mode)
    try:
        for k in range(6):
            w.submit(Job(k, 3 * k))
        assert w.pending == 6
        assert [w.take() for _ in range(6)] == [100, 101, 103, 106, 110, 115]
        assert w.pending == 0
    finally:
        w.close()


def test_a_closed_worker_process_exits_at_once_with_every_output_delivered():
    """The worker leaves by os._exit after flushing its outputs (the interpreter's teardown of the pipeline's
    libraries took ~0.5 s a worker): outputs not yet taken at close are in the pipe, and the exit is clean (status
    0, not the kill close() falls back to)."""
    w = OrderedWorker("summer", RunningSum, (0,), "process")
    try:
        for k in range(4):
            w.submit(Job(k, k))
        assert w.take() == 0
        proc = w._link.proc
        w._link.put(None)  # what close() sends; the three outputs not taken must still arrive
        assert [w.take() for _ in range(3)] == [1, 3, 6]
        proc.join(timeout=10)
        assert proc.exitcode == 0
    finally:
        w.close()


def test_process_worker_logs_come_back_with_the_output(caplog):
    with caplog.at_level(logging.INFO, logger="plvo"):  # the worker logs at the level "plvo" had when it started
        w = OrderedWorker("summer", RunningSum, (0,), "process")
        try:
            w.submit(Job(7, 21))
            assert w.take() == 7
        finally:
            w.close()
    assert "keyframe 7 summed" in caplog.text


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_a_failing_core_is_one_line_naming_worker_and_job(mode):
    w = OrderedWorker("back end", RunningSum, (0,), mode)
    try:
        w.submit(Job(1, 3))
        w.submit(Job(-2, 6))
        assert w.take() == 1
        with pytest.raises(WorkerError) as err:
            w.take()
        msg = str(err.value)
        assert "\n" not in msg
        assert msg == "the back end failed on keyframe -2 at frame 6: ValueError: negative keyframe -2"
        with pytest.raises(WorkerError):  # and it stays failed
            w.submit(Job(3, 9))
    finally:
        w.close()


def test_inline_failure_is_the_same_line():
    w = OrderedWorker("loop closer", RunningSum, (0,), "inline")
    with pytest.raises(WorkerError, match="the loop closer failed on keyframe -1 at frame 0: ValueError"):
        w.submit(Job(-1, 0))


class StartsSlowly(RunningSum):
    """A core whose making logs (as a worker's imports and set-up may) and may fail."""

    def __init__(self, start: int):
        if start < 0:
            raise ImportError("no module named 'open3d'")
        logging.getLogger("plvo.test_core").info("core made at %d", start)
        super().__init__(start)


def test_wait_ready_returns_once_the_core_is_made(caplog):
    with caplog.at_level(logging.INFO, logger="plvo"):
        w = OrderedWorker("summer", StartsSlowly, (5,), "process")
        try:
            w.wait_ready()
            assert "core made at 5" in caplog.text  # the worker's start-up logs arrive with the ready message
            w.wait_ready()  # again: nothing left to wait for
            w.submit(Job(2, 6))
            assert w.take() == 7
        finally:
            w.close()


@pytest.mark.parametrize("wait_first", [True, False])
def test_a_core_that_cannot_be_made_is_one_line_at_start(wait_first):
    w = OrderedWorker("back end", StartsSlowly, (-1,), "process")
    try:
        with pytest.raises(WorkerError) as err:
            if wait_first:
                w.wait_ready()
            else:  # take() waits for the start first: the same line
                w.submit(Job(1, 3))
                w.take()
        assert str(err.value) == "the back end failed to start: ImportError: no module named 'open3d'"
        with pytest.raises(WorkerError):
            w.submit(Job(1, 3))
    finally:
        w.close()


def test_a_worker_that_never_says_ready_is_refused():
    """A worker process that sends an output before its "ready" (a worker of another plvo version) is one line, not
    an output taken for the first job's."""
    w = OrderedWorker("back end", RunningSum, (0,), "process")
    try:
        w.wait_ready()
        w._ready = False  # as a parent of this version meeting a worker that does not announce itself
        w.submit(Job(4, 12))
        with pytest.raises(WorkerError, match=r"the back end worker sent an output \(int\) before saying it was ready"):
            w.take()
    finally:
        w.close()


class LibraryThreads:
    """A core that uses open3d and OpenCV, as the back end, the loop closer and the feature extraction do: reports
    how many threads each may use."""

    def __init__(self) -> None:
        import cv2  # noqa: F401 - imported by the core, as FeaturesCore's extraction does
        import open3d  # noqa: F401 - imported by the core, as BackendCore's registration does

    def process(self, job: Job) -> tuple[int, int]:
        import cv2
        import open3d

        return int(open3d.utility.get_max_threads()), int(cv2.getNumThreads())


def test_open3d_and_opencv_run_single_threaded_in_a_worker_process_only():
    """A worker process shares two cores with the tracker and the other workers: open3d's second TBB thread and
    OpenCV's second thread added CPU there, not speed. The limit is the worker process's alone: the caller's
    libraries keep their threads."""
    import os

    import cv2
    import open3d

    mine = open3d.utility.get_max_threads(), cv2.getNumThreads()
    w = OrderedWorker("registration", LibraryThreads, (), "process")
    try:
        w.submit(Job(0, 0))
        assert w.take() == (1, 1)
    finally:
        w.close()
    assert (open3d.utility.get_max_threads(), cv2.getNumThreads()) == mine
    if (os.cpu_count() or 1) > 1:
        assert min(mine) > 1  # the limits are not the machine's defaults (this test could not fail on one core)


class ScanSizedArrays:
    """A core that makes and frees scan-sized arrays (a KITTI scan's copies are ~2 MB each), as registration and the
    loop closer's thinning do every keyframe: reports the page faults it took."""

    def process(self, job: Job) -> int:
        return _faults_of_scan_sized_arrays()


def _faults_of_scan_sized_arrays(n: int = 20) -> int:
    """Page faults of n rounds of a keyframe's temporaries: arrays of 0.5-3 MB alive together, then all freed."""
    import resource

    import numpy as np

    def one_keyframe() -> None:
        arrays = [np.ones(kb << 7) for kb in (2048, 512, 1024, 1024, 1024, 3072)]  # float64: kb kB, written whole
        del arrays

    for _ in range(3):  # the first rounds may grow the heap
        one_keyframe()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        one_keyframe()
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc policy (plvo.allocator) is Linux-only")
def test_a_worker_process_reuses_freed_memory_instead_of_faulting_it_in_again():
    """20 rounds of 8.5 MB of arrays made and freed: glibc's default gives much of it back to the OS each round, so
    it is faulted in again page by page; a worker process keeps the memory (plvo.allocator.keep_freed_memory)."""
    import subprocess

    script = (f"import sys; sys.path[:0] = {sys.path!r}; "
              "from tests.plvo.runtime.test_workers import _faults_of_scan_sized_arrays as f; print(f())")
    default = int(subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                                 cwd=Path(__file__).resolve().parents[3]).stdout)
    assert default > 20 * 500  # the default policy: the test's premise
    w = OrderedWorker("registration", ScanSizedArrays, (), "process")
    try:
        w.submit(Job(0, 0))
        assert w.take() < default / 10
    finally:
        w.close()


def test_a_core_that_cannot_be_made_is_named_by_the_liveness_check_too():
    """A run that steps without waiting for the workers (run_dataset) first sees the dead worker in check_alive:
    the line is the failure it sent, not its exit."""
    import time

    w = OrderedWorker("back end", StartsSlowly, (-1,), "process")
    try:
        t0 = time.monotonic()
        while w._link is not None and w._link.proc.is_alive() and time.monotonic() - t0 < 60:
            time.sleep(0.05)
        with pytest.raises(WorkerError) as err:
            w.check_alive("frame 0")
        assert str(err.value) == "the back end failed to start: ImportError: no module named 'open3d'"
    finally:
        w.close()


class CountsIdle(RunningSum):
    """A core with work to do between jobs: its outputs say how often it was given the time. `raising`: its idle
    work fails every time."""

    def __init__(self, start: int, raising: bool = False, job_s: float = 0.0):
        super().__init__(start)
        self.idled, self.raising, self.job_s = 0, raising, job_s

    def idle(self) -> None:
        self.idled += 1
        if self.raising:
            raise RuntimeError("idle work failed")

    def process(self, job: Job) -> tuple[int, int]:
        import time

        time.sleep(self.job_s)
        return super().process(job), self.idled


@pytest.mark.parametrize("raising", [False, True])
def test_a_worker_process_gives_its_core_the_time_between_jobs(raising):
    """After sending a result, a worker process with no job waiting lets its core work ahead (`idle`, the back end's
    downsampling of the newest scan for the next registration); the outputs are the core's alone, and an idle that
    fails is no failure of the worker (the job that needs the work does it)."""
    import time

    w = OrderedWorker("summer", CountsIdle, (0, raising), "process")
    try:
        w.submit(Job(1, 3))
        assert w.take() == (1, 0)
        time.sleep(0.3)  # the worker has sent its result and found no job: its core had the time
        w.submit(Job(2, 6))
        assert w.take() == (3, 1)
    finally:
        w.close()


def test_a_worker_process_does_not_work_ahead_while_a_job_waits():
    w = OrderedWorker("summer", CountsIdle, (0, False, 0.3), "process")
    try:
        w.submit(Job(1, 3))
        w.submit(Job(2, 6))  # in the pipe while the first runs: the second starts at once
        assert [w.take(), w.take()] == [(1, 0), (3, 0)]
    finally:
        w.close()


@pytest.mark.parametrize("mode", ["inline", "thread"])
def test_idle_work_is_a_worker_process_s_alone(mode):
    """Inline and in a thread the core shares the caller's process: nothing runs it between jobs."""
    w = OrderedWorker("summer", CountsIdle, (0,), mode)
    try:
        for k in (1, 2, 3):
            w.submit(Job(k, 3 * k))
        assert [w.take() for _ in range(3)] == [(1, 0), (3, 0), (6, 0)]
    finally:
        w.close()


def test_the_libraries_get_their_threads_back_when_the_last_limit_is_given_back():
    """Two Systems of one process (an evaluation runs several) each limit the libraries while they run: the first
    to close must not give the second its threads back; the last gives back what the process had."""
    import os

    import cv2
    import open3d

    from plvo.runtime.workers import libraries_single_threaded

    mine = open3d.utility.get_max_threads(), cv2.getNumThreads()
    first = libraries_single_threaded()
    second = libraries_single_threaded()
    assert (open3d.utility.get_max_threads(), cv2.getNumThreads()) == (1, 1)
    first()
    first()  # giving back twice is once
    assert (open3d.utility.get_max_threads(), cv2.getNumThreads()) == (1, 1)
    second()
    assert (open3d.utility.get_max_threads(), cv2.getNumThreads()) == mine
    if (os.cpu_count() or 1) > 1:
        assert min(mine) > 1  # the limits are not the machine's defaults (this test could not fail on one core)
