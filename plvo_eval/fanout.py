"""Fan work out: over local processes, or over Ray (a local Ray started for the call, or a cluster's).

Used by the evaluation (plvo_eval.runner) and the twin batch generator (plvo_synth.twin.batch); both hand in a
picklable function and its argument tuples and take the results as they finish, on the driver.

Local processes are spawned (not forked) and end when their parent does. On Ray a task whose worker process or
node dies is run again by Ray (RAY_SYSTEM_RETRIES times, on any node that has a CPU free); an exception raised by
the function itself is not retried, so a bug is reported once. The functions handed in must therefore be safe to
run twice: the evaluation's tasks only compute and return (the driver writes their folders), a twin is written in
a resumable stage and renamed into place when complete. Before any task goes to a cluster, one small task on every
node with CPUs checks that the paths the tasks read exist there and that the folders they write are the driver's
own (a marker file the driver wrote is seen), so that a path missing on one node is one line before any work.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import secrets
import socket
import sys
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

RAY_SYSTEM_RETRIES = 3  # runs of a task again after its worker or node died (Ray's max_retries)
NODE_CHECK_SECONDS = 120.0  # how long the path check waits for every node to answer
CONNECT_SECONDS = 5.0  # how long a cluster address may take to accept a connection


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
                  error: Callable[[str], Exception], reads: Sequence[str] = (), writes: Sequence[str] = (),
                  hint: str = "put the data on a path every node sees"
                  ) -> Iterator[tuple[int, Any, BaseException | None]]:
    """Run fn(*calls[k]) as Ray tasks (one CPU each) -> (k, result, None) or (k, None, exception) as each finishes.

    address: "local" (a local Ray of `workers` CPUs) or a cluster address for ray.init. On a cluster, `reads`
    (files or folders the tasks read) must exist on every node and `writes` (folders the tasks write into) must be
    the driver's own, else error(one line ending in `hint`) is raised before any task runs; error is also what is
    raised when ray is not installed. A Ray started here is shut down at the end (also when the caller stops
    early)."""
    if not calls:
        return
    try:
        import ray
    except ImportError:
        raise error("--ray: the ray package is not installed (pip install 'ray[default]')") from None
    started = False
    if not ray.is_initialized():
        if address == "local":
            ray.init(num_cpus=max(1, workers), include_dashboard=False, log_to_driver=False)
        else:
            problem = unreachable(address)
            if problem:
                raise error(f"--ray {address}: {problem}; start the cluster (`ray start --head` on its head node) "
                            "or give its address, or --ray local")
            ray.init(address=address, log_to_driver=False)
        started = True
    try:
        if address != "local":
            problem = unseen_on_nodes(reads, writes)
            if problem:
                raise error(f"--ray {address}: {problem}; {hint}")
        remote = ray.remote(num_cpus=1, max_retries=RAY_SYSTEM_RETRIES, retry_exceptions=False)(fn)
        pending = {remote.remote(*args): k for k, args in enumerate(calls)}
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            k = pending.pop(ready[0])
            try:
                yield k, ray.get(ready[0]), None
            except Exception as exc:  # noqa: BLE001 - retries used up, or the task could not be shipped
                yield k, None, exc
    finally:
        if started:
            ray.shutdown()


def unreachable(address: str, timeout: float = CONNECT_SECONDS) -> str:
    """'' when something accepts a TCP connection at a cluster address (HOST:PORT, ray://HOST:PORT), else why not.
    Ray's own connect waits about two minutes for a head that is not there, printing its retries, and then takes
    another half minute to give in to SIGTERM. "auto" (Ray finds the cluster itself) is not probed."""
    if address == "auto":
        return ""
    hostport = address.split("://", 1)[-1].rstrip("/")
    host, sep, port = hostport.rpartition(":")
    if not sep or not port.isdigit():
        return "not a cluster address (HOST:PORT, ray://HOST:PORT or auto)"
    try:
        socket.create_connection((host or "127.0.0.1", int(port)), timeout=timeout).close()
    except OSError as exc:
        reason = "timed out" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        return f"no cluster answers at {host}:{port} ({reason})"
    return ""


def unseen_on_nodes(reads: Sequence[str], writes: Sequence[str], timeout: float = NODE_CHECK_SECONDS) -> str:
    """On the connected Ray: '' when every alive node with CPUs sees each path of `reads` and the driver's own
    folders `writes`, else what the first node lacks ('PATH is not visible on node IP (why)')."""
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    token = secrets.token_hex(8)
    markers = []
    try:
        for folder in writes:
            try:
                Path(folder).mkdir(parents=True, exist_ok=True)
                markers.append(Path(folder) / f".plvo-seen-{token}")
                markers[-1].write_text(token)
            except OSError as exc:
                return f"cannot write into {folder} ({exc.strerror or exc})"
        nodes = [n for n in ray.nodes() if n.get("Alive") and n.get("Resources", {}).get("CPU", 0) >= 1]
        probe = ray.remote(num_cpus=0, max_retries=0)(_unseen_here)
        refs = {
            probe.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False)).remote(
                [str(p) for p in reads], [(str(m), token) for m in markers]): n
            for n in nodes
        }
        ready, late = ray.wait(list(refs), num_returns=len(refs), timeout=timeout)
        problems = []
        for ref in ready:
            where = _node_name(refs[ref])
            try:
                problems += [f"{path} is not visible on node {where} ({why})" for path, why in ray.get(ref)]
            except (ray.exceptions.NodeDiedError, ray.exceptions.WorkerCrashedError,
                    ray.exceptions.TaskUnschedulableError) as exc:
                log.info("node %s left during the path check (%s): it runs no task", where, type(exc).__name__)
            except ray.exceptions.RayError as exc:
                first = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
                problems.append(f"the path check failed on node {where} ({first})")
        problems += [f"node {_node_name(refs[ref])} did not answer the path check within {timeout:.0f} s"
                     for ref in late]
        for ref in late:
            ray.cancel(ref, force=True)
    finally:
        for marker in markers:
            marker.unlink(missing_ok=True)
    if not problems:
        return ""
    return problems[0] + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else "")


def _node_name(node: dict) -> str:
    return f"{node.get('NodeManagerAddress', '?')} (id {str(node.get('NodeID', '?'))[:8]})"


def _unseen_here(reads: Sequence[str], markers: Sequence[tuple[str, str]]) -> list[tuple[str, str]]:
    """On a node: (path, why) for each path of reads that cannot be seen and each driver's marker not found."""
    out = []
    for path in reads:
        try:
            os.stat(path)
        except OSError as exc:
            out.append((path, exc.strerror or type(exc).__name__))
    for marker, token in markers:
        folder = str(Path(marker).parent)
        try:
            seen = Path(marker).read_text() == token
        except OSError:
            seen = False
        if not seen:
            out.append((folder, "a file the driver wrote there is not seen: not the same folder"))
    return out
