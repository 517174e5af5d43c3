"""Every frame's pose, kept relative to the keyframe it was tracked from: the back end and the loop closer move
keyframes after the tracker has passed them, and composing with the keyframe's current pose carries every
refinement into the reported trajectory (as ORB-SLAM2 reports its trajectory).

A frame between two keyframes also takes its share of the correction the later one received. The tracker's motion
from a keyframe carries its own scale and heading (the depth priors' scale, +1 % on the real KITTI 04 frames), which
the scale correction and the bundle adjustment take out at the next keyframe only; kept relative to the earlier
keyframe alone, the frames in between would keep it, a saw-tooth of a few centimetres every keyframe interval."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from plvo.geometry import se3
from plvo.results import KeyframeReason
from plvo.tracking.frontend import FrontendResult
from plvo.tracking.map import LandmarkMap
from plvo.types import Calibration

# Keyframes made while tracking went on: the motion to them is the tracker's, measured as the frames' before them
_TRACKED_ON = (KeyframeReason.FEW_TRACKED, KeyframeReason.ROTATION, KeyframeReason.INTERVAL)


@dataclass(frozen=True)
class _Successor:
    """The keyframe tracked after another: its id, frame index, and the tracker's motion to it from the earlier
    one (T_a_b, the earlier keyframe's pose as the map had it then)."""

    kf_id: int
    frame: int
    T_a_b: np.ndarray


class FramePoses:
    def __init__(self) -> None:
        self._ref: dict[int, tuple[int, np.ndarray]] = {}  # frame -> (keyframe id, T_kf_cam)
        self._kf = -1
        self._kf_frame: dict[int, int] = {}  # keyframe id -> its frame index
        self._next: dict[int, _Successor] = {}  # keyframe id -> the keyframe tracked after it

    def add(self, frame_index: int, res: FrontendResult, map_: LandmarkMap) -> None:
        """The frame's tracked pose relative to its reference keyframe, taken before inline workers move that
        keyframe (a keyframe frame is its own reference)."""
        T = np.asarray(res.T_world_cam, dtype=np.float64)
        if res.keyframe is not None:
            T_ref = np.asarray(res.keyframe.T_world_cam, dtype=np.float64)
            why = res.keyframe_reason
            if self._kf >= 0 and why is not None and why.kind in _TRACKED_ON:
                self._next[self._kf] = _Successor(res.keyframe.kf_id, frame_index,
                                                  se3.inv(map_.keyframe_pose(self._kf)) @ T_ref)
            self._kf = res.keyframe.kf_id
            self._kf_frame[self._kf] = frame_index
        else:
            T_ref = map_.keyframe_pose(self._kf)
        self._ref[frame_index] = (self._kf, se3.inv(T_ref) @ T)

    def world(self, map_: LandmarkMap) -> dict[int, np.ndarray]:
        """Frame index -> (4,4) T_world_cam with every refinement of its keyframe applied, and its share of the
        next keyframe's."""
        poses = {k: map_.keyframe_pose(k) for k in {k for k, _ in self._ref.values()}}
        shares = {a: self._correction(a, poses) for a in poses}
        out = {}
        for f, (k, T_kf_cam) in self._ref.items():
            D = shares[k]
            if D is not None and f != self._kf_frame[k]:
                alpha = (f - self._kf_frame[k]) / (self._next[k].frame - self._kf_frame[k])
                T_kf_cam = se3.exp(alpha * D) @ T_kf_cam
            out[f] = poses[k] @ T_kf_cam
        return out

    def _correction(self, a: int, poses: dict[int, np.ndarray]) -> np.ndarray | None:
        """(6,) log of the correction D (in keyframe a's frame) that the map applied to the tracker's motion from a
        to the keyframe after it: D T_a_b(tracked) = T_a_b(now). None when a has no successor tracked from it.
        poses holds every keyframe a frame refers to, the successor among them (its own frame refers to it)."""
        nxt = self._next.get(a)
        if nxt is None:
            return None
        return se3.log(se3.inv(poses[a]) @ poses[nxt.kf_id] @ se3.inv(nxt.T_a_b))

    def cam0(self, map_: LandmarkMap, calib: Calibration, frame_indices: Iterable[int]) -> np.ndarray:
        """(N,4,4) T_world_cam0 of the given frames (what KITTI pose files hold)."""
        T_cam_cam0 = se3.inv(np.asarray(calib.T_cam0_cam, dtype=float))
        poses = self.world(map_)
        return np.stack([poses[f] @ T_cam_cam0 for f in frame_indices])
