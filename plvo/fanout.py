"""Fan work out: over local processes, or over Ray (a local Ray started for the call, or a cluster's).

Used by the evaluation (plvo.eval.runner) and the twin batch generator (plvo.data.synth.twin.batch); both hand in a
picklable function and its argument tuples and take the results as they finish, on the driver.

Local processes are spawned (not forked) and end when their parent does. Ray tasks take one CPU
each and are not retried.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any



def worker_pool(workers: int) -> ProcessPoolExecutor:
    """A local process pool: spawned workers that end with this process."""
    # spawn, not fork: kiss_icp and OpenCV start thread pools that a forked child must not inherit
    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_die_with_parent)


def _die_with_parent() -> None:
    """In a pool worker: end when the parent (`plvo eval run`, `plvo synth`) does. A killed parent otherwise
    leaves its workers finishing their tasks (minutes of two cores each), writing into a folder nobody reads."""
    if sys.platform.startswith("linux"):
        import ctypes
        import signal

        pr_set_pdeathsig = 1
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL)


def ray_unordered(fn: Callable, calls: Sequence[tuple], address: str, workers: int,
                  missing: Callable[[str], Exception]) -> Iterator[tuple[int, Any, BaseException | None]]:
    """Run fn(*calls[k]) as Ray tasks (one CPU each, no retries) -> (k, result, None) or (k, None, exception) as
    each finishes. missing(message): the error to raise when ray is not installed. A Ray started here is shut
    down at the end (also when the caller stops early)."""
    try:
        import ray
    except ImportError:
        raise missing("--ray: the ray package is not installed (pip install 'ray[default]')") from None
    started = False
    if not ray.is_initialized():
        if address == "local":
            ray.init(num_cpus=max(1, workers), include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
        started = True
    try:
        remote = ray.remote(num_cpus=1, max_retries=0)(fn)
        pending = {remote.remote(*args): k for k, args in enumerate(calls)}
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            k = pending.pop(ready[0])
            try:
                yield k, ray.get(ready[0]), None
            except Exception as exc:  # noqa: BLE001 - a worker died or the task could not be shipped
                yield k, None, exc
    finally:
        if started:
            ray.shutdown()
