"""KISS-ICP (lidar only) as a comparison baseline, run on a Dataset's scans with the same frames as plvo.

Uses kiss_icp's Python pipeline API (KissICP + KISSConfig) directly, not its OdometryPipeline, so that it reads
scans through our datasets (any layout the registry opens, any frame selection). Defaults follow the figure in
shared/data/README.md: voxel 1.0 m, no deskew (KITTI odometry scans are already motion compensated), and
without kiss_icp's KITTI vertical-angle scan correction, which its own KITTI loader applies (measured on the 51
real frames: without it 0.74/0.63/0.55 % over 10/20/40 m, the reference; with it 0.77/0.67/0.61 %).

KISS-ICP estimates lidar poses T_lidar0_lidar; they are turned into cam0 poses through the calibration,
T_cam0_cam0i = T_cam0_velo @ T_lidar0_lidari @ T_velo_cam0, as kiss_icp's apply_calibration does.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from plvo.data.dataset import Dataset
from plvo.errors import DatasetError, PlvoError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class KissOptions:
    """KISS-ICP settings: voxel size (m), max/min range (m), deskew, kiss_icp's KITTI scan correction, threads
    (0 = all cores; the runner gives each of its workers a share)."""

    voxel_size_m: float = 1.0
    max_range_m: float = 100.0
    min_range_m: float = 0.0
    deskew: bool = False
    kitti_correction: bool = False
    max_threads: int = 0


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


def make_config(options: KissOptions):
    """KissOptions -> kiss_icp KISSConfig."""
    from kiss_icp.config import KISSConfig

    config = KISSConfig()
    config.mapping.voxel_size = float(options.voxel_size_m)
    config.data.max_range = float(options.max_range_m)
    config.data.min_range = float(options.min_range_m)
    config.data.deskew = bool(options.deskew)
    config.registration.max_num_threads = int(options.max_threads)
    return config


def scan_reader(dataset: Dataset):
    """i -> the scan (N,4) of position i, read from disk alone where the dataset can (KITTI's `load_scan`): a
    lidar-only method has no use for the camera image that `dataset[i]` decodes too (on 04: 5.7-7.8 ms a frame
    read whole against 1.7 ms for the scan alone, beside KISS-ICP's ~66 ms); other datasets give the frame's scan."""
    load_scan = getattr(dataset, "load_scan", None)
    if callable(load_scan):
        return load_scan
    return lambda i: dataset[i].scan


def _scan_points(dataset: Dataset, read, i: int, correct) -> np.ndarray:
    scan = np.asarray(read(i))
    frame = dataset.frame_indices[i]
    if scan.ndim != 2 or scan.shape[1] < 3:
        raise DatasetError(f"sequence {dataset.sequence}, frame {frame}: scan must be (N,4), got {scan.shape}")
    points = scan[:, :3].astype(np.float64)
    if not np.all(np.isfinite(points)):
        raise DatasetError(f"sequence {dataset.sequence}, frame {frame}: scan has NaN or infinite points")
    return correct(points) if correct is not None else points


def lidar_to_cam0(lidar_poses: np.ndarray, T_cam0_velo: np.ndarray) -> np.ndarray:
    """(N,4,4) T_lidar0_lidar -> (N,4,4) T_cam0_cam (cam0 of the first frame as the world)."""
    return T_cam0_velo @ lidar_poses @ np.linalg.inv(T_cam0_velo)


def run_kiss(dataset: Dataset, options: KissOptions | None = None) -> KissOutput:
    """Dataset's scans -> KISS-ICP poses (N,4,4) T_world_cam of cam0, world = cam0 of the dataset's first frame."""
    from kiss_icp.kiss_icp import KissICP
    from kiss_icp.pybind import kiss_icp_pybind

    options = options or KissOptions()
    if len(dataset) == 0:
        raise PlvoError(f"sequence {dataset.sequence}: no frames for KISS-ICP")
    correct = None
    if options.kitti_correction:
        def correct(points: np.ndarray) -> np.ndarray:
            return np.asarray(kiss_icp_pybind._correct_kitti_scan(kiss_icp_pybind._Vector3dVector(points)))

    odometry = KissICP(config=make_config(options))
    lidar_poses = np.zeros((len(dataset), 4, 4))
    seconds = np.zeros(len(dataset))
    no_times = np.zeros(0)  # without deskew the per-point timestamps are unused
    read = scan_reader(dataset)
    started_at = time.perf_counter()
    for i in range(len(dataset)):
        points = _scan_points(dataset, read, i, correct)
        t0 = time.perf_counter()
        odometry.register_frame(points, no_times)
        seconds[i] = time.perf_counter() - t0
        lidar_poses[i] = odometry.last_pose
    finished_at = time.perf_counter()
    calib = dataset.calib
    T_cam0_velo = np.asarray(calib.T_cam0_cam) @ np.asarray(calib.T_cam_velo)
    poses = lidar_to_cam0(lidar_poses, T_cam0_velo)
    # the first registration aligns to an empty map and returns its initial guess (identity); re-anchor anyway
    poses = np.linalg.inv(poses[0]) @ poses
    log.info("KISS-ICP on %s: %d frames, %.1f ms a frame", dataset.sequence, len(dataset), 1e3 * seconds.mean())
    return KissOutput(poses=poses, lidar_poses=lidar_poses, seconds=seconds, started_at=started_at,
                      finished_at=finished_at)
