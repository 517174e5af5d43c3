"""The loop database keeps what a later verification needs, compactly: memory is O(kept), not O(frames read)."""

from __future__ import annotations

import numpy as np

from plvo.config import LoopConfig, RegistrationConfig
from plvo.loop.closer import LoopCloser
from plvo.loop.scans import compact_scan, scan_points
from plvo.loop.verification import LoopKeyframe

K = np.array([[718.856, 0.0, 607.19], [0.0, 718.856, 185.2], [0.0, 0.0, 1.0]])


def _keyframe(kf_id: int, rng: np.random.Generator, scan: np.ndarray) -> LoopKeyframe:
    """A KITTI-sized keyframe: 1000 ORB points (40 % with depth), 150 segments (30 % with depth), the scan; 3 m
    further along a straight road than the keyframe before (as on KITTI at 36 km/h)."""
    n, m = 1000, 150
    pts = rng.uniform([-10, -2, 5], [10, 2, 40], (n, 3))
    pts[rng.random(n) > 0.4] = np.nan
    lines = rng.uniform(-10, 10, (m, 2, 3))
    lines[rng.random(m) > 0.3] = np.nan
    T = np.eye(4)
    T[2, 3] = 3.0 * kf_id
    return LoopKeyframe(kf_id, T, rng.uniform(0, 1200, (n, 2)), rng.integers(0, 256, (n, 32), np.uint8),
                        pts, rng.uniform(0, 1200, (m, 4)), rng.integers(0, 256, (m, 32), np.uint8), lines,
                        scan.astype(np.float32), 3 * kf_id)


def _bytes(kf: LoopKeyframe) -> int:
    return sum(np.asarray(getattr(kf, f)).nbytes for f in ("keypoints", "descriptors", "points_cam", "segments",
                                                           "line_descriptors", "lines_cam", "scan"))


def _town_scan(synth_seq) -> np.ndarray:
    """A scan of the synthetic town's HDL-64E model (KITTI's sensor, ~120k returns)."""
    return np.fromfile(synth_seq / "sequences" / "00" / "velodyne" / "000005.bin", np.float32).reshape(-1, 4)


def test_database_keeps_a_compact_copy_of_each_keyframe_on_disk(synth_seq):
    import tracemalloc

    from plvo.loop.lidar_place import RECENT_KEYFRAMES

    rng = np.random.default_rng(0)
    scan = _town_scan(synth_seq)
    closer = LoopCloser(K, cfg=LoopConfig(), reg_cfg=RegistrationConfig())
    raw = 0
    # past the local maps' window of recent scans (bounded, kept in memory), then 12 keyframes measured; traced from
    # the start, so that what the window lets go counts against what it takes in
    warm = RECENT_KEYFRAMES + 2
    frames = [_keyframe(k, rng, scan) for k in range(warm + 12)]
    tracemalloc.start()
    for kf in frames[:warm]:
        raw += _bytes(kf)
        closer.on_keyframe(kf)
    db = closer.detector.db
    index0 = db._points.nbytes() + db._lines.nbytes()
    before = tracemalloc.take_snapshot()
    for kf in frames[warm:]:
        closer.on_keyframe(kf)
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    # the inverted index is measured by its own arrays (its blocks merge by powers of two)
    beside_index = [tracemalloc.Filter(False, "*/loop/database.py"), tracemalloc.Filter(False, tracemalloc.__file__)]
    held = sum(d.size_diff for d in after.filter_traces(beside_index).compare_to(
        before.filter_traces(beside_index), "filename")) / 12
    index = (db._points.nbytes() + db._lines.nbytes() - index0) / 12
    kept = [closer.keyframe(k) for k in range(len(frames))]
    per_kf = sum(_bytes(kf) for kf in kept) / len(kept)
    # only features with depth, float32; the scan as int16 centimetres, cropped and thinned as registration uses it
    assert all(np.isfinite(kf.points_cam).all() and np.isfinite(kf.lines_cam).all() for kf in kept)
    assert all(kf.scan.dtype == np.int16 and kf.scan.shape[1] == 3 for kf in kept)
    assert per_kf < 0.1 * raw / warm, (per_kf, raw / warm)
    assert per_kf < 250_000, per_kf
    assert closer._kfs.bytes_on_disk >= len(frames) * per_kf
    # In memory a keyframe costs its words in the inverted index (~1150 words x 16 B) and a little bookkeeping
    # (pose, odometry, where its record is), not its features with depth (~25 kB) or its scan (~80 kB): on disk.
    assert index < 25_000 and held < 4_000, (held, index)
    # what is read back is what was kept: the query's features with depth, in float32
    first = frames[0]
    p = np.flatnonzero(np.isfinite(first.points_cam).all(axis=1))
    np.testing.assert_array_equal(kept[0].descriptors, first.descriptors[p])
    np.testing.assert_allclose(kept[0].points_cam, first.points_cam[p], rtol=1e-6)
    assert kept[0].frame_index == 0 and kept[3].frame_index == 9


def test_keyframe_store_reads_back_what_it_was_given_and_leaves_no_file(tmp_path):
    from plvo.loop.keyframe_store import FIELD_NAMES, KeyframeStore

    rng = np.random.default_rng(0)
    store = KeyframeStore(str(tmp_path))
    records = {}
    for k in range(20):
        n = int(rng.integers(0, 500))
        arrays = {f: rng.normal(size=(n, 3)).astype(np.float32) for f in FIELD_NAMES}
        arrays.update(T_world_cam=rng.normal(size=(4, 4)), keypoints=rng.normal(size=(n, 2)).astype(np.float32),
                      descriptors=rng.integers(0, 256, (n, 32), np.uint8), segments=np.zeros((0, 4), np.float32),
                      line_descriptors=np.zeros((0, 32), np.uint8), lines_cam=np.zeros((0, 2, 3), np.float32),
                      scan=None if k % 3 == 0 else rng.integers(-6000, 6000, (n, 3)).astype(np.int16))
        records[k] = arrays
        store.put(k, arrays, frame_index=3 * k)
    assert list(tmp_path.iterdir()) == []  # unlinked on open: a killed run leaves nothing behind
    for k in (7, 0, 19, 3):
        back, frame = store.get(k)
        assert frame == 3 * k
        for f in FIELD_NAMES:
            if records[k][f] is None:
                assert back[f] is None
            else:
                np.testing.assert_array_equal(back[f], records[k][f])
    assert store.get(99) is None and len(store) == 20
    store.close()


def test_compact_scan_keeps_the_returns_registration_uses_to_a_centimetre(synth_seq):
    scan = _town_scan(synth_seq)
    cfg = RegistrationConfig()
    back = scan_points(compact_scan(scan, cfg))
    r = np.linalg.norm(back, axis=1)
    assert back.dtype == np.float32 and r.min() >= cfg.min_range_m - 0.01 and r.max() <= cfg.max_range_m + 0.01
    # every kept point is one of the scan's returns, to the centimetre
    from scipy.spatial import cKDTree

    d, _ = cKDTree(scan[:, :3]).query(back)
    assert d.max() < 0.01

