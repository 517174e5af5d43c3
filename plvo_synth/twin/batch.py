"""Generate several KITTI twins at once: local processes by default, Ray when asked; each complete or absent.

A twin already under the root with the same settings and TWIN_VERSION (its gt/scene.json says so) is kept; any
other is generated into a staging folder and renamed into place when every file is written (twin.generate), so
an interrupted batch leaves finished twins and no half-written one, and a twin whose Ray node died is carried on
in its stage by the retried task. Progress comes back frame by frame from local workers (a queue) and twin by twin
from Ray. On a Ray cluster every node writes into the root, so it must be one folder that every node sees (checked
before any twin is started, as are the followed pose files; plvo_eval.fanout).
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import queue
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from plvo.errors import SynthError
from plvo_eval.fanout import ray_unordered, worker_pool
from plvo_synth.twin.follow import load_followed
from plvo_synth.twin.generate import TWIN_GENERATOR, TWIN_VERSION, TwinSettings, check_twin_request, generate_twin

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TwinJob:
    sequence: str
    settings: TwinSettings


@dataclass(frozen=True)
class TwinDone:
    sequence: str
    frames: int
    seconds: float
    cached: bool
    error: str = ""

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else 0.0


def parse_twins(text: str) -> list[str]:
    """'00-10' or '01,05,07' or '00-02,08' -> ['00', '01', ...]."""
    out: list[str] = []
    for part in str(text).split(","):
        part = part.strip()
        m = re.fullmatch(r"(\d{1,2})(?:-(\d{1,2}))?", part)
        if not m:
            raise SynthError(f"--twins {text!r}: {part!r} is not a sequence number or range like 00-10")
        a, b = int(m.group(1)), int(m.group(2) or m.group(1))
        if b < a:
            raise SynthError(f"--twins {text!r}: range {part!r} runs backwards")
        out += [f"{k:02d}" for k in range(a, b + 1) if f"{k:02d}" not in out]
    return out


def twin_jobs(sequences: Sequence[str], poses_dir: str | Path, base: TwinSettings) -> list[TwinJob]:
    """One job per sequence, following poses_dir/NN.txt (checked now: a missing file is named before any work)."""
    jobs = []
    for seq in sequences:
        follow = Path(poses_dir) / f"{seq}.txt"
        if not follow.is_file():
            raise SynthError(f"--twins: {follow}: no such pose file (give --kitti-poses DIR holding NN.txt)")
        jobs.append(TwinJob(seq, replace(base, follow=str(follow.resolve()))))
    return jobs


def _scene(root: Path, sequence: str) -> dict:
    """root/sequences/NN/gt/scene.json, or {} when there is none (or it cannot be read)."""
    try:
        return json.loads((Path(root) / "sequences" / sequence / "gt" / "scene.json").read_text())
    except (OSError, ValueError):
        return {}


def is_current(root: Path, job: TwinJob) -> bool:
    """Whether the twin under root was written with the job's settings (as scene.json records them: an ideal twin's
    without the realism, so twins written before it existed stay current for --ideal)."""
    data = _scene(root, job.sequence)
    wanted = json.loads(json.dumps(job.settings.as_json(), default=str))
    return data.get("twin_version") == TWIN_VERSION and data.get("settings") == wanted


def _run_local(job: TwinJob, root: str, progress_queue: queue.Queue[tuple[str, int]] | None = None) -> TwinDone:
    """In a worker: generate one twin, reporting (sequence, frames done) to the queue."""
    start = time.perf_counter()
    n = load_followed(job.settings.follow, job.settings.frames).n_frames

    def progress(done: int, total: int) -> None:
        if progress_queue is not None:
            progress_queue.put((job.sequence, done))

    try:
        generate_twin(root, job.sequence, job.settings, progress=progress, overwrite=True)
    except Exception as exc:  # one bad twin must not end the batch
        log.warning("twin %s failed: %s", job.sequence, exc)
        return TwinDone(job.sequence, 0, time.perf_counter() - start, False, f"{type(exc).__name__}: {exc}")
    return TwinDone(job.sequence, n, time.perf_counter() - start, False)


def is_twin(root: Path, sequence: str) -> bool:
    """Whether root/sequences/NN is a twin (which a batch may replace when stale), by its gt/scene.json."""
    return _scene(root, sequence).get("generator") == TWIN_GENERATOR


def ensure_twins(jobs: Sequence[TwinJob], root: str | Path, workers: int = 1, ray: str | None = None,
                 progress: Callable[[int, int], None] | None = None,
                 on_done: Callable[[TwinDone], None] | None = None, overwrite: bool = False) -> list[TwinDone]:
    """Generate every job's twin under root unless it is there and current; results in the order of jobs.
    A stale twin is replaced; any other sequence folder NN only with overwrite. progress(frames done, frames
    total) over all twins to generate; on_done(TwinDone) as each finishes."""
    root = Path(root)
    for job in jobs:
        check_twin_request(root, job.sequence, job.settings, overwrite=True)
        target = root / "sequences" / job.sequence
        if target.exists() and not overwrite and not is_twin(root, job.sequence):
            raise SynthError(f"{target}: exists and is not a twin (pass --overwrite to replace it)")
    results: dict[int, TwinDone] = {}
    todo = []
    for k, job in enumerate(jobs):
        if is_current(root, job):
            results[k] = TwinDone(job.sequence, 0, 0.0, True)
            if on_done:
                on_done(results[k])
        else:
            todo.append(k)
    frames = {k: load_followed(jobs[k].settings.follow, jobs[k].settings.frames).n_frames for k in todo}
    total = sum(frames.values())
    notify = on_done or (lambda d: None)
    if ray is not None:
        results.update(_ray(jobs, todo, frames, str(root), ray, workers, progress, total, notify))
    elif workers <= 1 or len(todo) <= 1:
        done_before = 0
        for k in todo:
            def one(done: int, n: int, base: int = done_before) -> None:
                if progress:
                    progress(base + done, total)
            start = time.perf_counter()
            try:
                generate_twin(root, jobs[k].sequence, jobs[k].settings, progress=one, overwrite=True)
                results[k] = TwinDone(jobs[k].sequence, frames[k], time.perf_counter() - start, False)
            except SynthError as exc:
                results[k] = TwinDone(jobs[k].sequence, 0, time.perf_counter() - start, False, str(exc))
            done_before += frames[k]
            notify(results[k])
    else:
        results.update(_processes(jobs, todo, str(root), workers, progress, total, notify))
    return [results[k] for k in range(len(jobs))]


def _processes(jobs: Sequence[TwinJob], todo: Sequence[int], root: str, workers: int,
               progress: Callable[[int, int], None] | None, total: int, notify: Callable[[TwinDone], None]
               ) -> dict[int, TwinDone]:
    out: dict[int, TwinDone] = {}
    with multiprocessing.get_context("spawn").Manager() as manager:
        q = manager.Queue()
        seen: dict[str, int] = {}
        with worker_pool(min(workers, len(todo))) as pool:
            futures = {pool.submit(_run_local, jobs[k], root, q): k for k in todo}
            pending = set(futures)
            while pending:
                try:
                    while True:
                        seq, done = q.get(timeout=0.5)
                        seen[seq] = done
                        if progress:
                            progress(sum(seen.values()), total)
                except queue.Empty:
                    pass
                for f in [f for f in pending if f.done()]:
                    pending.discard(f)
                    k = futures[f]
                    out[k] = f.result()
                    notify(out[k])
    return out


def _ray(jobs: Sequence[TwinJob], todo: Sequence[int], frames: dict[int, int], root: str, address: str, workers: int,
         progress: Callable[[int, int], None] | None, total: int, notify: Callable[[TwinDone], None]
         ) -> dict[int, TwinDone]:
    out: dict[int, TwinDone] = {}
    done_frames = 0
    follows = sorted({jobs[k].settings.follow for k in todo})
    for n, result, exc in ray_unordered(_run_local, [(jobs[k], root) for k in todo], address, workers, SynthError,
                                        reads=follows, writes=[root],
                                        hint="put the pose files and the twins' root on a path every node sees"):
        k = todo[n]
        out[k] = result if exc is None else TwinDone(jobs[k].sequence, 0, 0.0, False,
                                                     f"ray: {type(exc).__name__}: {exc}")
        done_frames += frames[k]
        if progress:
            progress(done_frames, total)
        notify(out[k])
    return out
