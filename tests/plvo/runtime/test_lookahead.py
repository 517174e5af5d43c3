"""Features extracted ahead of tracking: the prefetching thread runs `System.prepare` on the next frames
while the tracker works on the current one or waits for a worker; the trajectory must not change."""

from __future__ import annotations

import os
import sys
import threading

import numpy as np
import pytest

from plvo.runtime.prefetch import prefetched
from plvo.types import Frame


class _Frames:
    def __init__(self, n: int):
        self.n = n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> Frame:
        return Frame(i, 0.1 * i, np.full((4, 4), i, np.uint8), np.zeros((1, 4), np.float32), calib=None)


def _extraction_threads(monkeypatch) -> list[str]:
    """The names of the threads of this process that extract a frame's features from now on (a list that grows)."""
    from plvo.tracking.frontend import Frontend

    calls: list[str] = []
    original = Frontend.features

    def spy(self, image):
        calls.append(threading.current_thread().name)
        return original(self, image)

    monkeypatch.setattr(Frontend, "features", spy)
    return calls


def test_prepare_runs_in_the_prefetching_thread_in_order():
    threads = []

    def prepare(frame: Frame) -> Frame:
        threads.append(threading.current_thread().name)
        return Frame(frame.index, frame.time, frame.image, frame.scan, frame.calib, features_s=float(frame.index))

    got = list(prefetched(_Frames(6), prepare=prepare))
    assert [f.index for f in got] == list(range(6)) and [f.features_s for f in got] == list(range(6))
    assert set(threads) == {"plvo-prefetch"}
    assert [f.features_s for f in prefetched(_Frames(3), depth=0, prepare=prepare)] == [0, 1, 2]  # same, inline


def test_an_error_in_prepare_arrives_at_its_frame():
    def prepare(frame: Frame) -> Frame:
        if frame.index == 3:
            raise ValueError("frame 3: bad image")
        return frame

    seen = []
    with pytest.raises(ValueError, match="frame 3: bad image"):
        for frame in prefetched(_Frames(6), prepare=prepare):
            seen.append(frame.index)
    assert seen == [0, 1, 2]


def test_features_ahead_give_the_same_trajectory(synth_sequence_factory, monkeypatch):
    """run_system prepares frames in the prefetching thread; stepping the same frames without it must give the
    same poses to the last bit (features are a function of the image and the config alone), and the tracker must
    not extract any feature itself once the stages are built."""
    from plvo.config import SystemConfig, merge
    from plvo.data.kitti import KittiOdometry
    from plvo.runtime.run import run_system
    from plvo.runtime.system import System

    ds = KittiOdometry(synth_sequence_factory(16, seed=0), "00")
    cfg = merge(SystemConfig(), {"backend": {"concurrent": False}})
    calls = _extraction_threads(monkeypatch)
    ahead = run_system(System(cfg, calib=ds.calib), ds)
    assert calls == ["plvo-prefetch"] * len(ds)
    assert ahead.timings["features"] and min(ahead.timings["features"]) > 0  # the extraction's own time, reported

    calls.clear()
    system = System(cfg, calib=ds.calib)
    try:
        for i in range(len(ds)):
            system.step(ds[i])
        system.finish()
        plain = system.poses_cam0(ds.frame_indices)
    finally:
        system.close()
    assert calls == [threading.main_thread().name] * len(ds)
    np.testing.assert_array_equal(ahead.poses, plain)


def test_finish_collects_each_frame_one_frame_after_it_was_started():
    """With `finish`, the reading thread starts frame i+1 before it collects frame i (the features process then has
    the next image while it works), frames come out in order, and an error in either arrives at its own frame."""
    events: list[tuple[str, int]] = []

    def start(frame: Frame) -> int:
        events.append(("start", frame.index))
        return 10 * frame.index

    def finish(frame: Frame, started: int) -> Frame:
        events.append(("finish", frame.index))
        if frame.index == 4:
            raise ValueError("frame 4: the features process failed")
        return Frame(frame.index, frame.time, frame.image, frame.scan, frame.calib, features_s=float(started))

    got = []
    with pytest.raises(ValueError, match="frame 4"):
        for frame in prefetched(_Frames(6), prepare=start, finish=finish):
            got.append((frame.index, frame.features_s))
    assert got == [(i, 10.0 * i) for i in range(4)]
    assert events[:4] == [("start", 0), ("start", 1), ("finish", 0), ("start", 2)]
    for i in range(4):  # every frame is started before the frame before it is collected
        assert events.index(("start", i + 1)) < events.index(("finish", i))
    events.clear()
    assert [f.features_s for f in prefetched(_Frames(3), prepare=start, finish=finish)] == [0.0, 10.0, 20.0]
    assert events[-2:] == [("finish", 1), ("finish", 2)]  # the last frame collected after the loop
    assert [f.features_s for f in prefetched(_Frames(3), depth=0, prepare=start, finish=finish)] == [0.0, 10.0, 20.0]


