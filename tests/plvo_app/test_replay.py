"""A recording at the default level replays with something on every frame: the car, the trajectory and the map
everywhere, every keyframe's scan and image thinned (so the road is there between the detail frames), the full image
only where the level put detail (the 3D scan only at the full level: the thin one stands for it), the list of those
frames and why, and Rerun's camera panel showing the thin image. Checked on the fake run
(tests/helpers/app_fakes.py) read back, and on real KITTI 04: its bytes a keyframe and the estimate for a whole KITTI
00 against the 25 MB budget (plvo_app.level_sizes)."""

from __future__ import annotations

import json
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from app_fakes import CALIB, LOST_FRAME, drive, keyframe_frames, pose

from plvo.geometry.se3 import transform_points
from plvo_app.recording_levels import DetailOptions
from plvo_app.rerun_recorder import ENTITIES, RerunOptions, RerunRecorder
from plvo_app.rrd_index import load_rrd
from plvo_app.rrd_reader import read_rrd

N = 30
KFS = keyframe_frames(N)  # every 3 frames and LOST_FRAME
FACES = [p for p in ENTITIES if p.startswith("world/lidar/thin/")]


class KeepScans:
    """Passes everything to `rec`, keeping each frame's scan (what the thin one is checked against)."""

    def __init__(self, rec):
        self.rec, self.scans = rec, {}

    def __getattr__(self, name):
        return getattr(self.rec, name)

    def on_frame(self, frame):
        self.scans[frame.index] = frame.scan[:, :3].astype(float)
        self.rec.on_frame(frame)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    path = tmp_path_factory.mktemp("replay") / "default.rrd"
    rec = KeepScans(RerunRecorder(path, RerunOptions(detail=DetailOptions(keyframe_stride=4))))
    drive(rec, N)
    rec.close()
    return SimpleNamespace(path=path, data=read_rrd(path), store=load_rrd(path), scans=rec.scans)


def _runs(frames: list[int]) -> list[tuple[int, int]]:
    runs: list[tuple[int, int]] = []
    for f in frames:
        if runs and runs[-1][1] == f:
            runs[-1] = (runs[-1][0], f + 1)
        else:
            runs.append((f, f + 1))
    return runs


def test_the_car_the_trajectory_and_the_map_on_every_frame(recorded):
    data, store = recorded.data, recorded.store
    assert data.frames("/world/camera") == list(range(N))
    for f in range(N):
        np.testing.assert_allclose(store.latest("pose", f)[:3, 3], pose(f)[:3, 3], atol=1e-5)
        assert store.latest("map_points", f) is not None and store.latest("keyframes", f) is not None, f
    # the estimate, redrawn now and then, reaches the car through the camera's own track since
    for f in range(KFS[1], N):
        est = store.latest("est", f)
        at = store.source("est", f)[1]
        assert est is not None and len(est) >= 2, f
        tail = store.track(at, f)
        end = tail[-1] if len(tail) else np.asarray(est)[-1]
        np.testing.assert_allclose(end, pose(f)[:3, 3], atol=1e-4)


def test_thin_scan_and_image_on_every_keyframe_full_image_on_detail_frames(recorded):
    data, store = recorded.data, recorded.store
    assert RerunOptions().thin_every_keyframes == 1 and len(FACES) == 4
    for path in [*FACES, "world/camera/image/keyframe", "world/lidar"]:
        assert ENTITIES[path].level == "summary", path
    for path in FACES:
        assert data.frames(f"/{path}") == KFS, path
    assert data.frames("/world/camera/image/keyframe") == KFS
    assert data.frames("/world/lidar") == KFS  # the scans' pose
    detail = data.frames("/world/camera/image")  # the full image: the detail frames
    assert 0 < len(detail) < N and LOST_FRAME in detail
    assert {f for f in KFS if f in detail} <= set(data.frames("/world/camera/image/lidar"))  # the projected scan
    assert ENTITIES["world/lidar/scan"].level == "full" and "/world/lidar/scan" not in data.entities
    for f in range(N):
        img, scan = store.source("image", f), store.source("scan", f)
        last_kf = max(k for k in KFS if k <= f)
        # the image: the frame's own on a detail frame, else its keyframe's thin one; the scan: its keyframe's thin one
        assert img == (("full", f) if f in detail else ("thin", last_kf)), (f, img)
        assert scan == ("thin", last_kf), (f, scan)
    small = cv2.imdecode(np.frombuffer(store.latest("image", 13), np.uint8), cv2.IMREAD_UNCHANGED)
    assert small.shape[:2] == (72, 240)  # the fake's 1200 x 360 at 1/5


