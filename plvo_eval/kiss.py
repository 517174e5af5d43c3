"""KISS-ICP (lidar only) as a comparison baseline, run on a Dataset's scans with the same frames as plvo.

Uses kiss_icp's Python pipeline API (KissICP + KISSConfig) directly, not its OdometryPipeline, so that it reads
scans through our datasets (any layout the registry opens, any frame selection). Defaults follow the figure in
shared/data/README.md: voxel 1.0 m, and without kiss_icp's KITTI vertical-angle scan correction, which its own KITTI
loader applies (measured on the 51 real frames: without it 0.74/0.63/0.55 % over 10/20/40 m, the reference; with
it 0.77/0.67/0.61 %).

Deskew: KISS-ICP's own default (`data.deskew = True`), which deskews a scan given its returns' timestamps and
leaves it as it is without them. It gets them where the source says its scans are raw sweeps, not
motion-compensated (the twins, a KITTI raw drive, a bag's sweep with per-point times: `Frame.scan_compensated`), as
its own ROS loader reads them from such a bag: the data's per-return times (a bag's fields; a raw drive's azimuth
over its recorded sweep), else each return's azimuth time (plvo.lidar.deskew.azimuth_times), the same times plvo
deskews with. KITTI's odometry scans are compensated and get none, as kiss_icp's KITTI loader gives none.
`KissOptions(deskew=False)` runs it on the raw sweeps instead; on raw sweeps the evaluation runs it both ways and
reports the one closer to the truth (`both_ways`, plvo_eval.tasks), as deskewing does not help it everywhere: on
KITTI's raw drive 0009 (frames 0-50) deskewed it gets 2.99 / 2.74 / 2.61 % over 10 / 20 / 40 m (1.32 / 0.90 / 0.50
with the truth's heading offset taken out), not deskewed 2.90 / 2.72 / 2.62 % (1.27 / 0.89 / 0.48).

kiss_icp moves a deskewed scan to its sweep's *end* (the last timestamp) with the motion it predicts (its last
frame-to-frame delta), so its pose of that scan is the sensor's at the sweep's end, half a frame after the frame's
time where the ground truth and plvo put it (0.7 m further along at 14 m/s; on a 20-frame twin starting from
standstill it made the path 4.8 % too long). `sweep_end_to_frame_time` takes each such pose back to the frame's time
along that same predicted motion.

KISS-ICP estimates lidar poses T_lidar0_lidar; they are turned into cam0 poses through the calibration,
T_cam0_cam0i = T_cam0_velo @ T_lidar0_lidari @ T_velo_cam0, as kiss_icp's apply_calibration does.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from plvo.data.dataset import Dataset
from plvo.errors import DatasetError, PlvoError
from plvo.geometry import se3
from plvo.lidar.deskew import azimuth_times
from plvo.types import Frame

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class KissOptions:
    """KISS-ICP settings: voxel size (m), max/min range (m), deskew (with the scans' timestamps where they need it,
    see the module doc), kiss_icp's KITTI scan correction, threads (0 = all cores; the runner gives each of its
    workers a share); both_ways: where the data allow two readings (raw sweeps: deskewed or not; a lidar with
    KITTI's elevation error: kiss_icp's correction or not), the evaluation (plvo_eval.tasks) runs each and reports
    the one closer to the truth (run_kiss itself makes one run, as `deskew` and `kitti_correction` say)."""

    voxel_size_m: float = 1.0
    max_range_m: float = 100.0
    min_range_m: float = 0.0
    deskew: bool = True
    kitti_correction: bool = False
    max_threads: int = 0
    both_ways: bool = True


@dataclass(frozen=True)
class KissOutput:
    """poses: (N,4,4) T_world_cam of cam0, world = cam0 of the first frame; lidar_poses: (N,4,4) T_lidar0_lidar;
    seconds: (N,) registration time a frame (without reading the scan); started_at, finished_at: time.perf_counter()
    before the first scan was read and after the last was registered (kiss_icp's import and the pipeline's
    construction are before started_at, the poses' conversion after finished_at)."""

    poses: np.ndarray
    lidar_poses: np.ndarray
    seconds: np.ndarray
    started_at: float = 0.0
    finished_at: float = 0.0

    @property
    def wall_s(self) -> float:
        return self.finished_at - self.started_at


def make_config(options: KissOptions) -> Any:
    """KissOptions -> kiss_icp KISSConfig."""
    from kiss_icp.config import KISSConfig

    config = KISSConfig()
    config.mapping.voxel_size = float(options.voxel_size_m)
    config.data.max_range = float(options.max_range_m)
    config.data.min_range = float(options.min_range_m)
    config.data.deskew = bool(options.deskew)
    config.registration.max_num_threads = int(options.max_threads)
    return config


def scan_reader(dataset: Dataset) -> Callable[[int], np.ndarray]:
    """i -> the scan (N,4) of position i, read from disk alone where the dataset can (KITTI's `load_scan`): a
    lidar-only method has no use for the camera image that `dataset[i]` decodes too (on 04: 5.7-7.8 ms a frame
    read whole against 1.7 ms for the scan alone, beside KISS-ICP's ~66 ms); other datasets give the frame's scan."""
    read = timed_scan_reader(dataset)
    return lambda i: read(i)[0]


def timed_scan_reader(dataset: Dataset) -> Callable[[int], tuple[np.ndarray, np.ndarray | None]]:
    """i -> (scan (N,4), its returns' times (N,) in seconds after the frame's time, or None where the source says
    its scans are motion-compensated), read as `scan_reader` reads (the scan alone where the dataset can, with the
    times it records: `load_timed_scan`)."""
    compensated = bool(getattr(dataset, "scans_compensated", True))
    load_timed_scan = getattr(dataset, "load_timed_scan", None)
    if callable(load_timed_scan):
        def read(i: int) -> tuple[np.ndarray, np.ndarray | None]:
            scan, times = load_timed_scan(i)
            return _with_times(scan, times, compensated)

        return read
    load_scan = getattr(dataset, "load_scan", None)
    if callable(load_scan):
        return lambda i: _with_times(load_scan(i), None, compensated)
    return lambda i: _frame_scan(dataset[i])


def raw_sweeps(dataset: Dataset) -> bool:
    """Whether a dataset's scans are raw sweeps (each return at its own time), as the peers read them: the
    dataset's `scans_compensated` where it says, else its first frame's."""
    if hasattr(dataset, "scans_compensated"):
        return not dataset.scans_compensated
    return len(dataset) > 0 and timed_scan_reader(dataset)(0)[1] is not None


def _frame_scan(frame: Frame) -> tuple[np.ndarray, np.ndarray | None]:
    return _with_times(frame.scan, frame.scan_time, frame.scan_compensated)


def _with_times(scan: np.ndarray, times: np.ndarray | None, compensated: bool) -> tuple[np.ndarray, np.ndarray | None]:
    if compensated:
        return scan, None
    return scan, (azimuth_times(scan) if times is None else np.asarray(times, np.float64))


def _scan_points(dataset: Dataset, scan: np.ndarray, i: int,
                 correct: Callable[[np.ndarray], np.ndarray] | None) -> np.ndarray:
    scan = np.asarray(scan)
    frame = dataset.frame_indices[i]
    if scan.ndim != 2 or scan.shape[1] < 3:
        raise DatasetError(f"sequence {dataset.sequence}, frame {frame}: scan must be (N,4), got {scan.shape}")
    points = scan[:, :3].astype(np.float64)
    if not np.all(np.isfinite(points)):
        raise DatasetError(f"sequence {dataset.sequence}, frame {frame}: scan has NaN or infinite points")
    return correct(points) if correct is not None else points


def sweep_end_to_frame_time(stamps: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """A scan's timestamps (s after the frame's time; empty: not deskewed) and the motion (4,4) kiss_icp deskews it
    with -> T_end_frame (4,4), which takes its pose of the deskewed scan (the sensor at the last timestamp) to the
    frame's time: kiss_icp puts a return of normalised time s at exp((s - 1) log delta) from the sweep's end, and the
    frame's time has s0 = -min / (max - min)."""
    if len(stamps) == 0:
        return np.eye(4)
    lo, hi = float(np.min(stamps)), float(np.max(stamps))
    if not hi > lo:
        return np.eye(4)
    s0 = (0.0 - lo) / (hi - lo)
    return se3.exp((s0 - 1.0) * se3.log(np.asarray(delta, float)))


def lidar_to_cam0(lidar_poses: np.ndarray, T_cam0_velo: np.ndarray) -> np.ndarray:
    """(N,4,4) T_lidar0_lidar -> (N,4,4) T_cam0_cam (cam0 of the first frame as the world)."""
    return T_cam0_velo @ lidar_poses @ np.linalg.inv(T_cam0_velo)


def kitti_corrector() -> Callable[[np.ndarray], np.ndarray]:
    """kiss_icp's own KITTI scan correction (every return raised by its vertical-angle error), as a function of an
    (N,3) array, for KISS-ICP and KISS-SLAM alike."""
    from kiss_icp.pybind import kiss_icp_pybind

    def correct(points: np.ndarray) -> np.ndarray:
        return np.asarray(kiss_icp_pybind._correct_kitti_scan(kiss_icp_pybind._Vector3dVector(points)))

    return correct


def elevation_error(dataset: Dataset) -> bool:
    """Whether a dataset's lidar carries KITTI's vertical-angle error (real KITTI, realistic twins): kiss_icp's
    KITTI correction then applies to it."""
    calib = getattr(dataset, "calib", None)
    return float(getattr(calib, "lidar_elevation_offset_deg", 0.0) or 0.0) != 0.0


def run_kiss(dataset: Dataset, options: KissOptions | None = None) -> KissOutput:
    """Dataset's scans -> KISS-ICP poses (N,4,4) T_world_cam of cam0, world = cam0 of the dataset's first frame."""
    from kiss_icp.kiss_icp import KissICP

    options = options or KissOptions()
    if len(dataset) == 0:
        raise PlvoError(f"sequence {dataset.sequence}: no frames for KISS-ICP")
    correct = kitti_corrector() if options.kitti_correction else None

    odometry = KissICP(config=make_config(options))
    lidar_poses = np.zeros((len(dataset), 4, 4))
    seconds = np.zeros(len(dataset))
    no_times = np.zeros(0)  # kiss_icp leaves a scan without timestamps as it is
    read = timed_scan_reader(dataset)
    started_at = time.perf_counter()
    back = np.tile(np.eye(4), (len(dataset), 1, 1))  # each pose's way back from its sweep's end to the frame's time
    for i in range(len(dataset)):
        scan, times = read(i)
        points = _scan_points(dataset, scan, i, correct)
        stamps = times if options.deskew and times is not None else no_times
        back[i] = sweep_end_to_frame_time(stamps, odometry.last_delta)
        t0 = time.perf_counter()
        odometry.register_frame(points, stamps)
        seconds[i] = time.perf_counter() - t0
        lidar_poses[i] = odometry.last_pose
    finished_at = time.perf_counter()
    lidar_poses = lidar_poses @ back
    calib = dataset.calib
    T_cam0_velo = np.asarray(calib.T_cam0_cam) @ np.asarray(calib.T_cam_velo)
    poses = lidar_to_cam0(lidar_poses, T_cam0_velo)
    # the first registration aligns to an empty map and returns its initial guess (identity); re-anchor anyway
    poses = np.linalg.inv(poses[0]) @ poses
    log.info("KISS-ICP on %s: %d frames, %.1f ms a frame", dataset.sequence, len(dataset), 1e3 * seconds.mean())
    return KissOutput(poses=poses, lidar_poses=lidar_poses, seconds=seconds, started_at=started_at,
                      finished_at=finished_at)
