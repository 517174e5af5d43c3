"""Fan work out over Ray: a local Ray started for the call (`address="local"`) or a cluster's (`ray.init(address=)`).

Used by `plvo eval run --ray` and `plvo synth --twins ... --ray`; both hand in a picklable function and its
argument tuples and take the results as they finish, on the driver.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any


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