def test_the_thin_scan_is_the_scan(recorded):
    """Decoded from its depth images into the world, the thin scan lies on the scan (moved by the keyframe's lidar
    pose) to within the faces' 2-degree pixels (half of one at 20 m: 0.17 m)."""
    from scipy.spatial import cKDTree

    store = recorded.store
    f = KFS[2]
    world = transform_points(pose(f) @ CALIB.T_cam_velo, recorded.scans[f])
    pts, colors = store.latest("scan", f)
    d, _ = cKDTree(world).query(pts)
    assert len(pts) > 1000 and len(colors) == len(pts)
    assert np.median(d) < 0.2 and np.percentile(d, 95) < 0.6, (np.median(d), np.percentile(d, 95))


def test_the_detail_list_is_in_the_recording(recorded):
    data, store = recorded.data, recorded.store
    windows = json.loads(data.properties["plvo_detail:windows"])
    runs = _runs(data.frames("/world/camera/image"))
    assert [(a, b) for a, b, _ in windows] == runs
    why = {a: w for a, _, w in windows}
    assert "keyframe 0 (1 in 4)" in why[0] and f"tracking lost at frame {LOST_FRAME}" in why[0]
    assert any(w.startswith(f"loop accepted at frame {KFS[-1]}") for w in why.values())
    assert store.detail == [tuple(w) for w in windows]
    text = data.static["/detail"]["TextDocument:text"][0]
    assert "| 0-7 | keyframe 0 (1 in 4); tracking lost at frame 4 |" in text
    # a recording without the list (cut short before it closed): the runs of its full images, without why
    del store.index.properties["plvo_detail:windows"]
    assert [(a, b) for a, b, _ in store._detail_windows()] == runs


def test_rerun_camera_panel_shows_the_thin_image(recorded):
    """Rerun's camera panel is the image's pinhole space: the thin image is under it, scaled up to its pixels and
    drawn under the full image, so that between detail frames the panel shows the last keyframe's image."""
    from plvo_app.rrd_blueprint import blueprint

    data = recorded.data

    def views(c):
        kids = getattr(c, "contents", None)
        return [c] if not isinstance(kids, (list, tuple)) else [v for k in kids for v in views(k)]

    camera = [v for v in views(blueprint().root_container) if type(v).__name__ == "Spatial2DView"]
    assert len(camera) == 1 and camera[0].contents == "$origin/**"
    assert "world/camera/image/keyframe".startswith(camera[0].origin + "/")
    st = data.static["/world/camera/image/keyframe"]
    np.testing.assert_allclose(st["Transform3D:scale"][0], [1200 / 240, 360 / 72, 1.0])
    assert st["EncodedImage:draw_order"][0] < -10  # under the full image (Rerun's images draw at -10)
    assert "TextDocumentView" in {type(v).__name__ for v in views(blueprint().root_container)}


@pytest.fixture(scope="module")
def kitti_levels(kitti_root, tmp_path_factory):
    """KITTI 04's 51 frames recorded at every level side by side (plvo_app.level_sizes.measure_levels)."""
    from plvo.config import load_config
    from plvo.data.registry import open_dataset
    from plvo_app.level_sizes import measure_levels

    out = tmp_path_factory.mktemp("levels")
    dataset = open_dataset(kitti_root, "04", None)
    return measure_levels(dataset, load_config(None), len(dataset), out_dir=out, keep=True)


