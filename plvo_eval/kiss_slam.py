"""KISS-SLAM (lidar only, with loop closure) as a comparison baseline, run on a Dataset's scans with the same frames
as plvo.

Uses kiss_slam's Python API (KissSLAM with the config its own pipeline loads without a file, `load_config(None)`)
directly, not its SlamPipeline, so that it reads scans through our datasets exactly as plvo_eval.kiss reads them for
KISS-ICP (`scan_reader`, the same checks, no KITTI scan correction). Nothing of its config is tuned but the thread
count of its odometry (0, all cores, unless the runner shares them out as for KISS-ICP).

KISS-SLAM runs KISS-ICP odometry within local maps, a new one each `local_mapper.splitting_distance` travelled (100 m
by default). A finished local map is matched by map_closures against the maps more than 3 before it; a candidate is
accepted when, after an ICP refinement, the maps overlap by more than `loop_closer.overlap_threshold` (0.4), and
then adds a factor to the pose graph of the local maps' key poses, which is optimised. The per-frame trajectory is
taken as its pipeline takes it at the end of a run: the last local map is closed (`generate_new_node`, itself a
closure query), the empty map that makes is erased, and `fine_grained_optimization` spreads the key poses over the
frames' odometry; so a closed loop shows in every frame's pose. Within one local map (a run under 100 m) the poses
are KISS-ICP's with the same settings; past that they differ a little even without a closure, as each new local map
takes over the odometry's map re-gridded in its own frame.

Deskew: KISS-SLAM's default odometry config deskews (`preprocessing.deskew = True`), as KISS-ICP's does. kiss_icp
deskews only with per-point timestamps (any unit: it normalises them to the scan's own min..max and moves each point
to the sweep's end with the last frame-to-frame motion); given an empty array, as kiss_icp's own KITTI loader
gives, it leaves the scan as it is. It gets the same timestamps as KISS-ICP (plvo_eval.kiss: where the source says
its scans are not motion-compensated, the data's or the azimuth's), unless `KissSlamOptions(deskew=False)`, and its
poses of deskewed scans are taken from the sweep's end to the frame's time as KISS-ICP's are. On raw sweeps the
evaluation runs it both ways, as KISS-ICP, and reports the one closer to the truth (`both_ways`, plvo_eval.tasks).

KISS-SLAM prints its progress ("KissSLAM| Closure Detected", ...) to stdout and its pose-graph optimiser (g2o, in
C++) its iterations to stderr; both are captured at the file descriptors around its calls and logged at debug level
instead, so that our output stays ours (exceptions pass through).

Poses are turned into cam0 poses through the calibration as in plvo_eval.kiss (`lidar_to_cam0`).
"""

from __future__ import annotations

import contextlib
import ctypes
import io
import logging
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from plvo.data.dataset import Dataset
from plvo.errors import PlvoError
from plvo_eval.kiss import _scan_points, kitti_corrector, lidar_to_cam0, sweep_end_to_frame_time, timed_scan_reader

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class KissSlamOptions:
    """KISS-SLAM settings beyond its own defaults: the odometry's threads (0 = all cores; the runner gives each of
    its workers a share, as for KISS-ICP); deskew: give it the scans' timestamps where they need them (as KISS-ICP);
    both_ways: where the data allow two readings, the evaluation runs each and reports the one closer to the truth
    (as KissOptions.both_ways); kitti_correction: kiss_icp's KITTI scan correction applied to every scan (as
    KissOptions.kitti_correction)."""

    max_threads: int = 0
    deskew: bool = True
    both_ways: bool = True
    kitti_correction: bool = False


@dataclass(frozen=True)
class LoopClosure:
    """An accepted closure between two local maps: the reference (earlier) and query map ids and the frames (positions
    in the dataset, first..last inclusive) each map spans."""

    reference_map: int
    query_map: int
    reference_frames: tuple[int, int]
    query_frames: tuple[int, int]


@dataclass(frozen=True)
class KissSlamOutput:
    """poses: (N,4,4) T_world_cam of cam0, world = cam0 of the first frame, the final optimised trajectory;
    lidar_poses: (N,4,4) T_lidar0_lidar, the same; seconds: (N,) time of each frame's `process_scan` (without
    reading the scan; a frame that closes a local map includes the closure query and any optimisation);
    finalize_s: closing the last local map and the per-frame optimisation; closures: the accepted loop closures;
    n_local_maps: local maps at the end; started_at, finished_at: time.perf_counter() before the first scan was read
    and after the final trajectory was computed (imports and construction before, the cam0 conversion after)."""

    poses: np.ndarray
    lidar_poses: np.ndarray
    seconds: np.ndarray
    finalize_s: float
    closures: tuple[LoopClosure, ...] = field(default_factory=tuple)
    n_local_maps: int = 0
    started_at: float = 0.0
    finished_at: float = 0.0

    @property
    def wall_s(self) -> float:
        return self.finished_at - self.started_at

    @property
    def n_closures(self) -> int:
        return len(self.closures)


def make_config(options: KissSlamOptions) -> Any:
    """KissSlamOptions -> KISS-SLAM's default config (as its pipeline loads it without a file: the odometry voxel
    from max_range / 100) with the odometry's thread count set."""
    from kiss_slam.config import load_config

    config = load_config(None)
    config.odometry.registration.max_num_threads = int(options.max_threads)
    return config


