"""A whole run of the System over a dataset: every frame read ahead and stepped, the workers finished, the cam0
poses of every frame."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from plvo.config import SystemConfig
from plvo.recording import Recorder
from plvo.results import EdgeKind, StageSteps
from plvo.runtime.system import System

if TYPE_CHECKING:
    from plvo.data.dataset import Dataset


@dataclass(frozen=True)
class RunOutput:
    """A whole run: poses (N,4,4) T_world_cam0 of the frames in order, per-stage timings (seconds per run)."""

    frame_indices: tuple[int, ...]
    poses: np.ndarray
    timings: dict[str, list[float]]
    n_keyframes: int
    n_lost: int
    finished_at: float = 0.0  # time.perf_counter() once the workers' last results were applied (before closing)
    stage_steps: tuple[StageSteps, ...] = ()  # the back end's stage record, one a result (plvo_eval.stage_drift)
    # the frame of each keyframe (by id) and the accepted loops as the map keeps them: (match keyframe, query
    # keyframe, T_match_query (4,4) of the tracked camera) (plvo_eval.revisits judges them against ground truth)
    keyframe_frames: tuple[int, ...] = ()
    loop_edges: tuple[tuple[int, int, np.ndarray], ...] = ()
    trust: dict = field(default_factory=dict)  # System.trust_summary(): where each frame's pose came from


def run_dataset(dataset: Dataset, config: SystemConfig, recorder: Recorder | None = None,
                progress: Callable[[int], object] | None = None) -> RunOutput:
    """Run the whole pipeline over a Dataset -> RunOutput with cam0 poses of every frame (KITTI convention).

    progress: an optional callable taking the number of frames done (e.g. a tqdm bar's update).
    """
    return run_system(System(config, recorder, calib=dataset.calib), dataset, progress)


def step_through(system: System, dataset: Dataset, progress: Callable[[int], object] | None = None,
                 at: list[int] | None = None) -> None:
    """Step `system` (made for this dataset, not yet stepped) through every frame, each read while the one before
    is tracked, then let its workers finish (the System stays open). When the frames show that the run's config is
    wrong in a way a restart mends (System.restart_wanted: a camera-lidar time offset or a gross extrinsic error
    found), the System starts again from the first frame with the mended config, once; the frames so far count for
    nothing.

    progress: called with the number of frames done (1 a frame; minus the frames dropped at a restart: a tqdm
    bar's update); at: holds the index of the frame being stepped (what an error names). System.restarts says
    why and where a run started again."""
    while True:
        frames = system.read_ahead(dataset)
        try:
            for frame in frames:
                if at is not None:
                    at[0] = frame.index
                system.step(frame)
                if progress is not None:
                    progress(1)
                config = system.restart_wanted
                if config is not None:
                    break
            else:
                break
        finally:
            frames.close()  # the reading thread stops
        if progress is not None:
            progress(-system.frames_done)
        system.restart(config)
    system.finish()


def run_system(system: System, dataset: Any, progress: Callable[[int], object] | None = None) -> RunOutput:
    """Step `system` (made for this dataset, not yet stepped) through every frame (step_through), let its workers
    finish, and close it -> RunOutput."""
    try:
        step_through(system, dataset, progress)
        finished_at = time.perf_counter()
        poses = system.poses_cam0(dataset.frame_indices)
    finally:
        system.close()
    m = system.map
    kf_frames = () if m is None else tuple(m.keyframe_frame(k) for k in range(m.n_keyframes))
    loops = () if m is None else tuple((e.i, e.j, e.T_i_j) for e in m.edges if e.kind == EdgeKind.LOOP)
    return RunOutput(tuple(dataset.frame_indices), poses, dict(system.timings), m.n_keyframes if m is not None else 0,
                     system.n_lost, finished_at, tuple(system.record.stage_steps), kf_frames, loops,
                     system.trust_summary())
