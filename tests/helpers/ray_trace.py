"""The evaluation task with a trace, for the Ray cluster tests: every start of a task (a first run or Ray's retry)
appends `<setting>/<sequence> <node id>` to the file named by $PLVO_TEST_RAY_TRACE, then waits
$PLVO_TEST_RAY_DELAY_S seconds (so that a test can kill the node while the task runs) and runs the task as usual.

It runs on the cluster's workers, which import it by name: the tests folder is on their PYTHONPATH."""

from __future__ import annotations

import os
import time
from pathlib import Path

from plvo_eval.tasks import RunSpec, TaskOutput, execute_task

TRACE_ENV = "PLVO_TEST_RAY_TRACE"
DELAY_ENV = "PLVO_TEST_RAY_DELAY_S"


def traced_task(spec: RunSpec) -> TaskOutput:
    import ray

    node = ray.get_runtime_context().get_node_id()
    with open(os.environ[TRACE_ENV], "a") as trace:
        trace.write(f"{spec.setting}/{spec.source.name} {node}\n")
    time.sleep(float(os.environ.get(DELAY_ENV, "0")))
    return execute_task(spec)


def starts(path: str | os.PathLike[str]) -> list[tuple[str, str]]:
    """The trace's (task, node id) lines, in order."""
    try:
        text = Path(path).read_text()
    except FileNotFoundError:
        return []
    return [tuple(line.split()) for line in text.splitlines() if line.strip()]
