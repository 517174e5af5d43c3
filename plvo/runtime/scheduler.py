"""What is due when: the frames at which each worker's results are applied to the map.

The System's map has one writer, the tracking thread, and the workers' results reach it at fixed frames of the run,
never when a worker happens to finish, so that a run's trajectory does not depend on the machine's load:
- a keyframe's back-end result at the start of frame (its frame + `Lags.backend`), or before the next keyframe's
  window is read, whichever comes first;
- a keyframe's loop result at the start of frame (its frame + `Lags.loop`);
- a global bundle adjustment, submitted when a loop correction is applied, `Lags.global_ba` frames after that.
Inline (`backend.concurrent = false`) every lag is 0: each result is applied as soon as its job is submitted.

`Scheduler` keeps, per worker (`Channel`), the due frame of each job in flight in submission order, takes each
output when it is due (waiting for a late worker, timed) and hands it to the channel's `apply`. It also counts the
loop closer's corrections the map has applied (`loop_corrections_applied`): each loop job carries that count, so
the closer knows which of the corrections it made are still in flight (plvo.loop.worker), and a global BA job
whose count is below the closer's is stale (superseded by a later loop). And it says which keyframes' landmarks a
job in flight may still read (`oldest_reachable_keyframe`), which bounds what the map may drop.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from plvo.config import SystemConfig
from plvo.tracking.map import LandmarkMap


@dataclass(frozen=True)
class Lags:
    """Frames from a job's submission to its result's application: back end, loop result, global BA."""

    backend: int = 0
    loop: int = 0
    global_ba: int = 0

    @classmethod
    def of(cls, config: SystemConfig) -> Lags:
        if not config.backend.concurrent:
            return cls()
        return cls(max(0, config.backend.max_lag_frames), max(0, config.loop.max_lag_frames),
                   max(0, config.loop.global_ba_lag_frames))


class Worker(Protocol):
    """What the scheduler needs of a worker (plvo.runtime.workers.OrderedWorker)."""

    def submit(self, job: Any) -> None: ...

    def take(self) -> Any: ...


class Channel:
    """One worker's jobs in flight: the frame each is due at, in submission order, and what applies its output."""

    def __init__(self, name: str, worker: Worker, apply: Callable[[Any], None], lag: int):
        self.name = name
        self.worker = worker
        self.apply = apply
        self.lag = lag
        self.due: collections.deque[int] = collections.deque()

    def __repr__(self) -> str:
        return f"Channel({self.name!r}, lag {self.lag}, due {list(self.due)})"


class Scheduler:
    """The channels, in the order their due results are applied at a frame (the back end's first)."""

    def __init__(self, timed: Callable[[str, float], None] | None = None):
        """timed(stage, seconds): told how long each take waited for its worker ("<channel>_wait")."""
        self.channels: list[Channel] = []
        self._timed = timed if timed is not None else (lambda stage, seconds: None)
        self.loop_corrections_applied = 0

    def channel(self, name: str, worker: Worker, apply: Callable[[Any], None], lag: int) -> Channel:
        ch = Channel(name, worker, apply, lag)
        self.channels.append(ch)
        return ch

    def submit(self, ch: Channel, job: Any, frame: int, lag: int | None = None) -> None:
        """Hand `job` to the channel's worker; its output is due at frame + lag (the channel's lag by default)."""
        ch.worker.submit(job)
        ch.due.append(frame + (ch.lag if lag is None else lag))

    def settle(self, ch: Channel) -> None:
        """Inline (lag 0): apply what was just submitted before going on."""
        if ch.lag == 0:
            self.drain(ch)

    def apply_due(self, frame: int) -> None:
        """Wait for and apply every result due at or before `frame`, channel by channel."""
        for ch in self.channels:
            while ch.due and ch.due[0] <= frame:
                self._apply_next(ch)

    def drain(self, ch: Channel) -> int:
        """Wait for and apply every result of the channel in flight (also those its apply submits) -> how many."""
        n = 0
        while ch.due:
            self._apply_next(ch)
            n += 1
        return n

    def finish(self) -> None:
        """Wait for and apply everything in flight."""
        while any(ch.due for ch in self.channels):
            for ch in self.channels:
                self.drain(ch)

    @property
    def in_flight(self) -> int:
        return sum(len(ch.due) for ch in self.channels)

    def _apply_next(self, ch: Channel) -> None:
        ch.due.popleft()
        t0 = time.perf_counter()
        out = ch.worker.take()
        self._timed(f"{ch.name}_wait", time.perf_counter() - t0)
        ch.apply(out)


def oldest_reachable_keyframe(kf_id: int, config: SystemConfig) -> int:
    """The oldest keyframe whose landmarks anything may still read once keyframe `kf_id` is made: the window of the
    back-end job in flight (one at a time: the next keyframe's job waits for it) and of the next, and the tracker's
    recent keyframes."""
    reach = max(2, config.backend.window_keyframes, config.tracking.search_keyframes)
    return kf_id - reach


def drop_unreachable(map_: LandmarkMap, kf_id: int, frame_index: int, config: SystemConfig) -> None:
    """Drop from the map the landmarks no job in flight or to come can read once keyframe `kf_id` is made (those
    a future global bundle adjustment may still take are kept: its point budget, when there is one)."""
    loop = config.loop
    budget = loop.global_ba_max_points if loop.enabled and loop.global_ba else None
    map_.drop_unreachable(frame_index, oldest_reachable_keyframe(kf_id, config), global_ba_points=budget)
