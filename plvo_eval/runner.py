"""Evaluation runs at scale: one task per (sequence, setting), fanned out over local processes or Ray.

`build_specs` makes the RunSpecs (plvo under each ablation, KISS-ICP and KISS-SLAM beside it);
`execute(specs, out, workers=N)` runs them in this process for one worker, else over a local process pool whose
workers write their own task folders; `execute(..., ray="local" | ADDRESS)` sends one Ray task per spec (a local Ray
with `workers` CPUs, or `ray.init(address=ADDRESS)`) and writes the folders on the driver, so a cluster needs no
shared output folder; its nodes must see the datasets (and any config or calibration file) under the same paths,
which is checked on every node before the first task, and be able to import plvo. A task whose node dies is run
again by Ray elsewhere (plvo_eval.fanout). Whatever the fan-out, the results are the same TaskResults, read back from
the folders (see plvo_eval.tasks)."""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import as_completed
from dataclasses import replace
from typing import Any

from plvo.config import config_to_toml
from plvo.errors import PlvoError
from plvo_eval.fanout import ray_unordered, worker_pool  # noqa: F401  (worker_pool: also plvo_eval.bench's)
from plvo_eval.kiss import KissOptions
from plvo_eval.kiss_slam import KissSlamOptions
from plvo_eval.tasks import (  # noqa: F401  (re-exported: the runner is the public face)
    KISS_SETTING,
    KISS_SLAM_SETTING,
    METHODS,
    RESULT_FILE,
    MethodOutput,
    RunSpec,
    SequenceSource,
    TaskOutput,
    TaskResult,
    execute_task,
    load_poses,
    metrics_dict,
    plvo_config,
    read_result,
    run_and_write,
    run_pipeline,
    write_task,
)

log = logging.getLogger(__name__)


# ---------------------------------------------------------------- fan-out


def _done(spec: RunSpec, out_dir: str | os.PathLike[str]) -> TaskResult | None:
    """The finished result of the same spec in its folder, for --resume, else None.

    The same spec is not enough for plvo: an ablation's or a default's meaning can change between versions, so the
    configuration the run used (its config.toml) must also equal what the spec resolves to now."""
    folder = spec.folder(out_dir)
    if not (folder / RESULT_FILE).is_file():
        return None
    try:
        result = read_result(folder)
        if spec.method == "plvo":
            used = folder / "config.toml"
            if not used.is_file() or used.read_text() != config_to_toml(plvo_config(spec)):
                log.info("%s/%s: configuration changed since the last run; running again", spec.setting,
                         spec.source.name)
                return None
    except PlvoError:
        return None
    return result if result.ok and result.spec == spec else None


def execute(
    specs: Sequence[RunSpec],
    out_dir: str | os.PathLike[str],
    workers: int = 1,
    ray: str | None = None,
    resume: bool = False,
    on_result: Callable[[TaskResult], None] | None = None,
) -> list[TaskResult]:
    """Run every spec (one task each) and write its folder under out_dir; results in the order of specs.

    workers: local processes (1 = in this process) or, with ray="local", the CPUs of the local Ray; ray: None
    (local processes), "local" (start a local Ray) or a cluster address for ray.init. resume: keep the folders of
    specs already finished ok.
    """
    names = [(s.setting, s.source.name) for s in specs]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise PlvoError(f"two runs would write the same folder runs/{dup[0]}/{dup[1]}: give the sequences distinct "
                        "labels")
    out_dir = str(out_dir)
    results: dict[int, TaskResult] = {}
    todo = []
    for k, spec in enumerate(specs):
        previous = _done(spec, out_dir) if resume else None
        if previous is not None:
            results[k] = previous
        else:
            todo.append(k)
    if resume:
        log.info("--resume: %d of %d tasks finished already; running the other %d", len(results), len(specs),
                 len(todo))
    notify = on_result or (lambda r: None)
    for r in results.values():
        notify(r)
    todo_specs = [specs[k] for k in todo]
    if ray is not None:
        gathered = _execute_ray(todo_specs, out_dir, ray, workers, notify)
    elif workers <= 1 or len(todo_specs) <= 1:
        gathered = []
        for spec in todo_specs:
            gathered.append(run_and_write(spec, out_dir))
            notify(gathered[-1])
    else:
        gathered = _execute_processes(todo_specs, out_dir, workers, notify)
    results.update(zip(todo, gathered))
    return [results[k] for k in range(len(specs))]


