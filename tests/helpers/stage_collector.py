"""A recorder keeping what the loop-closure tests of the whole System look at (loops, keyframes' frames, lost
frames, pose graphs, the tracker's poses)."""

from __future__ import annotations

import numpy as np

from plvo.results import GraphResult, KeyframeResult, LoopResult, TrackingResult


class Collect:
    """Recorder keeping what the tests look at."""

    def __init__(self) -> None:
        self.loops: list[LoopResult] = []
        self.kf_frame: dict[int, int] = {}
        self.lost: list[int] = []
        self.graphs: list[GraphResult] = []
        self.tracked: dict[int, np.ndarray] = {}  # frame -> the tracker's pose when it was tracked

    def on_run_start(self, info) -> None:
        pass

    def on_frame(self, frame) -> None:
        pass

    def on_stage(self, frame_index: int, result) -> None:
        if isinstance(result, LoopResult):
            self.loops.append(result)
        elif isinstance(result, KeyframeResult):
            self.kf_frame[result.keyframe_id] = result.frame_index
        elif isinstance(result, GraphResult):
            self.graphs.append(result)
        elif isinstance(result, TrackingResult):
            self.tracked[frame_index] = np.asarray(result.T_world_cam)
            if not result.ok:
                self.lost.append(frame_index)

    def close(self) -> None:
        pass
