"""The Rerun recorder writes every entity of the table at the frames it belongs to (late back-end results at their
keyframe's frame), colours the tracker's matches, logs its decisions, and the .rrd reads back into the viewer's
store intact. Driven by a fake run (tests/helpers/app_fakes.py) shaped like plvo.runtime.system.System's: no dataset
needed."""

from __future__ import annotations

import numpy as np
import pytest
from app_fakes import CALIB, LOST_FRAME, drive, keyframe_frames, pose

from plvo.geometry.se3 import exp, inv
from plvo.recording import RunInfo
from plvo.types import Calibration
from plvo_app.recording_levels import DetailOptions
from plvo_app.rerun_recorder import ENTITIES, RerunOptions, RerunRecorder
from plvo_app.rrd_reader import read_rrd
from plvo_app.scene_common import GREEN, MAGENTA, RED, EstimateTrail, gt_in_estimate_world
from plvo_app.viser_viewer import SceneStore, load_rrd

N = 9
KFS = keyframe_frames(N)  # [0, 3, 4, 6]: every 3 frames and the re-initialisation at LOST_FRAME


@pytest.fixture(scope="module")
def rrd(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "fake.rrd"
    rec = RerunRecorder(path, RerunOptions(detail=DetailOptions(level="full")))
    drive(rec, N, backend_lag=1)
    rec.set_status("complete", N)
    rec.close()
    return path


@pytest.fixture(scope="module")
def data(rrd):
    return read_rrd(rrd)


def _rgb(packed) -> np.ndarray:
    c = np.asarray(packed, np.uint32)
    return np.stack([(c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255], 1)


def test_every_entity_with_its_frames(data):
    every, kfs = list(range(N)), KFS
    expect = {e: every for e in ("camera", "camera/image", "camera/image/orb", "camera/image/lsd_merged",
                                 "camera/image/tracked_points", "camera/image/tracked_lines")}
    expect.update({e: kfs for e in ("camera/image/lsd_raw", "camera/image/lidar", "camera/image/patches",
                                    "camera/image/line_patches", "lidar", "lidar/scan", "depth/points",
                                    "depth/lines", "depth/planes", "map/points", "map/lines")})
    expect.update({"keyframes": kfs + [N - 1], "trajectory/est": kfs[1:] + [N - 1], "graph": kfs[1:],
                   "loops": [kfs[-1]]})
    for entity, frames in expect.items():
        assert data.frames(f"/world/{entity}") == frames, entity
    for series, frames in {"time/total": every, "tracking/point_inliers": every, "tracking/lost": every,
                           "depth/point_priors": kfs, "map/points": kfs, "backend/scale_factor": kfs,
                           "time/bundle_adjustment": kfs, "loop/candidates": kfs}.items():
        assert data.frames(f"/metrics/{series}") == frames, series
    assert {"/world", "/world/camera/image", "/world/trajectory/gt"} <= set(data.static)
    assert {e.removeprefix("/") for e in data.entities if not e.startswith("/metrics")} <= set(ENTITIES)
    assert data.sensor_time[4] == pytest.approx(0.4)


def test_late_back_end_results_sit_at_their_keyframe(data):
    # the fake back end hands keyframe 3's map at frame 4: it is recorded at frame 3, with frame 3's sensor time
    assert len(data.temporal["/world/map/points"][3]["Points3D:positions"]) == 200 * 2
    assert len(data.temporal["/world/map/points"][4]["Points3D:positions"]) == 200 * 3


def test_tracked_matches_coloured_inlier_outlier(data):
    pts = data.temporal["/world/camera/image/tracked_points"][2]
    colors = _rgb(pts["Points2D:colors"])
    assert len(pts["Points2D:positions"]) == 20
    assert np.all(colors[::2] == GREEN) and np.all(colors[1::2] == RED)
    lines = data.temporal["/world/camera/image/tracked_lines"][2]
    assert len(lines["LineStrips2D:strips"]) == 4
    assert _rgb(lines["LineStrips2D:colors"]).tolist() == [list(GREEN)] * 3 + [list(RED)]
    # a re-initialised frame has no matches to landmarks: the overlay is cleared, not left from the last frame
    assert len(data.temporal["/world/camera/image/tracked_points"][LOST_FRAME]["Points2D:positions"]) == 0
    assert data.temporal["/metrics/tracking/point_inliers"][2]["Scalars:scalars"] == [10.0]
    assert data.temporal["/metrics/tracking/lost"][LOST_FRAME]["Scalars:scalars"] == [1.0]


def test_decisions_in_the_log(data):
    by_frame = {}
    for f, level, text in data.log:
        by_frame.setdefault(f, []).append((level, text))
    assert any("initialised from lidar depth" in t for _, t in by_frame[0])
    assert ("WARN", f"frame {LOST_FRAME}: tracking lost (too few matches); re-initialised from the current lidar "
            "depth") in by_frame[LOST_FRAME]
    for f in KFS:
        assert any(t.startswith(f"frame {f}: keyframe {KFS.index(f)} (") for _, t in by_frame[f]), by_frame[f]
    assert any("30 new point and 5 new line landmarks" in t for _, t in by_frame[3])
    assert any("loop keyframe 3 -> 0 accepted" in t and "verified" in t for _, t in by_frame[KFS[-1]])


def test_graph_coloured_by_zeta_and_loops(data):
    # at frame 6 the odometry edges have zeta 0, 0.1, 0.2: red, yellowish, green (exp(-2) = 0.135 and above)
    colors = _rgb(data.temporal["/world/graph"][3]["LineStrips3D:colors"])
    assert colors.tolist() == [[255, 0, 40]]  # zeta 0: no factor
    row = data.temporal["/world/graph"][KFS[-1]]  # the loop closer's graph overrides: one loop edge, magenta
    assert _rgb(row["LineStrips3D:colors"]).tolist() == [list(MAGENTA)]
    loops = np.asarray(data.temporal["/world/loops"][KFS[-1]]["LineStrips3D:strips"][0])
    np.testing.assert_allclose(loops, [pose(KFS[-1])[:3, 3], pose(0)[:3, 3]], atol=1e-5)


def test_estimate_is_every_frame_so_far(data):
    est = np.asarray(data.temporal["/world/trajectory/est"][N - 1]["LineStrips3D:strips"][0])
    want = np.array([pose(i)[:3, 3] for i in range(N)])
    np.testing.assert_allclose(est[:N], want, atol=1e-4)
    np.testing.assert_allclose(data.temporal["/world/camera"][5]["Transform3D:translation"][0], pose(5)[:3, 3],
                               atol=1e-5)


def test_estimate_follows_keyframe_refinement():
    trail = EstimateTrail()
    for i in range(4):
        trail.on_tracking(i, pose(i))
        if i in (0, 2):
            trail.on_keyframe(i // 2, i, pose(i))
    np.testing.assert_allclose(trail.positions(), [pose(i)[:3, 3] for i in range(4)], atol=1e-9)
    moved = exp(np.array([0.5, -0.2, 1.0, 0.0, 0.2, 0.0])) @ pose(2)  # the back end moves keyframe 1 (frame 2)
    trail.on_graph(np.array([0, 1]), np.stack([pose(0), moved]))
    p = trail.positions()
    np.testing.assert_allclose(p[:2], [pose(0)[:3, 3], pose(1)[:3, 3]], atol=1e-9)  # tracked from keyframe 0
    np.testing.assert_allclose(p[3], (moved @ inv(pose(2)) @ pose(3))[:3, 3], atol=1e-9)  # rigidly along
    np.testing.assert_allclose(trail.keyframe_positions()[1], moved[:3, 3])


def test_ground_truth_moved_into_the_estimates_world():
    T_cam0_cam = np.eye(4)
    T_cam0_cam[0, 3] = -0.54  # e.g. cam1 of KITTI
    calib = Calibration(K=CALIB.K, T_cam_velo=CALIB.T_cam_velo, width=1200, height=360, T_cam0_cam=T_cam0_cam)
    gt = np.array([pose(i) for i in range(3, 8)])  # frames 3:8 of a sequence: gt[0] far from identity
    info = RunInfo("r", "s", calib, tuple(range(3, 8)), gt, {}, "v", "g", "c")
    moved = gt_in_estimate_world(info)
    np.testing.assert_allclose(moved[0], T_cam0_cam, atol=1e-12)  # where the tracker starts camera 1
    np.testing.assert_allclose(moved[4], T_cam0_cam @ inv(gt[0]) @ gt[4], atol=1e-12)


def test_properties_say_how_it_was_made(data):
    props = data.properties
    assert props["plvo:version"] == "0.1.0" and props["plvo:git_revision"] == "abc123"
    assert props["plvo:command_line"] == "plvo-viz --seq fake"
    assert "n_features = 50" in props["plvo:config"]
    assert props["plvo_run:status"] == "complete" and props["plvo_run:frames_done"] == N


def test_images_are_jpeg_and_scans_thinned(data):
    _, row = next(data.rows("/world/camera/image"))
    assert bytes(row["EncodedImage:blob"][0])[:2] == b"\xff\xd8"  # JPEG magic
    _, scan = next(data.rows("/world/lidar/scan"))
    assert len(scan["Points3D:positions"]) <= 4000


def test_replay_store_round_trip(rrd):
    store = load_rrd(rrd)
    assert store.frames == list(range(N))
    np.testing.assert_allclose(store.K, CALIB.K, atol=1e-4)
    assert (store.width, store.height) == (CALIB.width, CALIB.height)
    for f in (0, 4, 8):  # poses far from symmetric: catches a transposed (column-major) rotation
        np.testing.assert_allclose(store.latest("pose", f), pose(f), atol=1e-5)
    # latest-at: frame 5 shows the scan of keyframe 4, placed in the world by T_world_cam @ T_cam_velo
    scan5, scan4 = store.latest("scan", 5)[0], store.latest("scan", 4)[0]
    assert scan5 is scan4 and scan4.dtype == np.float32
    assert store.gt.shape == (N, 3)
    np.testing.assert_allclose(store.gt[5], (inv(pose(0)) @ pose(5))[:3, 3], atol=1e-5)
    assert store.latest("loops", 8).shape == (1, 2, 3) and store.latest("loops", 5) is None
    assert store.latest("map_points", 7).shape == (800, 3)


def test_store_latest_at_semantics():
    s = SceneStore()
    s.put("x", 5, "a")
    s.put("x", 2, "b")
    s.put("x", 5, "c")
    assert [s.latest("x", f) for f in (1, 2, 4, 5, 9)] == [None, "b", "b", "c", "c"]


def test_unreadable_recording_is_a_plvo_error(tmp_path):
    from plvo.errors import RecordingError

    bad = tmp_path / "bad.rrd"
    bad.write_bytes(b"not a recording")
    with pytest.raises(RecordingError, match="bad.rrd"):
        read_rrd(bad)
    with pytest.raises(RecordingError, match="missing.rrd"):
        read_rrd(tmp_path / "missing.rrd")


def test_simplified_polyline_keeps_bends_not_straights():
    """A trajectory is drawn simplified to a tolerance: a straight stretch keeps its ends, a bend its points, a U-turn
    the point it folds back at (distances to the segment, not its line), all within the tolerance and the budget."""
    from plvo_app.scene_common import simplify_polyline

    rng = np.random.default_rng(0)
    ell = np.cumsum(np.r_[np.zeros((1, 3)), np.tile([0, 0, 1.0], (200, 1)), np.tile([1.0, 0, 0], (200, 1))], 0)
    np.testing.assert_array_equal(simplify_polyline(ell + rng.normal(0, 0.005, ell.shape), 0.05, 800), [0, 200, 400])
    u = np.c_[np.zeros((100, 2)), np.r_[np.arange(50.0), 49 - np.arange(50.0)]]
    np.testing.assert_array_equal(simplify_polyline(u, 0.05, 800), [0, 49, 99])
    a = np.linspace(0, np.pi, 1000)
    arc = np.c_[100 * np.cos(a), np.zeros(1000), 100 * np.sin(a)]
    idx = simplify_polyline(arc, 0.05, 800)
    assert idx[0] == 0 and idx[-1] == 999 and 50 < len(idx) < 400
    k = np.minimum(np.searchsorted(idx, np.arange(1000), side="right") - 1, len(idx) - 2)  # each vertex's chord
    a, d = arc[idx[k]], arc[idx[k + 1]] - arc[idx[k]]
    t = np.clip(np.einsum("ij,ij->i", arc - a, d) / np.einsum("ij,ij->i", d, d), 0, 1)
    assert np.linalg.norm(arc - a - t[:, None] * d, axis=1).max() <= 0.05
    assert len(simplify_polyline(arc, 0.0, 100)) <= 100 and simplify_polyline(arc, 0.0, 100)[-1] == 999
    np.testing.assert_array_equal(simplify_polyline(arc[:2], 0.05, 800), [0, 1])


def test_a_step_cut_short_leaves_no_frame_behind_its_status(tmp_path):
    """Ctrl-C inside frame 6's step, after its tracking: the recording says 6 frames done, and its per-frame series
    (the camera pose, the tracking scalars, buffered until close) end at frame 5, whatever stage the signal hit."""
    import app_fakes

    path = tmp_path / "cut.rrd"
    rec = RerunRecorder(path, RerunOptions())
    app_fakes.drive(rec, 6, backend_lag=0)
    rng = np.random.default_rng(1)
    rec.on_frame(app_fakes.frame(6, rng))
    fs = app_fakes.features(rng)
    rec.on_stage(6, fs)
    rec.on_stage(6, app_fakes.tracking(6, fs, False))  # the step is cut here, before its TimingResult
    rec.set_status("interrupted", 6)
    rec.close()
    data = read_rrd(path)
    assert data.properties["plvo_run:status"] == "interrupted" and data.properties["plvo_run:frames_done"] == 6
    assert data.frames("/world/camera") == list(range(6))
    assert data.frames("/metrics/tracking/point_inliers") == list(range(6))
    assert data.frames("/metrics/features/points") == list(range(6))


def test_a_step_cut_between_two_appends_still_closes(tmp_path):
    """Ctrl-C raises between any two bytecodes: here inside frame 6's step, after the estimate trail took the frame
    and its reference keyframe but not its position, and a scalar buffer its frame and time but not its value (CI
    met the first: closing raised an IndexError and the buffered scalars were lost). The recording still closes
    with every series ending at frame 5."""
    import app_fakes

    path = tmp_path / "cut.rrd"
    rec = RerunRecorder(path, RerunOptions())
    app_fakes.drive(rec, 6, backend_lag=0)
    rec._trail.frames.append(6)
    rec._trail._ref.append(rec._trail._ref[-1])
    frames, times, _ = rec._scalars_buf["metrics/time/total"]
    frames.append(6)
    times.append(0.6)
    rec.set_status("interrupted", 6)
    rec.close()
    data = read_rrd(path)
    assert data.frames("/metrics/time/total") == list(range(6))
    assert data.frames("/world/camera") == list(range(6))
    assert len(data.temporal["/world/trajectory/est"]) > 0


def test_a_restarted_run_records_the_run_that_counts(tmp_path):
    """System.restart (a camera-lidar time offset found at frame 4): the recording at the path holds the frames of
    the run started again, says why, and the first five frames are kept beside it, stamped "restarted"."""
    import app_fakes

    path = tmp_path / "run.rrd"
    rec = RerunRecorder(path, RerunOptions())
    app_fakes.drive(rec, 5, backend_lag=0)
    rec.on_restart(app_fakes.restart_info(N, 4))
    app_fakes.drive(rec, N, start=False)
    rec.set_status("complete", N)
    rec.close()
    before = tmp_path / "run-before-restart.rrd"
    assert rec.path == path and rec.before_restart == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run-before-restart.rrd", "run.rrd"]
    data, first = read_rrd(path), read_rrd(before)
    assert data.frames("/world/camera") == list(range(N))
    assert data.frames("/metrics/tracking/point_inliers") == list(range(N))  # the first run's series are not in it
    assert data.properties["plvo_run:status"] == "complete"
    assert data.properties["plvo_restart:at_frame"] == 4 and data.properties["plvo_restart:time_offset_s"] == 0.098
    assert data.properties["plvo_restart:before"] == str(before)
    assert first.properties["plvo_run:status"] == "restarted" and first.properties["plvo_run:frames_done"] == 5
    assert first.frames("/world/camera") == list(range(5))