def test_kitti_default_level_within_the_budget(kitti_levels):
    """Every keyframe's thin scan and image fit their share of the 25 MB a whole KITTI 00 may weigh, and so does the
    whole estimate (with every event window used)."""
    from plvo_app.level_sizes import BUDGET_MB, THIN_BYTES_PER_THIN_KEYFRAME, thin_bytes

    levels = kitti_levels
    assert levels["summary"]["bytes"] < levels["default"]["bytes"] < levels["full"]["bytes"]
    thin, n_thin = thin_bytes(levels["default"]["path"])
    n_kf = levels["default"]["keyframes"]
    assert n_thin == n_kf  # every keyframe
    assert thin / n_thin <= THIN_BYTES_PER_THIN_KEYFRAME, thin / n_thin
    est = levels["default"]["long_run"]
    print(f"\nKITTI 04, {levels['default']['frames']} frames, {n_kf} keyframes: summary "
          f"{levels['summary']['bytes'] / 1e3:.0f} kB, default {levels['default']['bytes'] / 1e3:.0f} kB, full "
          f"{levels['full']['bytes'] / 1e3:.0f} kB; thin {thin / n_thin:.0f} bytes a thin keyframe; "
          f"4541 frames at the default level: {est['mb']:.1f} MB ({est['how']})")
    assert est["mb"] <= BUDGET_MB


def test_kitti_default_level_replays_every_frame(kitti_levels):
    path = kitti_levels["default"]["path"]
    data, store = read_rrd(path, ["/world/camera", "/world/camera/image", "/world/camera/image/keyframe",
                                  "/world/lidar/**", "/log"]), load_rrd(path)
    frames = list(range(51))
    kfs = sorted({f for f, _, t in data.log if t.startswith(f"frame {f}: keyframe ")})
    assert data.frames("/world/camera") == frames and kfs[0] == 0
    assert data.frames("/world/camera/image/keyframe") == kfs
    assert data.frames("/world/lidar/thin/0") == kfs
    assert data.frames("/world/lidar/scan") == []  # the 3D scan: at the full level only
    detail = data.frames("/world/camera/image")
    assert detail == [0] and [w[:2] for w in store.detail] == [(0, 1)]  # keyframe 0; no event in 04's 51 frames
    for f in frames:
        scan = store.latest("scan", f)
        assert store.latest("image", f) is not None and scan is not None and len(scan[0]) > 2000, f


def test_the_faces_depth_steps():
    """A face's depth is in 0.1 m steps to 5 m, 0.2 m steps beyond (half a 2-degree pixel is 0.09 m wide at 5 m:
    the depth errs no more than the direction), 0 where no point is."""
    from plvo_app.scene_common import RangeFaces, depth_image_points

    faces = RangeFaces()
    z = np.array([0.02, 1.23, 4.97, 5.04, 5.13, 12.37, 12.43, 7000.0])
    np.testing.assert_array_equal(faces.counts(z), [1, 12, 50, 50, 52, 124, 124, 65535])
    scan = np.array([[3.0, 0.0, 0.0], [3.2, 0.0, 0.0], [20.07, 2.0, -1.0]])  # two in a pixel: the nearer is kept
    pts = depth_image_points(faces.encode(scan)[0], faces.K, 1 / faces.unit)
    assert sorted(np.round(pts[:, 2], 2)) == [3.0, 20.0]


def test_the_faces_keep_each_pixels_nearest_return_of_a_real_scan(kitti_root):
    """On a real KITTI 04 scan each face's pixel holds the smallest depth count of the returns it sees, as a plain
    z-buffer computed here by sorting the (pixel, count) keys gives it, and no pixel without a return has one."""
    from plvo.data.registry import open_dataset
    from plvo_app.scene_common import RangeFaces

    faces = RangeFaces()
    scan = open_dataset(kitti_root, "04", slice(0, 1))[0].scan
    w, h = faces.size
    seen = 0
    for png, (pixel, count) in zip(faces.encode(scan), faces.returns(scan), strict=True):
        got = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED).ravel()
        key = np.sort(pixel << 16 | count.astype(np.int64))
        first = np.diff(key >> 16, prepend=-1) != 0
        want = np.zeros(h * w, np.uint16)
        want[key[first] >> 16] = key[first] & 0xFFFF
        np.testing.assert_array_equal(got, want)
        seen += int((got > 0).sum())
    assert seen > 2000  # ~3700 of a KITTI scan's points kept over the four faces
