"""The loop database keeps what a later verification needs, compactly: memory is O(kept), not O(frames read)."""

from __future__ import annotations

import dataclasses

import numpy as np

from plvo.config import LoopConfig, RegistrationConfig
from plvo.loop.closer import LoopCloser, compact_scan, scan_points
from plvo.loop.verification import LoopKeyframe

K = np.array([[718.856, 0.0, 607.19], [0.0, 718.856, 185.2], [0.0, 0.0, 1.0]])


def _keyframe(kf_id: int, rng: np.random.Generator, scan: np.ndarray) -> LoopKeyframe:
    """A KITTI-sized keyframe: 1000 ORB points (40 % with depth), 150 segments (30 % with depth), the scan."""
    n, m = 1000, 150
    pts = rng.uniform([-10, -2, 5], [10, 2, 40], (n, 3))
    pts[rng.random(n) > 0.4] = np.nan
    lines = rng.uniform(-10, 10, (m, 2, 3))
    lines[rng.random(m) > 0.3] = np.nan
    return LoopKeyframe(kf_id, np.eye(4), rng.uniform(0, 1200, (n, 2)), rng.integers(0, 256, (n, 32), np.uint8),
                        pts, rng.uniform(0, 1200, (m, 4)), rng.integers(0, 256, (m, 32), np.uint8), lines,
                        scan.astype(np.float32), 3 * kf_id)


def _bytes(kf: LoopKeyframe) -> int:
    return sum(np.asarray(getattr(kf, f)).nbytes for f in ("keypoints", "descriptors", "points_cam", "segments",
                                                           "line_descriptors", "lines_cam", "scan"))


def _town_scan(synth_seq) -> np.ndarray:
    """A scan of the synthetic town's HDL-64E model (KITTI's sensor, ~120k returns)."""
    return np.fromfile(synth_seq / "sequences" / "00" / "velodyne" / "000005.bin", np.float32).reshape(-1, 4)


def test_database_keeps_a_compact_copy_of_each_keyframe(synth_seq):
    rng = np.random.default_rng(0)
    scan = _town_scan(synth_seq)
    closer = LoopCloser(K, cfg=LoopConfig(), reg_cfg=RegistrationConfig())
    raw = 0
    for k in range(12):
        kf = _keyframe(k, rng, scan)
        raw += _bytes(kf)
        closer.on_keyframe(kf)
    in_memory = [closer._kfs[k] for k in range(12)]
    assert all(kf.scan is None for kf in in_memory)  # the scans are on disk (plvo.loop.scan_store)
    per_kf_ram = sum(_bytes(dataclasses.replace(kf, scan=np.zeros((0, 3)))) for kf in in_memory) / 12
    kept = [closer.keyframe(k) for k in range(12)]
    per_kf = sum(_bytes(kf) for kf in kept) / len(kept)
    # only features with depth, float32; the scan as int16 centimetres, cropped and thinned as registration uses it
    assert all(np.isfinite(kf.points_cam).all() and np.isfinite(kf.lines_cam).all() for kf in kept)
    assert all(kf.scan.dtype == np.int16 and kf.scan.shape[1] == 3 for kf in kept)
    assert per_kf < 0.1 * raw / 12, (per_kf, raw / 12)
    assert per_kf < 250_000, per_kf
    # in memory, a keyframe is its features with depth: 1500 keyframes (KITTI 00) keep < 50 MB
    assert per_kf_ram < 35_000, per_kf_ram
    assert closer._scans.bytes_on_disk == sum(kf.scan.nbytes for kf in kept)


def test_scan_store_reads_back_what_it_was_given_and_leaves_no_file(tmp_path):
    from plvo.loop.scan_store import ScanStore

    rng = np.random.default_rng(0)
    store = ScanStore(str(tmp_path))
    scans = {k: rng.integers(-6000, 6000, (int(rng.integers(0, 5000)), 3)).astype(np.int16) for k in range(20)}
    for k, s in scans.items():
        store.put(k, s)
    assert list(tmp_path.iterdir()) == []  # unlinked on open: a killed run leaves nothing behind
    for k in (7, 0, 19, 3):
        np.testing.assert_array_equal(store.get(k), scans[k])
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
