"""Every frame's pose, kept relative to the keyframe it was tracked from: the back end and the loop closer move
keyframes after the tracker has passed them, and composing with the keyframe's current pose carries every
refinement into the reported trajectory (as ORB-SLAM2 reports its trajectory)."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from plvo.geometry import se3
from plvo.tracking.frontend import FrontendResult
from plvo.tracking.map import LandmarkMap
from plvo.types import Calibration


class FramePoses:
    def __init__(self) -> None:
        self._ref: dict[int, tuple[int, np.ndarray]] = {}  # frame -> (keyframe id, T_kf_cam)
        self._kf = -1

    def add(self, frame_index: int, res: FrontendResult, map_: LandmarkMap) -> None:
        """The frame's tracked pose relative to its reference keyframe, taken before inline workers move that
        keyframe (a keyframe frame is its own reference)."""
        T = np.asarray(res.T_world_cam, dtype=np.float64)
        if res.keyframe is not None:
            self._kf = res.keyframe.kf_id
            T_ref = np.asarray(res.keyframe.T_world_cam, dtype=np.float64)
        else:
            T_ref = map_.keyframe_pose(self._kf)
        self._ref[frame_index] = (self._kf, se3.inv(T_ref) @ T)

    def world(self, map_: LandmarkMap) -> dict[int, np.ndarray]:
        """Frame index -> (4,4) T_world_cam with every refinement of its keyframe applied."""
        return {f: map_.keyframe_pose(k) @ T_kf_cam for f, (k, T_kf_cam) in self._ref.items()}

    def cam0(self, map_: LandmarkMap, calib: Calibration, frame_indices: Iterable[int]) -> np.ndarray:
        """(N,4,4) T_world_cam0 of the given frames (what KITTI pose files hold)."""
        T_cam_cam0 = se3.inv(np.asarray(calib.T_cam0_cam, dtype=float))
        poses = self.world(map_)
        return np.stack([poses[f] @ T_cam_cam0 for f in frame_indices])
