"""Recording levels: a recording read back holds each level's entities (ENTITIES' level column) at the frames the
level promises: the summary at full length, detail on stride keyframes, around events (tracking lost, a loop, a
warning of the pipeline) and in the user's windows, cleared where it stops. Driven by the fake run of app_fakes."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from app_fakes import LOST_FRAME, drive, keyframe_frames

from plvo.errors import RecordingError
from plvo.results import TimingResult
from plvo_app.recording_levels import DetailOptions, DetailPolicy, parse_window
from plvo_app.rerun_recorder import ENTITIES, RerunOptions, RerunRecorder
from plvo_app.rrd_reader import read_rrd

N = 30
KFS = keyframe_frames(N)  # every 3 frames and LOST_FRAME
WARN_FRAME = 16
DETAIL_EVERY_FRAME = [p for p, e in ENTITIES.items() if e.level == "detail" and e.when == "frame"]
DETAIL_KEYFRAME = [p for p, e in ENTITIES.items() if e.level == "detail" and e.when == "keyframe"]
SUMMARY_EVERY_FRAME = [p for p, e in ENTITIES.items() if e.level == "summary" and e.when == "frame"
                       and p != "metrics"]


class WarnAt:
    """Passes everything to `rec`; at WARN_FRAME the pipeline logs a warning (as the back end does when it
    discards an optimisation)."""

    def __init__(self, rec):
        self.rec = rec

    def __getattr__(self, name):
        return getattr(self.rec, name)

    def on_stage(self, frame_index, result):
        if isinstance(result, TimingResult) and frame_index == WARN_FRAME:
            logging.getLogger("plvo.backend.worker").warning("back end: an optimisation moved a keyframe; discarded")
        self.rec.on_stage(frame_index, result)


def _record(path, detail: DetailOptions):
    rec = RerunRecorder(path, RerunOptions(detail=detail))
    drive(WarnAt(rec), N, backend_lag=1)
    rec.close()
    data = read_rrd(path)
    data.path = path
    return data


@pytest.fixture(scope="module")
def default(tmp_path_factory):
    return _record(tmp_path_factory.mktemp("lv") / "default.rrd", DetailOptions(keyframe_stride=4))


@pytest.fixture(scope="module")
def summary(tmp_path_factory):
    return _record(tmp_path_factory.mktemp("lv") / "summary.rrd", DetailOptions(level="summary",
                                                                               windows=((20, 23),)))


def _window(f: int, opt: DetailOptions = DetailOptions()) -> set[int]:
    return set(range(f - opt.before, f + opt.after + 1))


def test_summary_entities_at_full_length_in_every_level(default, summary):
    every = list(range(N))
    for data in (default, summary):
        for path in SUMMARY_EVERY_FRAME:
            assert data.frames(f"/{path}") == every, path
        for series in ("tracking/point_inliers", "features/points", "time/total"):
            assert data.frames(f"/metrics/{series}") == every, series
        assert data.frames("/world/map/points") == KFS  # the map at every keyframe
        # the graph at every back-end step: whole now and then (and the last one), else its recent edges
        whole, recent = data.frames("/world/graph"), data.frames("/world/graph/recent")
        assert sorted(set(whole) | set(recent)) == KFS[1:] and whole[0] == KFS[1] and whole[-1] == KFS[-1]
        assert data.frames("/world/loops") == [KFS[-1]]
        kf_lines = {f for f, _, t in data.log if t.startswith(f"frame {f}: keyframe ")}
        assert sorted(kf_lines) == KFS
        assert "/world/trajectory/est" in data.entities and "/world/trajectory/gt" in data.static


def test_default_detail_on_stride_keyframes_and_around_events(default):
    opt = DetailOptions(keyframe_stride=4)
    stride = {KFS[i] for i in range(0, len(KFS), 4)}
    last = N - 1  # the loop is handed over after the last frame: of its window, the frames still held back
    want = stride | _window(LOST_FRAME) | _window(WARN_FRAME) | {f for f in _window(KFS[-1])
                                                                  if last - opt.before < f <= last}
    for path in DETAIL_EVERY_FRAME:
        assert default.frames(f"/{path}") == sorted(want), path
    for path in DETAIL_KEYFRAME:
        assert default.frames(f"/{path}") == sorted(want & set(KFS)), path
    # where the window ends, the image is cleared (a viewer must not show frame 7's image at frame 8)
    assert max(_window(LOST_FRAME)) + 1 in default.cleared["/world/camera/image"]
    warned = [t for f, level, t in default.log if f == WARN_FRAME and level == "WARN"]
    assert warned and "discarded" in warned[0]


def test_replay_store_honours_the_clears(default):
    from plvo_app.rrd_index import load_rrd

    store = load_rrd(default.path)
    end = max(_window(LOST_FRAME)) + 1
    full = store.index.latest("/world/camera/image", "EncodedImage:blob", end)
    assert store.source("image", end - 1) == ("full", end - 1) and full is None
    # after the detail, the last keyframe's thin image, not the full image of a frame that has none
    last_thin = max(f for f in default.frames("/world/camera/image/keyframe") if f <= end)
    assert store.source("image", end) == ("thin", last_thin) and store.latest("image", end) is not None
    # frame 1 was cleared when it ended, then its held-back image was written when the loss at frame 4 wanted it
    assert 1 in default.cleared["/world/camera/image"] and store.source("image", 1) == ("full", 1)
    assert store.latest("pose", end) is not None  # the summary is not cleared


def test_map_thinned_outside_detail_full_inside(default):
    sizes = {f: len(row["Points3D:positions"]) for f, row in default.rows("/world/map/points")}
    kf_detail = set(default.frames("/world/camera/image/lidar"))  # the projected scan: detail keyframes
    outside = [f for f in KFS if f not in kf_detail]
    assert outside and all(sizes[f] <= RerunOptions().map_summary_points for f in outside)
    assert all(sizes[f] == 200 * (KFS.index(f) + 1) for f in kf_detail)  # the fake's full window map


def test_summary_level_has_detail_only_in_the_users_window(summary):
    for path in DETAIL_EVERY_FRAME:
        assert summary.frames(f"/{path}") == [20, 21, 22], path
    for path in DETAIL_KEYFRAME:
        assert summary.frames(f"/{path}") == [21], path
    assert summary.properties["plvo:record_level"] == "summary"


def test_the_3d_scan_at_the_full_level_only(default, summary):
    """Below the full level every keyframe's thin scan stands for the 3D one, also on detail frames (the full
    level's is checked in tests/plvo_app/test_rerun_recorder.py)."""
    full_only = [p for p, e in ENTITIES.items() if e.level == "full"]
    assert full_only == ["world/lidar/scan"]
    for data in (default, summary):
        assert "/world/lidar/scan" not in data.entities
        assert data.frames("/world/lidar/thin/0") == KFS


