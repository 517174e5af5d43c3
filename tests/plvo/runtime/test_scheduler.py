"""plvo.runtime.scheduler: each result applied exactly at the frame its lag sets, in submission order, back end before
loop at a frame; inline (lag 0) at once; the count of applied loop corrections a global BA job carries, by which the
loop closer judges it stale; what the map may drop."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from plvo.config import SystemConfig, merge
from plvo.runtime.scheduler import Lags, Scheduler, oldest_reachable_keyframe


@dataclass(frozen=True)
class Job:
    name: str


class Recording:
    """A worker whose outputs are its jobs; it logs when each was submitted and taken."""

    def __init__(self, log: list):
        self.log, self.queue = log, []

    def submit(self, job):
        self.queue.append(job)

    def take(self):
        return self.queue.pop(0)


def _scheduler(lag_b: int, lag_l: int):
    applied: list[tuple[int, str]] = []
    frame = [0]
    waited: list[str] = []
    s = Scheduler(lambda stage, seconds: waited.append(stage))
    b = s.channel("backend", Recording(applied), lambda out: applied.append((frame[0], out.name)), lag_b)
    lo = s.channel("loop", Recording(applied), lambda out: applied.append((frame[0], out.name)), lag_l)
    return s, b, lo, applied, frame, waited


def _run(s, frame, until: int) -> None:
    for f in range(until):
        frame[0] = f
        s.apply_due(f)


def test_lags_from_the_config_and_zero_inline():
    cfg = merge(SystemConfig(), {"backend": {"max_lag_frames": 4}, "loop": {"max_lag_frames": 9,
                                                                            "global_ba_lag_frames": 50}})
    assert Lags.of(cfg) == Lags(4, 9, 50)
    assert Lags.of(merge(cfg, {"backend": {"concurrent": False}})) == Lags(0, 0, 0)
    assert Lags.of(SystemConfig()) == Lags(6, 20, 100)  # the defaults


@pytest.mark.parametrize("lag_b, lag_l", [(1, 1), (6, 20), (3, 0), (0, 5)])
def test_each_result_is_applied_at_its_frame_plus_its_lag(lag_b, lag_l):
    s, b, lo, applied, frame, waited = _scheduler(lag_b, lag_l)
    for f in range(40):  # as the System steps: what is due first, then the keyframe's submissions
        frame[0] = f
        s.apply_due(f)
        if f in (0, 3, 6):
            s.submit(b, Job(f"b{f}"), f)
            s.settle(b)
            s.submit(lo, Job(f"l{f}"), f)
            s.settle(lo)
    want = sorted([(f + lag_b, f"b{f}") for f in (0, 3, 6)] + [(f + lag_l, f"l{f}") for f in (0, 3, 6)],
                  key=lambda e: (e[0], e[1][0] != "b"))
    got = sorted(applied, key=lambda e: (e[0], e[1][0] != "b"))
    # an inline channel applies at the frame of submission (its lag is 0): the same frame number
    assert got == want
    assert [n for _, n in applied if n[0] == "b"] == ["b0", "b3", "b6"]  # submission order
    assert waited.count("backend_wait") == 3 and waited.count("loop_wait") == 3


def test_at_one_frame_the_back_end_is_applied_before_the_loop():
    s, b, lo, applied, frame, _ = _scheduler(5, 5)
    s.submit(lo, Job("l"), 0)
    s.submit(b, Job("b"), 0)
    _run(s, frame, 6)
    assert applied == [(5, "b"), (5, "l")]


def test_a_result_is_not_applied_a_frame_early():
    s, b, lo, applied, frame, _ = _scheduler(6, 20)
    s.submit(b, Job("b"), 10)
    _run(s, frame, 16)
    assert applied == []
    frame[0] = 16
    s.apply_due(16)
    assert applied == [(16, "b")]


def test_drain_applies_what_is_in_flight_and_what_its_apply_submits():
    """The loop channel's apply submits a global BA on the same channel (LoopStage): a drain applies that too, and
    finish leaves nothing in flight."""
    s = Scheduler()
    applied = []

    def apply(out):
        applied.append(out.name)
        if out.name == "loop":
            s.submit(ch, Job("global BA"), 0, lag=100)

    ch = s.channel("loop", Recording(applied), apply, 20)
    s.submit(ch, Job("loop"), 0)
    assert s.drain(ch) == 2 and applied == ["loop", "global BA"] and s.in_flight == 0
    s.submit(ch, Job("loop"), 1)
    s.finish()
    assert applied[2:] == ["loop", "global BA"] and s.in_flight == 0


def test_the_global_ba_lag_is_counted_from_where_it_is_submitted():
    s = Scheduler()
    applied = []
    frame = [0]
    ch = s.channel("loop", Recording(applied), lambda out: applied.append((frame[0], out.name)), 20)
    s.submit(ch, Job("global BA"), 30, lag=100)
    _run(s, frame, 131)
    assert applied == [(130, "global BA")]


def test_stale_global_ba_is_judged_by_the_applied_count_it_carries():
    """The loop closer supersedes a global BA job whose count of applied corrections is below the number of
    corrections it has made (plvo.loop.worker): a loop correction in flight when the job was made. The count is
    the scheduler's, advanced by the loop stage at each applied correction."""
    from plvo.loop.worker import GlobalBAJob, LoopCore

    core = LoopCore.__new__(LoopCore)
    core._made = [object(), object()]  # two corrections made: the first applied, the second still in flight
    core._skipped = 0
    s = Scheduler()
    s.loop_corrections_applied = 1
    job = GlobalBAJob(30, None, 0.5, s.loop_corrections_applied)
    out = core.process(job)
    assert out.correction is None and out.rejected.startswith("superseded")


def test_what_the_map_may_drop_is_beyond_every_window_in_flight():
    cfg = merge(SystemConfig(), {"backend": {"window_keyframes": 8}, "tracking": {"search_keyframes": 3}})
    assert oldest_reachable_keyframe(20, cfg) == 12
    cfg = merge(cfg, {"tracking": {"search_keyframes": 11}})
    assert oldest_reachable_keyframe(20, cfg) == 9
