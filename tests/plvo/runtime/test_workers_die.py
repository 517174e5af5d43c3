"""A worker process that dies at any moment, or stops answering, ends the wait within seconds with one line naming
the worker, the job and what ended it; the process is reaped (no zombie); nothing needs the resource tracker.

Each test has a hard time limit: before the worker's pipes, a worker killed while sending its result left the
parent blocked for ever in the middle of a message (the write end of a multiprocessing queue's pipe stayed open in
the parent), so a regression hangs, and the limit turns the hang into a failure."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from dataclasses import dataclass

import psutil
import pytest

from plvo.errors import WorkerError
from plvo.runtime.workers import OrderedWorker

pytestmark = [pytest.mark.timeout(60),
              pytest.mark.skipif(not sys.platform.startswith("linux"), reason="signals and prctl: Linux")]


@dataclass(frozen=True)
class Job:
    kf_id: int
    frame_index: int
    action: str = "sum"  # what the core does with it (see Dies)


class Dies:
    """A core that, by the job's action, sums, dies at once, dies half-way through sending a large result, makes
    a large result, or hangs."""

    def __init__(self) -> None:
        self.total = 0

    def process(self, job: Job):
        if job.action == "die":
            os.kill(os.getpid(), signal.SIGKILL)
        if job.action == "segfault":
            import ctypes

            ctypes.string_at(0)  # a segfault in native code
        if job.action == "exit":
            os._exit(3)
        if job.action == "hang":
            time.sleep(3600)
        if job.action in ("big", "die_mid_send"):
            if job.action == "die_mid_send":
                threading.Thread(target=_kill_me_once_sending, daemon=True).start()
            return bytes(64 << 20)  # 64 MB: a thousand pipe buffers' worth
        self.total += job.kf_id
        return self.total


def _kill_me_once_sending() -> None:
    """In the worker process: SIGKILL it once its main thread is writing the result to the pipe (the header and
    some of the payload are out; the rest never comes)."""
    main = threading.main_thread().ident
    while True:
        frame = sys._current_frames().get(main)
        while frame is not None:
            if frame.f_code.co_name == "_send" and "connection" in frame.f_code.co_filename:
                time.sleep(0.002)  # into the 64 MB
                os.kill(os.getpid(), signal.SIGKILL)
            frame = frame.f_back
        time.sleep(0.0005)


class DiesAtStart:
    def __init__(self) -> None:
        os.kill(os.getpid(), signal.SIGKILL)


def _no_zombies(pid: int | None) -> None:
    """The worker process `pid` is reaped: gone, not a zombie child of this process."""
    assert pid is not None
    if psutil.pid_exists(pid):
        assert psutil.Process(pid).status() != psutil.STATUS_ZOMBIE, f"worker {pid} left a zombie"


def _fails_fast(w: OrderedWorker, limit_s: float = 10.0) -> str:
    t0 = time.monotonic()
    with pytest.raises(WorkerError) as err:
        w.take()
    assert time.monotonic() - t0 < limit_s
    msg = str(err.value)
    assert "\n" not in msg
    return msg


@pytest.mark.parametrize("action, how", [("die", "was killed by SIGKILL"), ("segfault", "was killed by SIGSEGV"),
                                         ("exit", "ended (exit code 3)")])
def test_a_worker_that_dies_in_a_job_is_one_line(action, how):
    w = OrderedWorker("back end", Dies, (), "process")
    worker_pid = w.pid
    try:
        w.submit(Job(1, 3))
        w.submit(Job(2, 6, action))
        assert w.take() == 1
        msg = _fails_fast(w)
        assert msg.startswith("the back end worker process (pid ")
        assert msg.endswith(f"{how} before keyframe 2 at frame 6")
        with pytest.raises(WorkerError, match="was killed|ended"):  # failed for good
            w.submit(Job(3, 9))
        _no_zombies(worker_pid)
    finally:
        w.close()


def test_a_worker_killed_while_sending_a_large_result_is_one_line():
    w = OrderedWorker("loop closer", Dies, (), "process")
    worker_pid = w.pid
    try:
        w.submit(Job(4, 12, "big"))
        assert len(w.take()) == 64 << 20  # a whole one arrives
        w.submit(Job(5, 15, "die_mid_send"))
        msg = _fails_fast(w)
        assert "was killed by SIGKILL while sending its result before keyframe 5 at frame 15" in msg, msg
        _no_zombies(worker_pid)
    finally:
        w.close()


def test_a_worker_killed_between_jobs_is_noticed_at_the_next_take():
    w = OrderedWorker("features", Dies, (), "process")
    worker_pid = w.pid
    try:
        w.submit(Job(1, 3))
        assert w.take() == 1
        os.kill(w.pid, signal.SIGKILL)  # idle, waiting for a job
        time.sleep(0.5)
        w.submit(Job(2, 6))  # sent to a dead process: no error here, and none of the BrokenPipe kind
        msg = _fails_fast(w)
        assert msg.endswith("was killed by SIGKILL before keyframe 2 at frame 6"), msg
        _no_zombies(worker_pid)
    finally:
        w.close()


def test_a_worker_that_dies_at_start_up_is_one_line():
    w = OrderedWorker("back end", DiesAtStart, (), "process")
    worker_pid = w.pid
    try:
        t0 = time.monotonic()
        with pytest.raises(WorkerError, match=r"the back end worker process \(pid \d+\) was killed by SIGKILL "
                                              r"before its start"):
            w.wait_ready()
        assert time.monotonic() - t0 < 20
        _no_zombies(worker_pid)
    finally:
        w.close()


@pytest.mark.parametrize("how", ["sigstop", "hang"])
def test_a_worker_that_stops_answering_fails_after_the_bound(how):
    w = OrderedWorker("back end", Dies, (), "process", timeout_s=2.0)
    worker_pid = w.pid
    try:
        w.wait_ready()
        pid = w.pid
        if how == "sigstop":
            os.kill(pid, signal.SIGSTOP)
            w.submit(Job(7, 21))
        else:
            w.submit(Job(7, 21, "hang"))
        t0 = time.monotonic()
        msg = _fails_fast(w, limit_s=8.0)
        assert time.monotonic() - t0 >= 2.0
        assert msg == (f"the back end worker process (pid {pid}) sent nothing for 2 s while keyframe 7 at frame 21 "
                       "was due (stopped or deadlocked; the bound is backend.worker_timeout_s); ended it")
        assert not psutil.pid_exists(pid) or psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
        _no_zombies(worker_pid)
    finally:
        w.close()


def test_a_thread_worker_that_hangs_fails_after_the_bound():
    w = OrderedWorker("loop closer", Dies, (), "thread", timeout_s=1.0)
    try:
        w.submit(Job(3, 9, "hang"))
        msg = _fails_fast(w, limit_s=5.0)
        assert msg.startswith("the loop closer thread sent nothing for 1 s while keyframe 3 at frame 9 was due")
    finally:
        t0 = time.monotonic()
        w.close()  # the hung thread cannot be joined: close() does not wait a minute for it
        assert time.monotonic() - t0 < 3


def test_worker_processes_use_no_resource_tracker_resources():
    """Jobs and outputs go through plain pipes: no semaphore or shared memory is registered with multiprocessing's
    resource tracker, so a tracker that dies (or is killed) has nothing to clean up or complain about."""
    from multiprocessing import resource_tracker

    registered = []
    real = resource_tracker.register
    resource_tracker.register = lambda name, rtype: registered.append((name, rtype)) or real(name, rtype)
    try:
        w = OrderedWorker("back end", Dies, (), "process")
        w.submit(Job(1, 1))
        assert w.take() == 1
        w.close()
    finally:
        resource_tracker.register = real
    assert registered == []


def test_the_worker_processes_are_named_after_their_core():
    w = OrderedWorker("loop closer", Dies, (), "process")
    try:
        w.wait_ready()
        assert psutil.Process(w.pid).name() == "plvo-loopcloser"
    finally:
        w.close()