def _flush_c_streams() -> None:
    """Flush the C library's stdio buffers (what C++ code wrote to std::cout but stdio still holds)."""
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):  # no C library to ask: nothing buffered that we could flush
        pass


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Capture what KISS-SLAM writes to stdout and stderr (its Python prints, g2o's optimiser iterations from C++)
    and log it at debug level, also when the call raises; the exception itself passes through."""
    sys.stdout.flush()
    sys.stderr.flush()
    _flush_c_streams()
    python_out = io.StringIO()
    with tempfile.TemporaryFile() as sink:
        saved: list[tuple[int, int]] = []
        try:
            for fd in (1, 2):
                try:
                    saved.append((fd, os.dup(fd)))
                except OSError:  # that descriptor is closed: nothing could be printed on it anyway
                    continue
                os.dup2(sink.fileno(), fd)
            with contextlib.redirect_stdout(python_out):
                yield
        finally:
            _flush_c_streams()
            for fd, copy in saved:
                os.dup2(copy, fd)
                os.close(copy)
            sink.seek(0)
            text = python_out.getvalue() + sink.read().decode(errors="replace")
            for line in text.splitlines():
                if line.strip():
                    log.debug("KISS-SLAM: %s", line.strip())


def frame_poses(slam: Any) -> tuple[np.ndarray, dict[int, tuple[int, int]]]:
    """A KissSLAM after its last scan -> (N,4,4) per-frame poses T_lidar0_lidar and local map id -> (first, last)
    frame, finishing the run as kiss_slam's SlamPipeline does (this changes `slam`: call it once)."""
    slam.generate_new_node()
    slam.local_map_graph.erase_last_local_map()
    spans = {}
    first = 0
    for node in slam.local_map_graph.local_maps():
        # map 0's trajectory starts at frame 0; a later map's starts at the previous map's last frame, shared
        last = first + len(node.local_trajectory) - 1
        spans[int(node.id)] = (first, last)
        first = last
    if first == 0:
        # one frame: its pose is the graph's fixed origin, and fine_grained_optimization would fix variable -1,
        # which does not exist (g2o then ends the process with a segmentation fault)
        return np.eye(4)[None], spans
    estimates, _graph = slam.fine_grained_optimization()
    return np.asarray(estimates, dtype=np.float64), spans


def run_kiss_slam(dataset: Dataset, options: KissSlamOptions | None = None) -> KissSlamOutput:
    """Dataset's scans -> KISS-SLAM's final poses (N,4,4) T_world_cam of cam0, world = cam0 of the first frame, and
    the loop closures it accepted."""
    with _quiet():
        from kiss_slam.slam import KissSLAM

    options = options or KissSlamOptions()
    if len(dataset) == 0:
        raise PlvoError(f"sequence {dataset.sequence}: no frames for KISS-SLAM")
    with _quiet():
        slam = KissSLAM(make_config(options))
    seconds = np.zeros(len(dataset))
    no_times = np.zeros(0)  # kiss_icp leaves a scan without timestamps as it is
    read = timed_scan_reader(dataset)
    correct = kitti_corrector() if options.kitti_correction else None
    back = np.tile(np.eye(4), (len(dataset), 1, 1))  # as KISS-ICP's (plvo_eval.kiss.sweep_end_to_frame_time)
    started_at = time.perf_counter()
    for i in range(len(dataset)):
        scan, times = read(i)
        points = _scan_points(dataset, scan, i, correct)
        stamps = times if options.deskew and times is not None else no_times
        back[i] = sweep_end_to_frame_time(stamps, slam.odometry.last_delta)
        with _quiet():
            t0 = time.perf_counter()
            slam.process_scan(points, stamps)
            seconds[i] = time.perf_counter() - t0
    t0 = time.perf_counter()
    with _quiet():
        lidar_poses, spans = frame_poses(slam)
    finished_at = time.perf_counter()
    if lidar_poses.shape != (len(dataset), 4, 4):
        raise PlvoError(f"sequence {dataset.sequence}: KISS-SLAM gave {len(lidar_poses)} poses for {len(dataset)} "
                        "frames")
    closures = tuple(LoopClosure(int(ref), int(query), spans[int(ref)], spans[int(query)])
                     for ref, query in slam.get_closures())
    calib = dataset.calib
    T_cam0_velo = np.asarray(calib.T_cam0_cam) @ np.asarray(calib.T_cam_velo)
    lidar_poses = lidar_poses @ back  # deskewed scans' poses at the sweep's end -> at the frame's time
    poses = lidar_to_cam0(lidar_poses, T_cam0_velo)
    # the first frame's pose is the fixed identity of the graph; re-anchor anyway, as for KISS-ICP
    poses = np.linalg.inv(poses[0]) @ poses
    log.info("KISS-SLAM on %s: %d frames, %.1f ms a frame, %d local maps, %d loop closures", dataset.sequence,
             len(dataset), 1e3 * seconds.mean(), len(spans), len(closures))
    return KissSlamOutput(poses=poses, lidar_poses=lidar_poses, seconds=seconds, finalize_s=finished_at - t0,
                          closures=closures, n_local_maps=len(spans), started_at=started_at, finished_at=finished_at)
