"""The reported trajectory: frames between keyframes take their share of the correction the later keyframe got, so
that the tracker's own scale and heading between keyframes do not stay in the frames after a correction."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from plvo.geometry import se3
from plvo.results import KeyframeReason, KeyframeWhy
from plvo.runtime.frame_poses import FramePoses
from plvo.tracking.map import LandmarkMap


def _pose(z: float, yaw: float = 0.0) -> np.ndarray:
    return se3.exp(np.array([0.0, 0.0, z, 0.0, yaw, 0.0]))


def _track(m: LandmarkMap, fp: FramePoses, poses: dict[int, np.ndarray], keyframes: dict[int, KeyframeReason]
           ) -> dict[int, int]:
    """Feed frames 0.. with the tracker's poses; frames in `keyframes` become keyframes -> frame -> keyframe id."""
    ids = {}
    for f in sorted(poses):
        kf = None
        if f in keyframes:
            ids[f] = m.add_keyframe(f, poses[f])
            kf = SimpleNamespace(kf_id=ids[f], T_world_cam=poses[f])
        why = KeyframeWhy(keyframes[f]) if f in keyframes else None
        fp.add(f, SimpleNamespace(T_world_cam=poses[f], keyframe=kf, keyframe_reason=why), m)
    return ids


def test_a_scale_correction_reaches_the_frames_before_the_keyframe():
    """The tracker runs 2 % long from keyframe 0 to keyframe 4 (1 m a frame, read as 1.02 m); the map sets keyframe
    4 back at 4 m. Frames 1-3 land on the truth, not 2 % long as kept relative to keyframe 0 alone; frames after
    the last keyframe keep the tracker's motion from it."""
    m, fp = LandmarkMap(), FramePoses()
    tracked = {f: _pose(1.02 * f) for f in range(7)}
    kfs = _track(m, fp, tracked, {0: KeyframeReason.FIRST, 4: KeyframeReason.INTERVAL})
    m.apply_update(keyframe_ids=np.array([kfs[4]]), keyframe_T_world_cam=_pose(4.0)[None])
    world = fp.world(m)
    z = np.array([world[f][2, 3] for f in range(7)])
    np.testing.assert_allclose(z[:5], np.arange(5.0), atol=1e-9)
    np.testing.assert_allclose(z[5:], 4.0 + 1.02 * np.array([1.0, 2.0]), atol=1e-9)  # the tracker's, from kf 4
    # the cam0 poses are the same frames
    calib = SimpleNamespace(T_cam0_cam=np.eye(4))
    np.testing.assert_allclose(fp.cam0(m, calib, range(7))[:, 2, 3], z, atol=1e-12)


def test_a_heading_correction_is_shared_in_proportion():
    """Keyframe 4 turned by 0.4 deg of yaw (about its own position) by the back end: each frame before it turns by
    its share, frame 2 (half way) by half, and keyframe 4 lands where the map put it."""
    m, fp = LandmarkMap(), FramePoses()
    kfs = _track(m, fp, {f: _pose(float(f)) for f in range(5)}, {0: KeyframeReason.FIRST,
                                                                  4: KeyframeReason.INTERVAL})
    turn = np.deg2rad(0.4)
    m.apply_update(keyframe_ids=np.array([kfs[4]]), keyframe_T_world_cam=_pose(4.0, turn)[None])
    world = fp.world(m)
    yaw = [se3.so3_log(world[f][:3, :3])[1] for f in range(5)]
    np.testing.assert_allclose(yaw, turn * np.arange(5) / 4, atol=1e-9)
    np.testing.assert_allclose(world[4], _pose(4.0, turn), atol=1e-12)


def test_no_share_across_a_reinitialisation():
    """A keyframe made after tracking was lost is not the tracker's motion from the one before: the frames before
    it keep their poses relative to the earlier keyframe, however far the later one is moved."""
    m, fp = LandmarkMap(), FramePoses()
    kfs = _track(m, fp, {f: _pose(1.02 * f) for f in range(5)}, {0: KeyframeReason.FIRST, 4: KeyframeReason.LOST})
    m.apply_update(keyframe_ids=np.array([kfs[4]]), keyframe_T_world_cam=_pose(6.0)[None])
    world = fp.world(m)
    np.testing.assert_allclose([world[f][2, 3] for f in range(4)], 1.02 * np.arange(4), atol=1e-9)
    np.testing.assert_allclose(world[4][2, 3], 6.0, atol=1e-12)


def test_later_keyframes_and_the_earlier_ones_move_together():
    """Both keyframes moved by the same rigid motion (a loop correction): the frames between move rigidly with
    them, their share of a correction that changed nothing between the two being the identity."""
    m, fp = LandmarkMap(), FramePoses()
    tracked = {f: _pose(float(f), 0.01 * f) for f in range(9)}
    kfs = _track(m, fp, tracked, {0: KeyframeReason.FIRST, 4: KeyframeReason.INTERVAL, 8: KeyframeReason.ROTATION})
    M = se3.exp(np.array([0.3, -0.1, 0.5, 0.0, 0.02, 0.01]))
    ids = np.array([kfs[0], kfs[4], kfs[8]])
    m.apply_update(keyframe_ids=ids, keyframe_T_world_cam=np.stack([M @ tracked[f] for f in (0, 4, 8)]))
    world = fp.world(m)
    for f in range(9):
        np.testing.assert_allclose(world[f], M @ tracked[f], atol=1e-9)
