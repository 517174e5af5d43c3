"""The run's own threads cannot hang it: the frame-reading thread (plvo.runtime.prefetch) and the recording's writer
thread (plvo_app.rrd_sink) each end in one error within their bound when what they wait on never returns."""

from __future__ import annotations

import threading
import time

import pytest

from plvo.errors import RecordingError, RunFailed
from plvo.runtime.prefetch import prefetched

pytestmark = pytest.mark.timeout(60)


class Frames:
    """A dataset whose frame `stuck_at` never loads (a hung network disk); the others are their index."""

    def __init__(self, n: int, stuck_at: int):
        self.n, self.stuck_at = n, stuck_at
        self.frame_indices = list(range(100, 100 + n))
        self.release = threading.Event()

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> int:
        if i == self.stuck_at:
            self.release.wait()
        return i


def test_a_frame_that_never_loads_fails_after_the_bound():
    data = Frames(6, stuck_at=3)
    got = []
    t0 = time.monotonic()
    with pytest.raises(RunFailed, match=r"^frame 103 was not read and prepared within 1 s"):
        for frame in prefetched(data, timeout_s=1.0):
            got.append(frame)
    assert got == [0, 1, 2] and time.monotonic() - t0 < 10
    data.release.set()


def test_without_a_bound_the_frames_come_as_before():
    data = Frames(5, stuck_at=-1)
    assert list(prefetched(data, timeout_s=None)) == [0, 1, 2, 3, 4]


@pytest.fixture
def sink(tmp_path, monkeypatch):
    import rerun as rr

    from plvo_app import rrd_sink

    monkeypatch.setattr(rrd_sink, "WRITE_INTERVAL_S", 0.02)
    rec = rr.RecordingStream("plvo_test_sink")
    made = []

    def make():
        made.append(rrd_sink.RrdFileSink(rec, tmp_path / "run.rrd"))
        rr.log("/x", rr.Scalars(1.0), recording=rec)
        return made[-1]

    yield make
    for s in made:
        s._stop.set()


def test_a_writer_thread_that_fails_unexpectedly_stops_the_run(sink, monkeypatch):
    from plvo_app import rrd_sink

    def broken(self):
        raise ValueError("encoder exploded")

    monkeypatch.setattr(rrd_sink.RrdFileSink, "_write_pending", broken)
    s = sink()
    t0 = time.monotonic()
    while s._writer.is_alive() and time.monotonic() - t0 < 10:
        time.sleep(0.02)
    with pytest.raises(RecordingError, match=r"writing the recording failed \(ValueError: encoder exploded\)"):
        s.pump()


def test_a_write_that_never_returns_fails_the_close_after_the_bound(sink, monkeypatch):
    from plvo_app import rrd_sink

    release, entered = threading.Event(), threading.Event()
    real = rrd_sink.RrdFileSink._write

    def blocked(self, chunk, ends):
        entered.set()
        release.wait()
        real(self, chunk, ends)

    monkeypatch.setattr(rrd_sink.RrdFileSink, "_write", blocked)
    monkeypatch.setattr(rrd_sink, "CLOSE_TIMEOUT_S", 1.0)
    s = sink()
    assert entered.wait(10)  # the writer thread is in its blocked write
    t0 = time.monotonic()
    with pytest.raises(RecordingError, match=r"a write of the recording did not return within 1 s"):
        s.close()
    assert time.monotonic() - t0 < 5
    release.set()
