"""The Rerun recorder writes every entity of the table, and the .rrd reads back into the viewer's store intact."""

from __future__ import annotations

import numpy as np
import pytest

from app_fakes import CALIB, drive, pose
from plvo_app.rerun_recorder import ENTITIES, RerunRecorder
from plvo_app.rrd_reader import read_rrd
from plvo_app.viser_viewer import SceneStore, load_rrd

N = 9  # frames; keyframes at 0, 3, 6


@pytest.fixture(scope="module")
def rrd(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "fake.rrd"
    rec = RerunRecorder(path)
    drive(rec, N)
    rec.set_status("complete", N)
    rec.close()
    return path


def test_every_entity_with_its_frames(rrd):
    data = read_rrd(rrd)
    every = list(range(N))
    keyframes = [0, 3, 6]
    expect = {
        "/world/camera": every, "/world/camera/image": every, "/world/camera/image/orb": every,
        "/world/camera/image/lsd_raw": every, "/world/camera/image/lsd_merged": every,
        "/world/camera/image/lidar": keyframes, "/world/lidar/scan": keyframes, "/world/lidar": keyframes,
        "/world/depth/points": keyframes, "/world/depth/lines": keyframes, "/world/map/points": keyframes,
        "/world/map/lines": keyframes, "/world/keyframes": [0, 3, 6, 8], "/world/graph": [3, 6, 8],
        "/world/loops": [8], "/world/trajectory/est": keyframes, "/metrics/time/features": every,
        "/metrics/tracking/point_inliers": every,
    }
    for entity, frames in expect.items():
        assert data.frames(entity) == frames, entity
    assert {"/world", "/world/camera/image", "/world/trajectory/gt"} <= set(data.static)
    assert set(expect) | {"/world/trajectory/gt"} <= {"/" + p for p in ENTITIES} | {
        e for e in expect if e.startswith("/metrics")}
    assert data.sensor_time[4] == pytest.approx(0.4)


def test_properties_say_how_it_was_made(rrd):
    props = read_rrd(rrd).properties
    assert props["plvo:version"] == "0.1.0" and props["plvo:git_revision"] == "abc123"
    assert props["plvo:command_line"] == "plvo-viz --seq fake"
    assert "n_features = 50" in props["plvo:config"]
    assert props["plvo_run:status"] == "complete" and props["plvo_run:frames_done"] == N


def test_images_are_jpeg_and_scans_thinned(rrd):
    data = read_rrd(rrd)
    _, row = next(data.rows("/world/camera/image"))
    assert bytes(row["EncodedImage:blob"][0])[:2] == b"\xff\xd8"  # JPEG magic
    _, scan = next(data.rows("/world/lidar/scan"))
    assert len(scan["Points3D:positions"]) <= 12000


def test_orb_tracked_ones_coloured(rrd):
    row = read_rrd(rrd).temporal["/world/camera/image/orb"][2]
    colors = np.asarray(row["Points2D:colors"], np.uint32)
    green = (colors >> 16) & 255
    assert len(colors) == 50 and np.all(green[::2] == 220) and np.all(green[1::2] == 170)


def test_replay_store_round_trip(rrd):
    store = load_rrd(rrd)
    assert store.frames == list(range(N))
    np.testing.assert_allclose(store.K, CALIB.K, atol=1e-4)
    assert (store.width, store.height) == (CALIB.width, CALIB.height)
    for f in (0, 4, 8):  # poses far from symmetric: catches a transposed (column-major) rotation
        np.testing.assert_allclose(store.latest("pose", f), pose(f), atol=1e-5)
    # latest-at: frame 4 shows the scan of keyframe 3, placed in the world by T_world_cam @ T_cam_velo
    scan4, scan3 = store.latest("scan", 4)[0], store.latest("scan", 3)[0]
    assert scan4 is scan3 and scan3.dtype == np.float32
    assert store.gt.shape == (N, 3)
    np.testing.assert_allclose(store.gt[5], pose(5)[:3, 3], atol=1e-5)
    assert store.latest("loops", 8).shape == (1, 2, 3) and store.latest("loops", 7) is None
    assert store.latest("map_points", 7).shape == (600, 3)


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
