"""The frame-to-frame tracker (paper II-C): features, 2D-2D matching with the previous frame, PnPL against the
landmarks seen in the previous frame, outlier removal, keyframes with landmarks from the lidar depth priors.

Landmark creation, in keyframes only:
- with depth priors (default): a point with a depth prior is back-projected; a line with a depth prior gets its
  trimmed 3D endpoints. Lines are never triangulated from views alone.
- ablation `use_depth_priors=False`: point landmarks are triangulated between the previous keyframe and this one
  with the tracker's own poses (2D tracks chained through the frame-to-frame matches); lines are not used at
  all. The first frame and every re-initialisation still take lidar depth, or the run would have no scale.
- `points_only`: no line is matched, created or used.

Beyond the paper, landmarks of the recent keyframes that the 2D-2D matching missed are re-found by projection
after the solve (points near their projection, lines lying on their projected line: plvo.tracking.search), and
the pose is refined on all of them.

Tracking loss (PnPL fails or keeps fewer than cfg.tracking.min_pnp_inliers matches) takes the constant-velocity
prediction as the pose, forgets the tracked landmarks, makes a keyframe and re-initialises its landmarks from the
current lidar depth; the log and the result's message say so.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from plvo.config import TrackerSections
from plvo.depth.extract import extract_depth_priors
from plvo.features.extract import extract_features
from plvo.features.matching import match_lines, match_points
from plvo.geometry import se3
from plvo.geometry.camera import backproject, in_image, project
from plvo.lidar.deskew import Sweep, azimuth_times, needs_deskew, twist_from_motion
from plvo.results import KeyframeReason, KeyframeWhy, TrackingResult
from plvo.tracking.association import FrameAssociation, search_by_projection
from plvo.tracking.corrections import RELOCALISED, MapCorrection
from plvo.tracking.correspondences import Correspondences
from plvo.tracking.extrinsic import ExtrinsicEstimate, ExtrinsicEstimator
from plvo.tracking.keyframes import KeyframeInfo, KeyframePolicy, triangulate_tracks
from plvo.tracking.lidar_check import (
    CAMERA,
    CAMERA_SEEDED,
    LIDAR,
    PREDICTION,
    CheckLog,
    LidarMotion,
    LidarOdometer,
    agrees,
    disagreement,
    mean_abs_difference,
    same_scan,
)
from plvo.tracking.map import LandmarkMap
from plvo.tracking.pnpl import PnPLResult, refine_pose, snap_pose, solve_pnpl
from plvo.tracking.search import predict_points, predict_segments, project_segments, search_lines_by_projection
from plvo.tracking.time_offset import OffsetEstimate, TimeOffsetEstimator
from plvo.types import Calibration, DepthPriors, FeatureSet, Frame, Matches

log = logging.getLogger(__name__)

INITIALISED, TRACKED, REINITIALISED = "initialised", "tracked", "reinitialised"
OVERRULED = "overruled"  # the camera's estimate disagreed with the lidar's: the pose is the lidar's (lidar_check)
HELD = "held"  # the image repeats the previous one while the lidar moves: the pose is the lidar's
NO_MOTION_MODEL = "no motion model yet"  # the doubt of a run's first tracked step
_NONE = np.zeros(0)  # no PnPL residuals (nothing solved); read-only like every result's arrays


def _arr(shape: tuple[int, ...], dtype: type = float) -> np.ndarray:
    return field(default_factory=lambda: np.zeros(shape, dtype))


@dataclass(frozen=True)
class FrontendResult(TrackingResult):
    """plvo.results.TrackingResult (what recorders read) plus what the tracker knows beyond it.

    Base fields: T_world_cam (4,4) of the tracked camera; point_inliers / line_inliers: indices of this frame's
    keypoints / segments tracked and kept by PnPL; ok: False after a tracking loss (the pose is then the
    constant-velocity prediction and the landmarks were re-initialised from lidar depth).
    Extra: T_world_cam0 (4,4) the same pose for cam0 (what is reported); status "initialised" | "tracked" |
    "reinitialised"; point_uv (K,2) current pixels of the 3D-2D point matches, point_landmark (K,) their landmark
    ids, point_inlier (K,) bool; line_segments (L,4), line_landmark (L,), line_inlier (L,) likewise; association:
    this frame's features -> landmark ids after outlier removal; keyframe: what the back end needs when this frame
    is a keyframe; timings: seconds per step ("features", "matching", "pnpl", "keyframe", "total").
    """

    T_world_cam0: np.ndarray = field(default_factory=lambda: np.eye(4))
    status: str = TRACKED
    keyframe_reason: KeyframeWhy | None = None  # when this frame became a keyframe
    point_uv: np.ndarray = _arr((0, 2))
    point_landmark: np.ndarray = _arr((0,), np.int64)
    point_inlier: np.ndarray = _arr((0,), bool)
    line_segments: np.ndarray = _arr((0, 4))
    line_landmark: np.ndarray = _arr((0,), np.int64)
    line_inlier: np.ndarray = _arr((0,), bool)
    n_new_points: int = 0
    n_new_lines: int = 0
    association: FrameAssociation | None = None
    features: FeatureSet | None = None
    keyframe: KeyframeInfo | None = None
    timings: dict[str, float] = field(default_factory=dict)
    source: str = CAMERA  # where the pose came from (plvo.tracking.lidar_check.SOURCES)

    @property
    def n_point_inliers(self) -> int:
        return int(self.point_inlier.sum())

    @property
    def n_line_inliers(self) -> int:
        return int(self.line_inlier.sum())


@dataclass(frozen=True)
class _TrackedAtKeyframe:
    """What a keyframe was tracked on: the older landmarks it matched (ids) and where (pixels, segments)."""

    kf_id: int
    point_ids: np.ndarray
    uv: np.ndarray
    line_ids: np.ndarray
    segments: np.ndarray


@dataclass
class _FrameState:
    index: int
    features: FeatureSet
    T_world_cam: np.ndarray
    assoc: FrameAssociation
    kf_track: np.ndarray  # (N,) keypoint index in the last keyframe this keypoint was tracked from, -1 none


class Stages(NamedTuple):
    """The tracker's stages: plvo's (`_default_stages`), or stand-ins with their signatures (a test's synthetic
    world, the System's depth stage that also keeps what the extraction saw for the viewers)."""

    extract: Callable[..., FeatureSet]  # as plvo.features.extract.extract_features
    match_points: Callable[..., Matches]  # as plvo.features.matching.match_points
    match_lines: Callable[..., Matches]  # as plvo.features.matching.match_lines
    depth: Callable[..., DepthPriors]  # as plvo.depth.extract.extract_depth_priors


def _default_stages() -> Stages:
    return Stages(extract_features, match_points, match_lines, extract_depth_priors)


class Frontend:
    """Per-frame tracker. `track(frame)` once per frame, in order; `map` is shared with the back end."""

    def __init__(self, calib: Calibration, config: TrackerSections, landmark_map: LandmarkMap | None = None,
                 T_world_cam_init: np.ndarray | None = None, stages: Stages | None = None):
        """stages: the feature extraction, point and line matching and depth priors (Stages), defaults to plvo's."""
        self.calib = calib
        self.cfg = config
        self.K = np.asarray(calib.K, dtype=float)
        self.map = landmark_map if landmark_map is not None else LandmarkMap()
        self.policy = KeyframePolicy(config.tracking)
        self._extract, self._match_points, self._match_lines, self._depth = stages or _default_stages()
        self._T_init = np.array(calib.T_cam0_cam if T_world_cam_init is None else T_world_cam_init, dtype=float)
        self._T_cam_cam0 = se3.inv(np.asarray(calib.T_cam0_cam, dtype=float))
        self._prev: _FrameState | None = None
        self._last_kf: _FrameState | None = None
        self._last_kf_id = -1
        self._recent_kfs: deque[_FrameState] = deque(maxlen=max(1, config.tracking.search_keyframes))
        self._last_kf_pose_seen: np.ndarray | None = None
        self._velocity = np.eye(4)  # T_prev_cur of the last tracked step
        self._prev_time: float | None = None  # the previous frame's time (s): the velocity's interval
        self._last_inliers = 0  # frame-to-frame PnPL inliers of the last tracked frame
        self._kf_tracked: _TrackedAtKeyframe | None = None  # the newest keyframe's matches to older landmarks
        self.uses_lines = not (config.tracking.points_only or not config.tracking.use_depth_priors)
        # the camera checked against the lidar (plvo.tracking.lidar_check)
        self.checks = CheckLog(log)
        self._lidar = LidarOdometer(calib.T_cam_velo, config.crosscheck) if config.crosscheck.enabled else None
        self._last_input: Frame | None = None  # the previous frame: the other end of a frame's check
        self._last_kf_input: Frame | None = None  # the newest keyframe's frame: the other end of a keyframe's check
        self._held: np.ndarray | None = None  # pose of the previous frame when the lidar held it (a repeated image)
        self._motion_known = False  # a step has been tracked: the motion model predicts something
        self._prev_dt: float | None = None  # the last interval between frames (s)
        cc = config.crosscheck
        self.offset = (TimeOffsetEstimator(cc.offset_max_s, cc.offset_sigma_s)
                       if self._lidar is not None and cc.estimate_time_offset else None)
        self.offset_found: OffsetEstimate | None = None  # the estimate once it was observable and large
        self._offset_s = cc.time_offset_s  # the stated offset: scans moved by it to the images' instants
        self.extrinsic = (ExtrinsicEstimator(cc.extrinsic_prior_deg)
                          if self._lidar is not None and cc.estimate_extrinsic else None)
        self.extrinsic_found: ExtrinsicEstimate | None = None  # the estimate once it departed from the stated one
        # with an offset stated: the camera's velocity (twist a second, its frame) at recent frames, which moves the
        # check's lidar motions from the scans' instants to the images'
        self._twists: dict[int, np.ndarray] = {}

    # ---- the per-frame entry point -----------------------------------------------------------------------
    @property
    def feature_settings(self) -> tuple:
        """(orb, lines, points_only): what the extraction of the features `track` uses takes beside the image; no
        lines are detected when none is used. Also the features process's (plvo.features.worker)."""
        return self.cfg.orb, self.cfg.lines, not self.uses_lines

    def features(self, image: np.ndarray) -> FeatureSet:
        """The features `track` uses of an image (a pure function of it and the config: safe in another thread)."""
        return self._extract(image, *self.feature_settings)

    def track(self, frame: Frame) -> FrontendResult:
        """Estimate the pose of `frame` (the next one in order) and update the map."""
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        if frame.features is not None:  # extracted ahead (System.prepare): its time was spent off this thread
            feats = frame.features
            timings["features"] = frame.features_s
        else:
            feats = self.features(frame.image)
            timings["features"] = time.perf_counter() - t0
        if self._prev is None:
            res = self._initialise(frame, feats, self._T_init, INITIALISED, KeyframeWhy(KeyframeReason.FIRST),
                                   "first frame", timings)
        else:
            res = self._track(frame, feats, timings, self._prev)
        if self._prev_time is not None and frame.time > self._prev_time:
            self._prev_dt = frame.time - self._prev_time
        self._prev_time = frame.time
        if self._offset_s and self._prev_dt:
            self._keep_twist(frame.index)
        self._last_input = frame
        if self.offset is not None:
            self.offset.frame(frame.time, res.T_world_cam[:3, :3], own=res.source == CAMERA)
        self.checks.source(res.source)
        self.checks.frame_done(frame.index)
        timings["total"] = time.perf_counter() - t0
        return dataclasses.replace(res, timings=timings)

    def _track(self, frame: Frame, feats: FeatureSet, timings: dict[str, float], prev: _FrameState) -> FrontendResult:
        self._reanchor_to_map(prev)
        cc, last = self.cfg.crosscheck, self._last_input
        assert last is not None  # a previous frame state means a previous frame
        base = prev.T_world_cam if self._held is None else self._held  # the previous frame's pose
        velocity, doubts = self._velocity, []
        dt = None if self._prev_time is None else frame.time - self._prev_time
        if dt is not None and self._prev_dt and dt > cc.gap_factor * self._prev_dt:  # with or without the check
            velocity = se3.exp(se3.log(self._velocity) * (dt / self._prev_dt))
            doubts.append("a gap in the frame times")
            self.checks.note(frame.index, "frames dropped", f"{dt:.3f} s since frame {last.index} against "
                             f"{self._prev_dt:.3f} s before; the motion model stretched over the gap")
        T_pred = base @ velocity
        repeated_scan = cc.enabled and same_scan(frame.scan, last.scan)
        if repeated_scan:
            self.checks.note(frame.index, "scan repeated", f"the scan of frame {last.index} again: no keyframe on it "
                             "and no check against the lidar")
        lidar_ok = self._lidar is not None and not repeated_scan
        if lidar_ok and mean_abs_difference(frame.image, last.image) < cc.frozen_image_grey:
            still = self._lidar_motion(last, frame, [velocity, np.eye(4)], timings)
            if still.usable and still.step_m > cc.still_m:
                return self._hold(frame, feats, base, still, timings)
        t = time.perf_counter()
        pm, lm = self._match(prev, feats, T_pred)
        corr = self._correspondences(prev, feats, pm, lm)
        timings["matching"] = time.perf_counter() - t
        t = time.perf_counter()
        sol = solve_pnpl(self.K, *corr.solver_inputs(), T_pred, self.cfg.tracking)
        timings["pnpl"] = time.perf_counter() - t
        if not sol.success:
            first = sol.message
            sol, corr = self._rescue(prev, feats, T_pred, corr, timings)
            doubts.append("a rescue")
            if sol.success:
                log.info("frame %d: frame-to-frame PnPL failed (%s); recovered (%s)", frame.index, first,
                         sol.message)
        elif sol.n_inliers < self.cfg.tracking.weak_inlier_share * self._last_inliers:
            # A solution on a fraction of the last frame's inliers: the motion model mispredicted (a turn that
            # begins or ends: 4-9 deg of yaw a frame more than predicted, ~100 px) and the few predicted matches
            # may fit a wrong pose (2.7 m off at a synthetic turn). Match again without prediction; keep the better.
            t = time.perf_counter()
            alt, alt_corr = self._match_and_solve(prev, feats, None)
            timings["rescue"] = time.perf_counter() - t
            if alt.success and alt.n_inliers > sol.n_inliers:
                log.info("frame %d: %d inliers with the motion model, %d without it: took the latter", frame.index,
                         sol.n_inliers, alt.n_inliers)
                sol, corr = alt, alt_corr
                doubts.append("a rescue")
        if sol.success:
            self._last_inliers = sol.n_inliers
        lidar: LidarMotion | None = None
        source = CAMERA
        if not sol.success:
            if lidar_ok:  # the lidar's motion instead of the motion model's, and the camera tried again from it
                lidar = self._lidar_motion(last, frame, [velocity, np.eye(4)], timings)
            if lidar is not None and lidar.usable:
                found = self._seeded(prev, feats, base, lidar, timings)
                if found is None:
                    return self._overrule(frame, feats, base, base, lidar, "tracking lost", timings, corr)
                self.checks.note(frame.index, "camera re-tracked from the lidar's motion",
                                 f"tracking was lost ({sol.message}); matched again from the lidar's motion")
                sol, corr, T, p_in, l_in = found
                pm, lm = _no_matches(), _no_matches()  # the first matching's pairs are not the solution's
                source = CAMERA_SEEDED
            else:
                msg = (f"frame {frame.index}: tracking lost ({sol.message}; {corr.n_points} point and "
                       f"{corr.n_lines} line matches to landmarks); re-initialised from the current lidar depth")
                log.info(msg)  # one warning an episode names the frames (CheckLog)
                self.checks.note(frame.index, "tracking lost", f"{sol.message}; the lidar "
                                 f"{'could not judge' if lidar is not None else 'was not asked'}: the motion "
                                 "model's guess, landmarks from the current lidar depth")
                res = self._initialise(frame, feats, T_pred, REINITIALISED, KeyframeWhy(KeyframeReason.LOST), msg,
                                       timings, corr)
                return dataclasses.replace(res, source=PREDICTION)
        if source == CAMERA:
            t = time.perf_counter()
            T, corr, p_in, l_in = self._search_landmarks(feats, sol.T_world_cam, corr, sol.point_inliers,
                                                         sol.line_inliers)
            timings["search"] = time.perf_counter() - t
            step = se3.inv(base) @ T
            dm, ddeg = disagreement(velocity, step)
            if not self._motion_known:  # then the "motion model" is a placeholder: a step far from it says nothing
                doubts.append(NO_MOTION_MODEL)
            elif dm > cc.doubt_m + cc.doubt_share * np.linalg.norm(velocity[:3, 3]) or ddeg > cc.doubt_deg:
                doubts.append(f"{dm:.2f} m / {ddeg:.1f} deg from the motion model")
            is_kf = self.policy.decide(frame.index, T, int(p_in.sum() + l_in.sum())).is_keyframe
            if lidar_ok and (doubts or (is_kf and cc.at_keyframes)):
                found = self._check(frame, feats, prev, base, T, velocity, doubts, timings)
                if isinstance(found, FrontendResult):
                    return found
                if found is not None:
                    (sol, corr, T, p_in, l_in), source = found, CAMERA_SEEDED
                    pm, lm = _no_matches(), _no_matches()
                    why = ", ".join(doubts) or "at a keyframe"
                    self.checks.note(frame.index, "camera corrected by the lidar", f"the camera's motion disagreed "
                                     f"with the lidar's ({why}); matched again from the lidar's motion")
        self._motion_known = True
        self._held = None
        assoc = FrameAssociation.empty(feats.n_points, feats.n_lines)
        assoc.point_landmark[corr.point_features[p_in]] = corr.point_landmarks[p_in]
        assoc.line_landmark[corr.line_features[l_in]] = corr.line_landmarks[l_in]
        kf_track = np.full(feats.n_points, -1, np.int64)
        kf_track[pm.pairs[:, 1]] = prev.kf_track[pm.pairs[:, 0]]
        self.map.mark_seen(assoc.point_landmark[assoc.point_landmark >= 0],
                           assoc.line_landmark[assoc.line_landmark >= 0], frame.index)
        self._velocity = se3.inv(base) @ T
        state = _FrameState(frame.index, feats, T, assoc, kf_track)
        decision = self.policy.decide(frame.index, T, assoc.n_points + assoc.n_lines)
        keyframe, n_new = None, (0, 0)
        if decision.reason is not None and not repeated_scan:  # a repeated scan's depth would be the previous frame's
            t = time.perf_counter()
            keyframe, n_new = self._make_keyframe(frame, state, decision.reason, from_lidar=False)
            timings["keyframe"] = time.perf_counter() - t
        self._prev = state
        n_found = corr.n_points - len(sol.point_inliers)
        n_found_l = corr.n_lines - len(sol.line_inliers)
        msg = (f"frame {frame.index}: {int(p_in.sum())}/{len(p_in)} point ({n_found} re-found by projection) and "
               f"{int(l_in.sum())}/{len(l_in)} line ({n_found_l} re-found) inliers"
               + (f"; keyframe ({decision.reason})" if keyframe else ""))
        log.debug(msg)
        res = self._result(frame, state, TRACKED, msg, corr, timings, reason=decision.reason if keyframe else None,
                           n_pm=len(pm), n_lm=len(lm), inliers=(p_in, l_in), n_new=n_new, keyframe=keyframe,
                           pnpl_residuals=(sol.point_residuals[sol.point_inliers],
                                           sol.line_residuals[sol.line_inliers]))
        return dataclasses.replace(res, source=source)

    # ---- the camera checked against the lidar ---------------------------------------------------------------
    def _lidar_motion(self, src: Frame, dst: Frame, guesses: list[np.ndarray], timings: dict[str, float],
                      thorough: bool = True) -> LidarMotion:
        """The lidar's motion from src to dst, in the camera's frame; with a stated time offset, between the
        images' instants: the scans, taken `o` later, span M(t_src + o)^-1 M(t_dst + o) = E_src^-1 D E_dst with
        E = exp(o twist) the motion over o at each end (the camera's velocity there), so D = E_src D_lidar
        E_dst^-1 (for a compensated scan, exactly what moving the scan to its image's instant does)."""
        assert self._lidar is not None
        ends = self._offset_ends(src.index)
        if ends is not None:
            E_src, E_dst = ends
            guesses = [se3.inv(E_src) @ g @ E_dst for g in guesses]
        motion = self._lidar.motion((src.index, src.scan), (dst.index, dst.scan), guesses, thorough)
        timings["crosscheck"] = timings.get("crosscheck", 0.0) + motion.time_s
        if thorough:  # the frames that needed more than a quick look, and what those cost
            timings["crosscheck_thorough"] = timings.get("crosscheck_thorough", 0.0) + motion.time_s
        if ends is None:
            return motion
        return dataclasses.replace(motion, T_camprev_camcur=ends[0] @ motion.T_camprev_camcur @ se3.inv(ends[1]),
                                   T_as_taken=motion.T_camprev_camcur)

    def _keep_twist(self, frame_index: int) -> None:
        """The camera's velocity at this frame (the last step's), for `_offset_ends`; those of frames no check
        starts from any more are dropped."""
        assert self._prev_dt is not None
        self._twists[frame_index] = se3.log(self._velocity) / self._prev_dt
        oldest = min(frame_index - 1, self._last_kf_input.index if self._last_kf_input is not None else frame_index)
        for f in [f for f in self._twists if f < oldest]:
            del self._twists[f]

    def _offset_ends(self, src_index: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(E_src, E_dst): the camera's motion over the stated offset at the interval's start and end (the end's
        velocity: the last known, the step to the previous frame); None without an offset or a velocity yet."""
        last = self._last_input
        if not self._offset_s or last is None or src_index not in self._twists or last.index not in self._twists:
            return None
        return se3.exp(self._offset_s * self._twists[src_index]), se3.exp(self._offset_s * self._twists[last.index])

    def _check(self, frame: Frame, feats: FeatureSet, prev: _FrameState, base: np.ndarray, T: np.ndarray,
               velocity: np.ndarray, doubts: list[str], timings: dict[str, float]) -> Any:
        """The camera's pose T checked against the lidar: over the last frame's interval when the estimate is in
        doubt, else (at a keyframe) since the newest keyframe. None: they agree (or the lidar cannot judge, or only
        the rotation disagrees); the camera's solution matched again from the lidar's motion (`_seeded`); or the
        result with the lidar's own pose (`_overrule`)."""
        kf = self._last_kf_input
        if doubts or kf is None or self._last_kf_id < 0:
            assert self._last_input is not None
            src, T_src, model = self._last_input, base, [velocity]
        else:
            src, T_src, model = kf, self.map.keyframe_pose(self._last_kf_id), []
        moved = se3.inv(T_src) @ T  # the camera's motion over the interval
        guesses = [moved, *model, np.eye(4)]
        # A first step is doubted only because nothing predicted it: a quick look from the camera's motion confirms a
        # right one (a wrong one disagrees and is looked at thoroughly, as at a keyframe). A thorough look there cost
        # a run's start ~30 ms of CPU and, while the workers still start up, 70-105 ms of waiting (real KITTI 04).
        thorough = bool(doubts) and doubts != [NO_MOTION_MODEL]
        lidar = self._lidar_motion(src, frame, guesses, timings, thorough=thorough)
        if lidar.usable and agrees(moved, lidar, self.cfg.crosscheck):
            self._learn_from(frame, src.time, moved, lidar)
            return None
        if not thorough:  # a quick look disagreed: a thorough one before the camera is called wrong
            lidar = self._lidar_motion(src, frame, guesses, timings)
        if not lidar.usable or agrees(moved, lidar, self.cfg.crosscheck):
            return None
        found = self._seeded(prev, feats, T_src, lidar, timings)
        if found is None:
            cc = self.cfg.crosscheck
            dm, ddeg = disagreement(moved, lidar.T_camprev_camcur)
            if dm <= cc.agree_m + cc.agree_share * lidar.step_m:
                # The rotation alone disagrees and the images, matched from the lidar's, keep theirs: the images fix
                # a rotation better than 1.5 m voxels do, and a lidar whose clock is off turns early or late at a
                # turn's start and end (the time offset's estimate then names it); the camera is kept
                self.checks.note(frame.index, "rotation disagrees with the lidar's", f"{ddeg:.1f} deg since frame "
                                 f"{src.index} (translation {dm:.2f} m): the camera's kept")
                self._learn_from(frame, src.time, moved, lidar)
                return None
            return self._overrule(frame, feats, base, T_src, lidar, f"the camera's motion {dm:.2f} m / {ddeg:.1f} deg "
                                  f"from the lidar's since frame {src.index}", timings)
        return found

    def _learn_from(self, frame: Frame, t_src: float, T_camera: np.ndarray, lidar: LidarMotion) -> None:
        """A checked interval whose frames the camera kept (T_camera its motion, from the frame at t_src), to the
        time offset's and the extrinsic's estimates."""
        self._estimate_offset(frame, t_src, lidar)
        self._estimate_extrinsic(frame, T_camera, lidar)

    def _estimate_offset(self, frame: Frame, t_src: float, lidar: LidarMotion) -> None:
        """Add a checked interval whose frames the camera kept to the time offset's estimate (where the lidar's
        motion was taken, the two agree at any offset and would pull the estimate to none); every 5th, estimate;
        the first time the offset is observable and over crosscheck.offset_warn_s from the stated one by
        crosscheck.offset_confidence_sigmas of its standard deviations, name it and what to state.

        It is not corrected mid-run: the landmarks and the back end's local map made so far hold the offset, and
        moving the scans from a frame on mixed the two (docs/crosscheck.md); the run loop starts again from the
        first frame with it stated instead (System.restart_wanted)."""
        if self.offset is None:
            return
        cc = self.cfg.crosscheck
        self.offset.interval(t_src, frame.time, lidar.rotation_as_taken)
        if self.offset_found is not None or not _estimate_due(self.offset.n_intervals):
            return
        est = self.offset.estimate()
        if est is None or not est.departs_from(self._offset_s, cc.offset_warn_s, cc.offset_confidence_sigmas):
            return
        self.offset_found = est
        what = "after" if est.offset_s > 0 else "before"
        use = ("the run starts again from its first frame with them moved to the images' instants"
               if cc.restart_on_offset else
               f"run again with --time-offset {est.offset_s:.3f} to move them to the images' instants")
        self.checks.note(frame.index, "camera-lidar time offset", f"the scans are taken {abs(est.offset_s):.3f} s "
                         f"(+- {est.sigma_s:.3f}) {what} the images (from the rotations of {est.n_intervals} "
                         f"intervals); {use}")

    def _estimate_extrinsic(self, frame: Frame, T_camera: np.ndarray, lidar: LidarMotion) -> None:
        """Add a checked interval whose frames the camera kept (T_camera its motion) to the extrinsic's estimate;
        every 5th (25th after 50), estimate; the first time a component departs from the stated extrinsic by
        crosscheck.extrinsic_warn_deg and extrinsic_confidence_sigmas of its standard deviations, name it. Like an
        offset it is not corrected mid-run (the landmarks and the back end's map hold the stated one): with
        crosscheck.restart_on_extrinsic the run starts again with it (System.restart_wanted)."""
        if self.extrinsic is None:
            return
        cc = self.cfg.crosscheck
        self.extrinsic.interval(T_camera, lidar.T_camprev_camcur)
        if self.extrinsic_found is not None or not _estimate_due(self.extrinsic.n_intervals):
            return
        est = self.extrinsic.estimate()
        if est is None or not est.departs(cc.extrinsic_warn_deg, cc.extrinsic_confidence_sigmas):
            return
        self.extrinsic_found = est
        angles = ", ".join(f"{v:+.2f}" for v in est.correction_deg)
        spread = ", ".join(f"{v:.2f}" for v in est.sigma_deg)
        use = ("the run starts again from its first frame with it corrected" if cc.restart_on_extrinsic else
               f"run again with crosscheck.extrinsic_correction_deg = [{angles}] (composed with the one stated)")
        self.checks.note(frame.index, "camera-lidar extrinsic", f"the lidar's motions agree with the camera's through "
                         f"the extrinsic turned by [{angles}] deg (+- [{spread}]; x right, y down, z ahead) over "
                         f"{est.n_intervals} intervals; {use}")

    def _seeded(self, prev: _FrameState, feats: FeatureSet, T_src: np.ndarray, lidar: LidarMotion,
                timings: dict[str, float]
                ) -> tuple[PnPLResult, Correspondences, np.ndarray, np.ndarray, np.ndarray] | None:
        """The camera's pose matched and solved again from the lidar's motion (the pose of the interval's start
        T_src times it): (solution, correspondences, T, point inliers, line inliers) when it agrees with the
        lidar's, else None."""
        t = time.perf_counter()
        sol, corr = self._match_and_solve(prev, feats, T_src @ lidar.T_camprev_camcur)
        found = None
        if sol.success:
            T, corr, p_in, l_in = self._search_landmarks(feats, sol.T_world_cam, corr, sol.point_inliers,
                                                         sol.line_inliers)
            if agrees(se3.inv(T_src) @ T, lidar, self.cfg.crosscheck):
                found = sol, corr, T, p_in, l_in
        timings["crosscheck"] = timings.get("crosscheck", 0.0) + time.perf_counter() - t
        return found

    def _overrule(self, frame: Frame, feats: FeatureSet, base: np.ndarray, T_src: np.ndarray, lidar: LidarMotion,
                  why: str, timings: dict[str, float], corr: Correspondences | None = None) -> FrontendResult:
        """The lidar's pose for this frame (the camera disagreed and could not be matched again from it), with
        landmarks made anew from the lidar's depth, as after a tracking loss."""
        T = T_src @ lidar.T_camprev_camcur
        self.checks.note(frame.index, "camera overruled by the lidar", f"{why}; poses from the lidar "
                         f"({lidar.step_m:.2f} m since the check's start), landmarks made anew from its depth")
        msg = f"frame {frame.index}: camera overruled by the lidar ({why}); re-initialised from the lidar's depth"
        self._velocity = se3.inv(base) @ T  # base: the previous frame's pose
        self._held = None
        res = self._initialise(frame, feats, T, OVERRULED, KeyframeWhy(KeyframeReason.OVERRULED), msg, timings, corr)
        return dataclasses.replace(res, source=LIDAR)

    def _hold(self, frame: Frame, feats: FeatureSet, base: np.ndarray, lidar: LidarMotion,
              timings: dict[str, float]) -> FrontendResult:
        """A repeated image while the lidar moves (a frozen camera): the lidar's pose, no keyframe, and the next
        image tracked against the last real one, predicted from here."""
        T = base @ lidar.T_camprev_camcur
        self._held, self._velocity = T, lidar.T_camprev_camcur
        self.checks.note(frame.index, "frozen image", f"the image repeats the one before while the lidar moves "
                         f"({lidar.step_m:.2f} m a frame): poses from the lidar")
        state = _FrameState(frame.index, feats, T, FrameAssociation.empty(feats.n_points, feats.n_lines),
                            np.full(feats.n_points, -1, np.int64))
        msg = f"frame {frame.index}: the image repeats the previous one while the lidar moves: pose from the lidar"
        corr = self._correspondences(state, feats, _no_matches(), _no_matches())
        res = self._result(frame, state, HELD, msg, corr, timings)
        return dataclasses.replace(res, source=LIDAR)

    # ---- matching and correspondences --------------------------------------------------------------------
    def _match(self, prev: _FrameState, feats: FeatureSet, T_pred: np.ndarray | None) -> tuple[Matches, Matches]:
        """2D-2D matches prev -> feats (indices into the full feature sets), predicted by T_pred (None: without).

        Only the previous features tracked to a landmark are matched when landmarks come from depth priors: the
        others cannot give a 3D-2D match, and leaving them out makes point matching several times cheaper. (The
        triangulation ablation chains every keypoint from keyframe to keyframe, so it matches all.)"""
        pf = prev.features
        p_rows = (np.flatnonzero(prev.assoc.point_landmark >= 0) if self.cfg.tracking.use_depth_priors
                  else np.arange(pf.n_points))
        sub = dataclasses.replace(pf, keypoints=pf.keypoints[p_rows], descriptors=pf.descriptors[p_rows],
                                  kp_octave=pf.kp_octave[p_rows], kp_angle=pf.kp_angle[p_rows],
                                  kp_response=pf.kp_response[p_rows])
        pred_uv = None if T_pred is None else predict_points(self.K, self.map, prev.T_world_cam, pf.keypoints[p_rows],
                                                             prev.assoc.point_landmark[p_rows], T_pred)
        pm = _remap(self._match_points(sub, feats, self.cfg.matching, predicted_uv=pred_uv), p_rows)
        l_rows = np.flatnonzero(prev.assoc.line_landmark >= 0)
        if not self.uses_lines or len(l_rows) == 0 or feats.n_lines == 0:
            return pm, _no_matches()
        sub = dataclasses.replace(pf, segments=pf.segments[l_rows], line_descriptors=pf.line_descriptors[l_rows])
        pred_seg = None if T_pred is None else predict_segments(self.K, self.map, prev.T_world_cam, pf.segments[l_rows],
                                                                 prev.assoc.line_landmark[l_rows], T_pred)
        lm = _remap(self._match_lines(sub, feats, self.cfg.matching, predicted_segments=pred_seg), l_rows)
        return pm, lm

    def _correspondences(self, prev: _FrameState, feats: FeatureSet, pm: Matches, lm: Matches) -> Correspondences:
        """3D-2D matches from the 2D-2D matches whose previous feature is tracked to a live landmark."""
        p_lm, p_cur = _tracked(prev.assoc.point_landmark, pm, self.map.point_alive)
        l_lm, l_cur = _tracked(prev.assoc.line_landmark, lm, self.map.line_alive)
        return Correspondences(
            p_lm, p_cur, self.map.point_positions(p_lm), feats.keypoints[p_cur].astype(float).reshape(-1, 2),
            l_lm, l_cur, self.map.line_endpoints(l_lm), feats.segments[l_cur].astype(float).reshape(-1, 4))

    def _search_landmarks(self, feats: FeatureSet, T: np.ndarray, corr: Correspondences, p_in: np.ndarray,
                          l_in: np.ndarray, widen: float = 1.0, refine: bool = True
                          ) -> tuple[np.ndarray, Correspondences, np.ndarray, np.ndarray]:
        """Re-find landmarks of the recent keyframes (and, for lines, of the previous frame) that the
        frame-to-frame matching lost: project them with pose T, match by descriptor near the projection (points
        within cfg.tracking.search_radius_px, lines on the projected line, see plvo.tracking.search), refine the
        pose on all. widen scales the windows (the rescue after a failed solve).
        (An addition to the paper's frame-to-frame scheme: without it most landmarks live two or three frames.)
        Returns (T, corr extended by the found matches, point inliers, line inliers)."""
        cfg = self.cfg.tracking
        if cfg.search_keyframes <= 0 or not self._recent_kfs:
            return T, corr, p_in, l_in
        n_p, n_l = corr.n_points, corr.n_lines
        corr = self._search_points(feats, T, corr, widen * cfg.search_radius_px)
        if self.uses_lines and cfg.search_lines:
            corr = self._search_lines(feats, T, corr, widen)
        n_p, n_l = corr.n_points - n_p, corr.n_lines - n_l
        if n_p + n_l == 0:
            return T, corr, p_in, l_in
        p_in = np.r_[p_in, np.zeros(n_p, bool)]
        l_in = np.r_[l_in, np.zeros(n_l, bool)]
        if refine:
            T, p_in, l_in = refine_pose(self.K, T, *corr.solver_inputs(), cfg)
        return T, corr, p_in, l_in

    def _search_candidates(self, kind: str, matched: np.ndarray) -> np.ndarray:
        views = list(self._recent_kfs) + ([self._prev] if kind == "line" and self._prev is not None else [])
        ids = np.unique(np.concatenate([getattr(v.assoc, f"{kind}_landmark") for v in views]))
        ids = np.setdiff1d(ids[ids >= 0], matched)
        return ids[(self.map.point_alive if kind == "point" else self.map.line_alive)(ids)]

    def _search_points(self, feats: FeatureSet, T: np.ndarray, corr: Correspondences,
                       radius_px: float) -> Correspondences:
        """corr with the point landmarks found near their projection added."""
        cand = self._search_candidates("point", corr.point_landmarks)
        if len(cand) == 0:
            return corr
        uv, z = project(self.K, se3.transform_points(se3.inv(T), self.map.point_positions(cand)))
        uv[(z < 0.5) | ~in_image(uv, self.calib.width, self.calib.height)] = np.nan
        free = np.ones(feats.n_points, bool)
        free[corr.point_features] = False
        rows, kps = search_by_projection(uv, self.map.point_descriptors(cand), feats.keypoints, feats.descriptors,
                                         free, radius_px, self.cfg.matching.point_max_hamming)
        return corr.with_points(cand[rows], kps, self.map.point_positions(cand[rows]),
                                feats.keypoints[kps].astype(float).reshape(-1, 2))

    def _search_lines(self, feats: FeatureSet, T: np.ndarray, corr: Correspondences,
                      widen: float) -> Correspondences:
        """corr with the line landmarks found on their projected line added."""
        cfg = self.cfg.tracking
        cand = self._search_candidates("line", corr.line_landmarks)
        if len(cand) == 0 or feats.n_lines == 0:
            return corr
        ends = self.map.line_endpoints(cand)
        proj = project_segments(self.K, T, ends, self.calib.width, self.calib.height)
        free = np.ones(feats.n_lines, bool)
        free[corr.line_features] = False
        rows, segs = search_lines_by_projection(
            proj, self.map.line_descriptors(cand), feats.segments, feats.line_descriptors, free,
            widen * cfg.line_search_px, widen * cfg.line_search_angle_deg, cfg.line_search_overlap,
            self.cfg.matching.line_max_lbd)
        return corr.with_lines(cand[rows], segs, ends[rows], feats.segments[segs].astype(float).reshape(-1, 4))

    def _rescue(self, prev: _FrameState, feats: FeatureSet, T_pred: np.ndarray, corr: Correspondences,
                timings: dict[str, float]) -> tuple[PnPLResult, Correspondences]:
        """Frame-to-frame PnPL failed. Search the recent keyframes' landmarks around their predicted projections
        in a wider window, and, as the prediction itself is suspect (a turn that begins or ends), match the
        previous frame again without any prediction and let RANSAC find the pose; keep the better."""
        t = time.perf_counter()
        none = np.zeros(corr.n_points, bool)
        _, wide, _, _ = self._search_landmarks(feats, T_pred, corr, none, np.zeros(corr.n_lines, bool),
                                               widen=3.0, refine=False)
        sol = solve_pnpl(self.K, *wide.solver_inputs(), T_pred, self.cfg.tracking)
        # All of them, and the one with more inliers: at a turn's start the wide window alone found 27 inliers
        # for a pose 2.6 m off (synthetic town, 12.5 m/s, yaw 4 -> 9 deg a frame). Without a prediction the
        # ratio test starves on repeated facades (8 matches at a synthetic turn, tracking lost), so the motion
        # model is also tried turned by a few yaw steps about the camera's vertical axis.
        tries = [self._match_and_solve(prev, feats, None)]
        tries += [self._match_and_solve(prev, feats, T_pred @ _yaw(np.radians(deg)))
                  for deg in self.cfg.tracking.rescue_yaw_deg]
        for sol_try, c in tries:
            if sol_try.success and (not sol.success or sol_try.n_inliers > sol.n_inliers):
                sol, wide = sol_try, c
        timings["rescue"] = time.perf_counter() - t
        return sol, wide

    def _match_and_solve(self, prev: _FrameState, feats: FeatureSet, T_guess: np.ndarray | None
                         ) -> tuple[PnPLResult, Correspondences]:
        """Match the previous frame predicted by T_guess (None: without a prediction) and solve from it ->
        (PnPLResult, correspondences)."""
        pm, lm = self._match(prev, feats, T_guess)
        c = self._correspondences(prev, feats, pm, lm)
        return solve_pnpl(self.K, *c.solver_inputs(), T_guess, self.cfg.tracking), c

    def relocalise_keyframe(self) -> MapCorrection | None:
        """The newest keyframe's pose solved again on its tracked matches against the landmarks as the map holds
        them now, as a correction for the map (None: no keyframe, or too few matches left).

        For the System, after it applied a back-end result that arrived while this keyframe was being tracked:
        the keyframe was then solved against the landmarks before that refinement and carried rigidly with the
        refined window's newest keyframe, while the landmarks it sees moved each by its own refinement. Inline,
        every keyframe is tracked after the previous one's refinement; this gives the deployed mode the same
        pose (on the 3000-frame town the un-relocalised keyframes made the drift closed by the loop 14 % larger
        than inline). Its own new landmarks, made from its pose, move with it (LandmarkMap.apply)."""
        t = self._kf_tracked
        if t is None or t.kf_id != self._last_kf_id:
            return None
        cfg = self.cfg.tracking
        p_ok, l_ok = self.map.point_alive(t.point_ids), self.map.line_alive(t.line_ids)
        P, L = self.map.point_positions(t.point_ids[p_ok]), self.map.line_endpoints(t.line_ids[l_ok])
        T_before = self.map.keyframe_pose(t.kf_id)
        T, p_in, l_in = refine_pose(self.K, T_before, P, t.uv[p_ok], L, t.segments[l_ok], cfg)
        if int(p_in.sum() + l_in.sum()) < cfg.min_pnp_inliers:
            return None
        ids = np.array([t.kf_id], np.int64)
        return MapCorrection(RELOCALISED, ids, T_before[None], snap_pose(T)[None])

    def _reanchor_to_map(self, prev: _FrameState) -> None:
        """Follow the back end: when it moved the last keyframe, move the previous frame's pose rigidly with it."""
        if self._last_kf_id < 0 or self._last_kf_pose_seen is None:
            return
        T_kf = self.map.keyframe_pose(self._last_kf_id)
        if np.allclose(T_kf, self._last_kf_pose_seen, atol=1e-12):
            return
        prev.T_world_cam = T_kf @ se3.inv(self._last_kf_pose_seen) @ prev.T_world_cam
        if self._held is not None:
            self._held = T_kf @ se3.inv(self._last_kf_pose_seen) @ self._held
        self._last_kf_pose_seen = T_kf

    # ---- keyframes and landmarks -------------------------------------------------------------------------
    def _initialise(self, frame: Frame, feats: FeatureSet, T: np.ndarray, status: str, reason: KeyframeWhy,
                    msg: str, timings: dict[str, float], corr: Correspondences | None = None) -> FrontendResult:
        """A keyframe whose landmarks all come from the current lidar depth (first frame, or after a loss)."""
        state = _FrameState(frame.index, feats, np.array(T, dtype=float),
                            FrameAssociation.empty(feats.n_points, feats.n_lines),
                            np.full(feats.n_points, -1, np.int64))
        t = time.perf_counter()
        keyframe, n_new = self._make_keyframe(frame, state, reason, from_lidar=True)
        timings["keyframe"] = time.perf_counter() - t
        log.info("frame %d: %s; %d point and %d line landmarks from lidar depth", frame.index, reason, *n_new)
        self._prev = state
        if corr is None:
            corr = self._correspondences(state, feats, _no_matches(), _no_matches())
        return self._result(frame, state, status, msg, corr, timings, reason=reason, n_new=n_new, keyframe=keyframe)

    def _make_keyframe(self, frame: Frame, state: _FrameState, reason: KeyframeWhy, from_lidar: bool
                       ) -> tuple[KeyframeInfo, tuple[int, int]]:
        kf_id = self.map.add_keyframe(frame.index, state.T_world_cam)
        assoc, feats = state.assoc, state.features
        priors: DepthPriors | None = None
        if from_lidar or self.cfg.tracking.use_depth_priors:
            priors = self._depth(prior_scan(frame, self._sweep(frame)), feats, self.calib, self.cfg.depth)
        # The observations carry this keyframe's depth priors: the back end and the global BA read them there.
        pi = np.flatnonzero(assoc.point_landmark >= 0)
        self.map.add_point_observations(assoc.point_landmark[pi], kf_id, pi, feats.keypoints[pi],
                                        None if priors is None else _point_prior(priors, pi),
                                        None if priors is None else _point_prior(priors, pi, "point_residual"))
        li = np.flatnonzero(assoc.line_landmark >= 0)
        self.map.add_line_observations(assoc.line_landmark[li], kf_id, li, feats.segments[li],
                                       None if priors is None else _line_prior(priors, li))
        self._kf_tracked = _TrackedAtKeyframe(kf_id, assoc.point_landmark[pi], feats.keypoints[pi],
                                              assoc.line_landmark[li], feats.segments[li])
        if priors is not None:
            n_new = self._landmarks_from_priors(kf_id, state, priors, lines=self.uses_lines)
        else:
            n_new = (self._landmarks_from_triangulation(kf_id, state), 0)
        self.policy.accept(frame.index, state.T_world_cam)
        state.kf_track = np.arange(feats.n_points)
        self._last_kf, self._last_kf_id = state, kf_id
        self._last_kf_input = frame
        self._recent_kfs.append(state)
        self._last_kf_pose_seen = state.T_world_cam.copy()
        log.info("frame %d: keyframe %d (%s): %d new point and %d new line landmarks", frame.index, kf_id, reason,
                 *n_new)
        info = KeyframeInfo(kf_id, frame.index, state.T_world_cam.copy(), frame, feats, priors,
                            assoc.point_landmark.copy(), assoc.line_landmark.copy(), reason, self._sweep(frame))
        return info, n_new

    def _sweep(self, frame: Frame) -> Sweep | None:
        """How the keyframe's scan is deskewed (plvo.lidar.deskew), as far as this frame tells: before the frame's
        time, the tracker's last motion (this frame's, or after a loss the prediction's) over the time since the
        previous frame (None at the first frame); the motion after it is the next frame's (`sweep_after`). None when
        the scan is not deskewed.
        A stated camera-lidar time offset (crosscheck.time_offset_s) adds to every return's time: the scan, taken
        that long after the image, is moved to the image's instant, for the depth priors and the workers."""
        deskewed = needs_deskew(frame, self.cfg.registration.deskew)
        if not deskewed and not self._offset_s:
            return None
        dt = None if self._prev_time is None else frame.time - self._prev_time
        before = None if dt is None or not dt > 0 else \
            twist_from_motion(self._velocity, dt, np.asarray(self.calib.T_cam_velo, float))
        if not self._offset_s:
            return Sweep(before, None, frame.scan_time)
        if not deskewed:
            times = np.zeros(len(frame.scan))
        else:
            times = azimuth_times(frame.scan) if frame.scan_time is None else np.asarray(frame.scan_time, float)
        # at the first frame no motion is known yet: the workers' scan then moves with the motion to the next
        # frame (`sweep_after`), the depth priors' stays as taken
        return Sweep(before, None, times + self._offset_s)

    def sweep_after(self, kf: KeyframeInfo, frame: Frame, T_world_cam: np.ndarray) -> Sweep | None:
        """Keyframe kf's sweep completed with the motion from it to the next frame (tracked at T_world_cam), from
        the keyframe's pose as the map has it now; as it was when the frames are not a positive time apart."""
        if kf.sweep is None or not frame.time > kf.frame.time:
            return kf.sweep
        T_step = se3.inv(self.map.keyframe_pose(kf.kf_id)) @ np.asarray(T_world_cam, float)
        return kf.sweep.with_after(twist_from_motion(T_step, frame.time - kf.frame.time,
                                                     np.asarray(self.calib.T_cam_velo, float)))

    def _landmarks_from_priors(self, kf_id: int, state: _FrameState, priors: DepthPriors, lines: bool
                               ) -> tuple[int, int]:
        assoc, feats, T = state.assoc, state.features, state.T_world_cam
        new_p = np.flatnonzero((assoc.point_landmark < 0) & priors.point_valid)
        pc = backproject(self.K, feats.keypoints[new_p], priors.point_depth[new_p])
        ids = self.map.add_points(se3.transform_points(T, pc), feats.descriptors[new_p], np.ones(len(new_p), bool),
                                  kf_id, new_p, feats.keypoints[new_p], _point_prior(priors, new_p),
                                  _point_prior(priors, new_p, "point_residual"))
        assoc.point_landmark[new_p] = ids
        if not lines:
            return len(new_p), 0
        new_l = np.flatnonzero((assoc.line_landmark < 0) & priors.line_valid
                               & np.isfinite(priors.line_endpoints).reshape(-1, 6).all(axis=1))
        ends = se3.transform_points(T, priors.line_endpoints[new_l].reshape(-1, 3)).reshape(-1, 2, 3)
        ids = self.map.add_lines(ends, feats.line_descriptors[new_l], np.ones(len(new_l), bool), kf_id, new_l,
                                 feats.segments[new_l], _line_prior(priors, new_l))
        assoc.line_landmark[new_l] = ids
        return len(new_p), len(new_l)

    def _landmarks_from_triangulation(self, kf_id: int, state: _FrameState) -> int:
        """No-depth-priors ablation: triangulate keypoints tracked since the previous keyframe."""
        last = self._last_kf
        if last is None:
            return 0
        j = np.flatnonzero((state.assoc.point_landmark < 0) & (state.kf_track >= 0))
        k = state.kf_track[j]
        k_free = last.assoc.point_landmark[k] < 0  # a keypoint already tied to a landmark lost it as an outlier
        j, k = j[k_free], k[k_free]
        uv0, uv1 = last.features.keypoints[k].astype(float), state.features.keypoints[j].astype(float)
        pw, ok = triangulate_tracks(self.K, last.T_world_cam, uv0, state.T_world_cam, uv1,
                                    self.cfg.tracking.outlier_reproj_px)
        j, k, pw = j[ok], k[ok], pw[ok]
        ids = self.map.add_points(pw, state.features.descriptors[j], np.zeros(len(j), bool), kf_id, j,
                                  state.features.keypoints[j])
        self.map.add_point_observations(ids, self._last_kf_id, k, uv0[ok])
        state.assoc.point_landmark[j] = ids
        return len(j)

    # ---- result ------------------------------------------------------------------------------------------
    def _result(self, frame: Frame, state: _FrameState, status: str, msg: str, corr: Correspondences,
                timings: dict[str, float], *, reason: KeyframeWhy | None = None, n_pm: int = 0, n_lm: int = 0,
                inliers: tuple[np.ndarray, np.ndarray] | None = None, n_new: tuple[int, int] = (0, 0),
                keyframe: KeyframeInfo | None = None,
                pnpl_residuals: tuple[np.ndarray, np.ndarray] = (_NONE, _NONE)) -> FrontendResult:
        """The frame's FrontendResult: what it was tracked against (corr), and, where they apply, the keyframe
        made (its reason, the landmarks it added), the frame-to-frame matches, the solver's inliers and residuals."""
        if inliers is None or status == REINITIALISED:
            inliers = (np.zeros(corr.n_points, bool), np.zeros(corr.n_lines, bool))
        p_in, l_in = inliers
        return FrontendResult(
            frame_index=frame.index, T_world_cam=state.T_world_cam.copy(), n_point_matches=n_pm,
            n_line_matches=n_lm, point_inliers=corr.point_features[p_in], line_inliers=corr.line_features[l_in],
            is_keyframe=keyframe is not None, ok=status != REINITIALISED, message=msg,
            T_world_cam0=state.T_world_cam @ self._T_cam_cam0, status=status, keyframe_reason=reason,
            point_uv=corr.point_pixels, point_landmark=corr.point_landmarks, point_inlier=p_in,
            line_segments=corr.line_segments, line_landmark=corr.line_landmarks, line_inlier=l_in,
            n_new_points=n_new[0], n_new_lines=n_new[1],
            association=FrameAssociation(state.assoc.point_landmark.copy(), state.assoc.line_landmark.copy()),
            features=state.features, keyframe=keyframe, timings=dict(timings),
            pnpl_point_residuals=pnpl_residuals[0], pnpl_line_residuals=pnpl_residuals[1],
        )


def prior_scan(frame: Frame, sweep: Sweep | None) -> np.ndarray:
    """The scan a keyframe's depth priors are fitted to: the frame's own, or where it is a raw sweep (sweep not
    None), its returns ahead of the lidar moved to the frame's instant with the motion before it. Those are the
    ones the camera sees, taken within ~13 ms of the frame's time (the sweep faces forward then), so the motion to
    the next frame, not known yet, is not needed; left as swept, a raw drive's returns in the image sit up to 0.13 m
    off, in opposite directions on the image's two sides (on the twin of raw drive 2011_09_26_drive_0009 the priors
    from the deskewed scan took the 10 / 20 / 40 m errors from 0.31 / 0.21 / 0.15 % to 0.28 / 0.18 / 0.13 %)."""
    if sweep is None or sweep.before is None:
        return frame.scan
    ahead = frame.scan[:, 0] > 0.0
    times = None if sweep.times is None else np.asarray(sweep.times)[ahead]
    return Sweep(sweep.before, None, times).apply(frame.scan[ahead])


def _point_prior(priors: DepthPriors, rows: np.ndarray, field: str = "point_depth") -> np.ndarray:
    """Depth prior z of keypoints rows (NaN where none), as the map stores it with each observation; or another of
    the priors' per-keypoint fields (the plane fit's rms, "point_residual")."""
    d = np.asarray(getattr(priors, field), float)
    out = np.full(len(rows), np.nan)
    ok = rows < len(d)
    out[ok] = d[rows[ok]]
    return out


def _line_prior(priors: DepthPriors, rows: np.ndarray) -> np.ndarray:
    """Camera-frame prior endpoints (n,2,3) of segments rows (NaN where none)."""
    e = np.asarray(priors.line_endpoints, float).reshape(-1, 2, 3)
    out = np.full((len(rows), 2, 3), np.nan)
    ok = rows < len(e)
    out[ok] = e[rows[ok]]
    return out


def _yaw(angle: float) -> np.ndarray:
    """(4,4) rotation by angle (rad) about the camera's y axis (the vertical of a forward-looking camera)."""
    c, s = np.cos(angle), np.sin(angle)
    T = np.eye(4)
    T[0, 0], T[0, 2], T[2, 0], T[2, 2] = c, s, -s, c
    return T


def _tracked(prev_landmark: np.ndarray, matches: Matches, alive: Callable[[np.ndarray], np.ndarray]
             ) -> tuple[np.ndarray, np.ndarray]:
    """Matches whose previous feature is tied to a live landmark -> (landmark ids, current feature indices)."""
    if not len(matches):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    lm, cur = prev_landmark[matches.pairs[:, 0]], matches.pairs[:, 1]
    lm, cur = lm[lm >= 0], cur[lm >= 0]
    ok = alive(lm)
    return lm[ok], cur[ok]


def _no_matches() -> Matches:
    return Matches(np.zeros((0, 2), np.int64), np.zeros(0))


def _remap(m: Matches, prev_rows: np.ndarray) -> Matches:
    """Matches of a subset of the previous features -> matches indexing the full set."""
    return Matches(np.c_[prev_rows[m.pairs[:, 0]], m.pairs[:, 1]].astype(np.int64).reshape(-1, 2), m.distance)


def _estimate_due(n: int) -> bool:
    """Whether the n-th interval added to an estimate (the time offset's, the extrinsic's) makes one: every 5th, every
    25th after 50 (an offset's estimate costs ~10-50 ms at a full window: ever rarer as the run goes)."""
    return n % (5 if n < 50 else 25) == 0