def test_event_windows_are_bounded():
    policy = DetailPolicy(DetailOptions(max_event_windows=3, max_windows_per_kind=2))
    for f in range(0, 200, 20):
        policy.event(f, "loop rejected")
    policy.event(300, "tracking lost")
    policy.event(400, "tracking lost")
    assert policy.n_event_windows == 3 and policy.want(300) and not policy.want(400)
    assert policy.want(20) and not policy.want(40)  # two of a kind, then the loop near-misses stop
    assert len(policy.events) == 12  # every event is kept, with or without detail


def test_bad_level_and_window_are_one_line_errors():
    with pytest.raises(RecordingError, match="recording level 'loud'"):
        DetailOptions(level="loud")
    with pytest.raises(RecordingError, match="window '9:3'"):
        parse_window("9:3")
    assert parse_window("1200:1300") == (1200, 1300)
    assert np.all(np.array(parse_window(" 0:1 ")) == (0, 1))


def test_a_slow_frame_is_slow_against_the_running_mean():
    """Frames between keyframes arrive fast (features extracted ahead), keyframes wait for the back end: that
    rhythm is not an event; a stall is."""
    policy = DetailPolicy(DetailOptions(level="default"))
    rhythm = [0.04, 0.04, 0.20] * 20  # 40 ms, 40 ms, then a keyframe's 200 ms: 5x the median, under 4x the mean
    assert not any(policy.timing(f, s) for f, s in enumerate(rhythm))
    assert policy.timing(len(rhythm), 2.0)  # a 2 s stall


def test_held_back_detail_is_made_only_for_the_frames_written(tmp_path, monkeypatch):
    """Per-frame detail (features, tracked matches) is held back as a recipe: Rerun's archetypes are made only
    for the frames the recording gets (stride keyframes, event windows), not for every frame."""
    import plvo_app.rerun_recorder as rrec

    made: list[str] = []
    for name in ("_points2d", "_strips2d"):
        real = getattr(rrec, name)
        monkeypatch.setattr(rrec, name, lambda *a, _real=real, _name=name, **k: made.append(_name) or _real(*a, **k))
    data = _record(tmp_path / "made.rrd", DetailOptions(keyframe_stride=4))
    written = {p: len(data.frames(f"/{rrec.E[p]}")) for p in ("orb", "tracked_points", "lsd_merged", "tracked_lines")}
    assert 0 < written["orb"] < N  # most frames' detail was held back and never written
    assert made.count("_points2d") == written["orb"] + written["tracked_points"]
    assert made.count("_strips2d") == written["lsd_merged"] + written["tracked_lines"]
