"""A real KITTI raw drive read as raw sweeps: each return's time spans the sweep its velodyne timestamps give, zero
facing forward; plvo deskews the keyframes' scans with those times and the tracker's motion; the peers get the same
times. Reads ../shared/data/kitti_raw (drive 2011_09_26_drive_0009) and skips with a reason when it is absent."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from plvo.config import SystemConfig, merge
from plvo.data.kitti import KittiRaw
from plvo.lidar.deskew import Sweep, needs_deskew
from plvo_eval.kiss import raw_sweeps, timed_scan_reader

RAW_ROOT = Path(__file__).resolve().parents[4] / "shared" / "data" / "kitti_raw"
DRIVE = "2011_09_26_drive_0009"
VELODYNE = RAW_ROOT / "2011_09_26" / f"{DRIVE}_sync" / "velodyne_points"


@pytest.fixture(scope="module")
def raw_root() -> Path:
    if not (VELODYNE / "timestamps.txt").is_file():
        pytest.skip(f"real KITTI raw drive not found at {VELODYNE.parent} (see ../shared/data/README.md)")
    return RAW_ROOT


def _stamps_ns(name: str) -> np.ndarray:
    """The first 51 lines of a velodyne timestamps file -> (51,) int64 nanoseconds."""
    return np.array([np.datetime64(line.strip().replace(" ", "T"), "ns").astype(np.int64)
                     for line in (VELODYNE / name).read_text().splitlines()[:51]])


def test_real_returns_span_the_sweep_their_timestamps_give(raw_root):
    start, forward, end = (1e-9 * (_stamps_ns(n) - _stamps_ns("timestamps.txt")[0]).astype(np.float64)
                           for n in ("timestamps_start.txt", "timestamps.txt", "timestamps_end.txt"))
    ds = KittiRaw(raw_root, DRIVE, frames=slice(0, 40, 13))
    np.testing.assert_allclose(ds.times, forward[[0, 13, 26, 39]], atol=1e-9)
    for i, k in enumerate(ds.frame_indices):
        frame = ds[i]
        sweep = end[k] - start[k]
        assert 0.101 < sweep < 0.106  # the HDL-64E's real spin, not a nominal 0.1 s
        assert not frame.scan_compensated and frame.scan_time is not None
        t = frame.scan_time
        # the returns fill the turn but for the lidar's own blind spots: their times span 99-100 % of the sweep
        assert 0.99 * sweep < np.ptp(t) <= sweep + 1e-9, (k, np.ptp(t), sweep)
        assert t.min() >= start[k] - forward[k] - 1e-9 and t.max() <= end[k] - forward[k] + 1e-9
        azimuth = np.degrees(np.arctan2(frame.scan[:, 1], frame.scan[:, 0]))
        ahead, left = np.abs(azimuth) < 0.05, np.abs(azimuth - 90.0) < 0.05
        assert ahead.sum() > 20 and np.abs(t[ahead]).max() < 0.05 / 360 * sweep + 1e-7  # zero facing forward
        assert np.median(t[left]) == pytest.approx(-sweep / 4, abs=1e-4)  # clockwise: the left before forward


def test_peers_read_the_raw_drive_with_the_same_times(raw_root):
    ds = KittiRaw(raw_root, DRIVE, frames=slice(5, 7))
    assert raw_sweeps(ds)
    read = timed_scan_reader(ds)
    for i in range(len(ds)):
        scan, times = read(i)
        frame = ds[i]
        np.testing.assert_array_equal(scan, frame.scan)
        np.testing.assert_array_equal(times, frame.scan_time)


def test_plvo_deskews_a_raw_drive_with_its_times_and_the_tracked_motion(raw_root, monkeypatch):
    """registration.deskew = "auto" (the default) deskews every keyframe's scan of a raw drive before registration:
    with the loader's return times and the tracker's motion either side of the frame, at the truth's speed."""
    from plvo.runtime.run import run_dataset

    ds = KittiRaw(raw_root, DRIVE, frames=slice(0, 5))
    assert SystemConfig().registration.deskew == "auto" and needs_deskew(ds[0], "auto")
    applied: list[tuple[Sweep, np.ndarray]] = []
    apply = Sweep.apply

    def spy(self: Sweep, scan: np.ndarray) -> np.ndarray:
        out = apply(self, scan)
        applied.append((self, np.linalg.norm(out[:, :3] - scan[:, :3], axis=1)))
        return out

    monkeypatch.setattr(Sweep, "apply", spy)
    out = run_dataset(ds, merge(SystemConfig(), {"backend": {"concurrent": False}}))
    assert out.keyframe_frames == (0, 3)
    # the registration's (the motion after the frame known) and the depth priors' (frontend.prior_scan: the returns
    # ahead, with the motion before the frame only; none at frame 0, where there is no motion before it)
    registered = [a for a in applied if a[0].after is not None]
    priors = [a for a in applied if a[0].after is None]
    assert len(registered) == 2 and len(priors) == 1  # each keyframe's scan once for both workers
    ahead = ds[3].scan[:, 0] > 0.0
    np.testing.assert_array_equal(priors[0][0].times, ds[3].scan_time[ahead])
    gt = ds.gt_T_world_cam
    speed = np.linalg.norm(gt[4, :3, 3] - gt[0, :3, 3]) / (ds.times[4] - ds.times[0])  # 10.6 m/s
    assert np.linalg.norm(priors[0][0].before[:3]) == pytest.approx(speed, rel=0.1)
    first, second = registered
    assert first[0].before is None and first[0].after is not None  # frame 0: only the motion after it is known
    sweep, moved = second
    assert sweep.before is not None and sweep.after is not None
    np.testing.assert_array_equal(sweep.times, ds[3].scan_time)
    for twist in (sweep.before, sweep.after):
        assert np.linalg.norm(twist[:3]) == pytest.approx(speed, rel=0.1)
    # the returns behind, taken half a sweep from the frame's time, move by about half a sweep's travel
    assert np.percentile(moved, 99.9) == pytest.approx(speed * 0.1035 / 2, rel=0.1)