def test_the_features_process_gives_the_trajectory_of_features_in_a_thread(synth_sequence_factory, monkeypatch):
    """The deployed mode extracts features in a process of its own (plvo.features.worker): the tracker's process
    extracts none, and the poses equal those of the same workers run as threads (features extracted in the reading
    thread), to the last bit. The tracker's process, sharing the cores with its worker processes, runs open3d and
    OpenCV single-threaded while the System runs (plvo.runtime.workers.libraries_single_threaded), and gets their
    threads back at its close."""
    import cv2
    import open3d

    from plvo.config import SystemConfig, merge
    from plvo.data.kitti import KittiOdometry
    from plvo.runtime.run import run_system
    from plvo.runtime.system import System

    ds = KittiOdometry(synth_sequence_factory(16, seed=0), "00")
    calls = _extraction_threads(monkeypatch)
    mine = open3d.utility.get_max_threads(), cv2.getNumThreads()
    system = System(SystemConfig(), calib=ds.calib)  # the defaults: concurrent workers in processes
    system.wait_ready()
    assert len(system.worker_pids) == 3  # back end, loop closer, features
    # the tracker's process shares the cores with its workers: its libraries single-threaded while the System runs
    assert (open3d.utility.get_max_threads(), cv2.getNumThreads()) == (1, 1)
    in_process = run_system(system, ds)
    assert (open3d.utility.get_max_threads(), cv2.getNumThreads()) == mine  # given back at close
    if (os.cpu_count() or 1) > 1:
        assert min(mine) > 1  # the limits are not the machine's defaults (this could not fail on one core)
    assert calls == []
    assert len(in_process.timings["features"]) == len(ds) and min(in_process.timings["features"]) > 0

    threads = run_system(System(merge(SystemConfig(), {"backend": {"executor": "thread"}}), calib=ds.calib), ds)
    assert calls == ["plvo-prefetch"] * len(ds)
    np.testing.assert_array_equal(in_process.poses, threads.poses)


def _nice() -> int:
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread priorities are Linux's")
def test_the_look_ahead_runs_at_a_lower_priority(synth_sequence_factory):
    """The System's reading thread, the line thread it uses, the features process and the loop closer's process run
    at LOOKAHEAD_NICENESS or lower; the tracker's thread keeps its priority."""
    import psutil

    from plvo.config import SystemConfig, merge
    from plvo.data.kitti import KittiOdometry
    from plvo.features import extract
    from plvo.priority import LOOKAHEAD_NICENESS
    from plvo.runtime.system import System

    ds = KittiOdometry(synth_sequence_factory(16, seed=0), "00")
    system = System(merge(SystemConfig(), {"loop": {"enabled": True}}), calib=ds.calib)
    seen = []
    start = system._lookahead.start  # the reading thread's call for each frame (the deployed mode's)

    def spy(frame):
        seen.append(_nice())
        return start(frame)

    system._lookahead.start = spy
    mine = _nice()
    try:
        system.wait_ready()
        assert psutil.Process(system.worker_pids[1]).nice() >= LOOKAHEAD_NICENESS  # the loop closer
        assert psutil.Process(system.worker_pids[2]).nice() >= LOOKAHEAD_NICENESS  # the features process
        assert psutil.Process(system.worker_pids[0]).nice() == psutil.Process().nice()  # the back end: as the caller
        for frame in system.read_ahead(ds):
            system.step(frame)
        system.finish()
    finally:
        system.close()
    assert len(seen) == len(ds) and min(seen) >= LOOKAHEAD_NICENESS
    assert extract._executor().submit(_nice).result() >= LOOKAHEAD_NICENESS
    assert _nice() == mine


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread priorities are Linux's")
def test_lower_priority_only_lowers():
    from plvo.priority import lower_priority

    def body(out):
        lower_priority(7)
        lower_priority(3)  # never raised back: that would need a privilege
        out.append(_nice())

    out: list[int] = []
    t = threading.Thread(target=body, args=(out,))
    t.start()
    t.join()
    assert out == [max(7, _nice())]


def test_a_failure_in_the_features_process_names_its_frame(synth_sequence_factory):
    """An image the extraction refuses fails the run at that frame with one line naming the worker and the frame."""
    import dataclasses

    from plvo.config import SystemConfig
    from plvo.data.kitti import KittiOdometry
    from plvo.errors import WorkerError
    from plvo.runtime.system import System

    ds = KittiOdometry(synth_sequence_factory(16, seed=0), "00")

    class _OneBadImage:
        calib, frame_indices = ds.calib, ds.frame_indices

        def __len__(self) -> int:
            return 6

        def __getitem__(self, i: int) -> Frame:
            frame = ds[i]
            return dataclasses.replace(frame, image=frame.image.astype(np.float32)) if i == 4 else frame

    system = System(SystemConfig(), calib=ds.calib)
    done = []
    try:
        with pytest.raises(WorkerError, match=r"^the features failed on frame 4 \(FeaturesJob\): PlvoError: "
                                              r"extract_features: field 'image' must be \(H,W\) uint8"):
            for frame in system.read_ahead(_OneBadImage()):
                system.step(frame)
                done.append(frame.index)
    finally:
        system.close()
    assert done == [0, 1, 2, 3]