def _execute_processes(
    specs: Sequence[RunSpec], out_dir: str, workers: int, notify: Callable[[TaskResult], None]
) -> list[TaskResult]:
    results: dict[int, TaskResult] = {}
    with worker_pool(min(workers, len(specs))) as pool:
        futures = {pool.submit(run_and_write, spec, out_dir): k for k, spec in enumerate(specs)}
        for future in as_completed(futures):
            results[futures[future]] = future.result()
            notify(results[futures[future]])
    return [results[k] for k in range(len(specs))]


def _execute_ray(
    specs: Sequence[RunSpec], out_dir: str, address: str, workers: int, notify: Callable[[TaskResult], None]
) -> list[TaskResult]:
    results: dict[int, TaskResult] = {}
    reads = sorted({p for s in specs for p in (s.source.root, s.source.calib, s.config_path) if p})
    for k, output, exc in ray_unordered(execute_task, [(spec,) for spec in specs], address, workers, PlvoError,
                                        reads=reads, hint="put the data on a path every node sees"):
        if exc is not None:
            output = TaskOutput(specs[k], "failed", error=f"ray: {type(exc).__name__}: {exc}")
        results[k] = write_task(output, out_dir)
        notify(results[k])
    return [results[k] for k in range(len(specs))]


# ---------------------------------------------------------------- building specs


INLINE_SUFFIX = "_inline"  # setting name of an ablation run inline (eval run --inline)


def build_specs(
    sources: Iterable[SequenceSource],
    ablations: Sequence[str] = ("full",),
    kiss: bool = False,
    overrides: Mapping[str, Mapping[str, Any]] | None = None,
    config_path: str | None = None,
    kiss_options: KissOptions | None = None,
    inline: bool = False,
    kiss_slam: bool = False,
    kiss_slam_options: KissSlamOptions | None = None,
) -> list[RunSpec]:
    """Every (sequence, setting) pair: plvo under each ablation (the deployed mode: the config's concurrent
    workers), with `inline` each also as `<ablation>_inline` (backend.concurrent = false, a fixed order of work with
    no lag), then KISS-ICP and KISS-SLAM when asked."""
    specs = []
    for source in sources:
        for ablation in ablations:
            specs.append(
                RunSpec(source, "plvo", ablation, ablation, dict(overrides or {}), config_path)
            )
            if inline:
                sections = {k: dict(v) for k, v in (overrides or {}).items()}
                sections.setdefault("backend", {})["concurrent"] = False
                specs.append(RunSpec(source, "plvo", f"{ablation}{INLINE_SUFFIX}", ablation, sections, config_path))
        if kiss:
            specs.append(RunSpec(source, "kiss", KISS_SETTING, None, {}, None, kiss_options or KissOptions()))
        if kiss_slam:
            specs.append(RunSpec(source, "kiss_slam", KISS_SLAM_SETTING, None, {}, None,
                                 kiss_slam=kiss_slam_options or KissSlamOptions()))
    return specs


def kiss_threads(workers: int, ray: str | None) -> int:
    """Threads for each KISS-ICP or KISS-SLAM task: all cores alone (0), a fair share among local workers, 1 a Ray
    CPU."""
    if ray is not None:
        return 1
    return 0 if workers <= 1 else max(1, (os.cpu_count() or 1) // workers)


def with_threads(specs: Sequence[RunSpec], threads: int) -> list[RunSpec]:
    """The specs with KISS-ICP's and KISS-SLAM's thread counts set (see kiss_threads)."""
    out = []
    for s in specs:
        if s.method == "kiss":
            s = replace(s, kiss=replace(s.kiss, max_threads=threads))
        elif s.method == "kiss_slam":
            s = replace(s, kiss_slam=replace(s.kiss_slam, max_threads=threads))
        out.append(s)
    return out
