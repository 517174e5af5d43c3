"""What each stage of a plvo run saw and did, as statistics that can be set beside another run's (a real clip's
beside its twin's, plvo_eval.stage_report).

`StageStatsRecorder` is a recorder (plvo.recording.Recorder): the System hands it every stage's typed result and it
keeps only counts and residuals, cheaply, in the tracking thread. `StageStatsRecorder.summary()` turns them into
statistics; `backend_moves` and `drift_stats` add what the back end's stage record (RunOutput.stage_steps) and
plvo_eval.stage_drift say. Every statistic is one `describe`d entry: n (how many values), median and mean of the
finite values, and `value`, the figure to compare (the median of a distribution, the mean of a share or a rate, a
run's figure as it is). Per stage:

- features, per frame: ORB keypoints, line segments (the repaired LSD segments the tracker uses);
- matching, per tracked frame (not the first, not a re-initialisation): 2D-2D matches to the previous frame, 3D-2D
  correspondences (with the landmarks re-found by projection), PnPL inliers and their share of the correspondences;
  the PnPL inliers' reprojection residuals (px, pooled over every inlier of the run); the share of frames lost and
  of frames made keyframes;
- tracks: the share of landmarks tied to a feature in more than the frame that made them, and for those the frames
  and the keyframes they were tied to a feature in (censored at the run's end alike for every run of one length);
- depth priors, per keyframe: the share of its keypoints / segments with a prior, the share without one for each
  reason (plvo.types.DEPTH_REASONS), the lidar returns projected into the image; pooled over the priors, the plane's
  or line's RMS fit residual against the scan (m) and the returns it was fitted to;
- lidar alignment, per keyframe: e_hat (the residual at the tracker's pose), e_bar (at the registered pose), zeta,
  fitness, the share that failed, the scale correction (%, signed and its size);
- bundle adjustment, per keyframe: initial and final cost, their ratio, iterations; how far the scale correction and
  the adjustment moved the newest keyframe relative to the previous one (m, deg; from the stage record); how far a
  keyframe tracked before a refinement was moved when solved again on it (relocalised_m);
- drift, per stage of plvo_eval.stage_drift (tracker, scale, ba, final): heading (deg per 100 m) and scale (%) lost,
  as mean absolute stretch figures and as the run's signed bias. A heading offset of the truth against the sensors
  (a constant rotation about the vertical) leaves every step's yaw and length as they are: these figures do not see
  it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from plvo.depth.extract import DepthDebug
from plvo.geometry import se3
from plvo.recording import RunInfo, StageResult
from plvo.results import MetricsResult, StageSteps, TrackingResult
from plvo.types import (
    DEPTH_BAD_FIT,
    DEPTH_GRAZING_RAY,
    DEPTH_NOT_CONVERGED,
    DEPTH_OK,
    DEPTH_OUT_OF_RANGE,
    DEPTH_TOO_FEW_POINTS,
    DepthPriors,
    FeatureSet,
    Frame,
)

# Figure kinds: a distribution (compared by its median), a share or rate (its mean), a run's own figure, a signed
# figure (compared by value too, but a ratio of signed numbers says little: not flagged)
DISTRIBUTION, SHARE, FIGURE, SIGNED = "distribution", "share", "figure", "signed"

# DEPTH_* reason -> short key of the share statistics
REASON_KEYS = {DEPTH_TOO_FEW_POINTS: "too_few_points", DEPTH_BAD_FIT: "bad_fit", DEPTH_GRAZING_RAY: "grazing_ray",
               DEPTH_OUT_OF_RANGE: "out_of_range", DEPTH_NOT_CONVERGED: "not_converged"}


def describe(values: Iterable[float] | np.ndarray, stage: str, unit: str, kind: str = DISTRIBUTION) -> dict[str, Any]:
    """Values -> {stage, unit, kind, n, median, mean, value}: n the finite values, value the mean of a share, else
    the median (None without values)."""
    v = np.asarray(list(values) if not isinstance(values, np.ndarray) else values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    median = float(np.median(v)) if len(v) else None
    mean = float(np.mean(v)) if len(v) else None
    return {"stage": stage, "unit": unit, "kind": kind, "n": int(len(v)), "median": median, "mean": mean,
            "value": mean if kind == SHARE else median}


def figure(value: float | None, n: int, stage: str, unit: str, kind: str = FIGURE) -> dict[str, Any]:
    """A run's own figure (a drift over the run) as a statistic entry; n: what it stands on (steps)."""
    v = None if value is None or not np.isfinite(value) else float(value)
    return {"stage": stage, "unit": unit, "kind": kind, "n": int(n), "median": None, "mean": None, "value": v}


class _Tracks:
    """How many frames and keyframes each landmark id was tied to a feature in (ids are the map's, dense)."""

    def __init__(self) -> None:
        self.frames = np.zeros(0, np.int64)
        self.keyframes = np.zeros(0, np.int64)

    def add(self, ids: np.ndarray, keyframe: bool) -> None:
        ids = np.unique(ids[ids >= 0])
        if not len(ids):
            return
        if ids[-1] >= len(self.frames):
            grow = max(int(ids[-1]) + 1, 2 * len(self.frames))
            self.frames = np.r_[self.frames, np.zeros(grow - len(self.frames), np.int64)]
            self.keyframes = np.r_[self.keyframes, np.zeros(grow - len(self.keyframes), np.int64)]
        self.frames[ids] += 1
        if keyframe:
            self.keyframes[ids] += 1


class StageStatsRecorder:
    """A recorder gathering per-stage statistics of a run (see the module doc); `summary()` once the run is done.

    It reads the tracker's FrontendResult fields where the TrackingResult is one (the 3D-2D correspondences and
    each landmark tied to a feature) and falls back on the TrackingResult's own counts where it is not."""

    def __init__(self) -> None:
        self._reset()

    def _reset(self) -> None:
        self.lists: dict[str, list[float]] = {}
        self.pooled: dict[str, list[np.ndarray]] = {}
        self.point_tracks = _Tracks()
        self.line_tracks = _Tracks()
        self._first_tracking = True

    # ---- the Recorder protocol -------------------------------------------------------------------------------
    def on_run_start(self, info: RunInfo) -> None:
        pass

    def on_restart(self, info: RunInfo) -> None:
        self._reset()  # the statistics of the run that counts alone

    def on_frame(self, frame: Frame) -> None:
        pass

    def on_stage(self, frame_index: int, result: StageResult) -> None:
        if isinstance(result, FeatureSet):
            self._add("orb_keypoints", result.n_points)
            self._add("line_segments", result.n_lines)
        elif isinstance(result, TrackingResult):
            self._tracking(result)
        elif isinstance(result, DepthPriors):
            self._priors(result)
        elif isinstance(result, MetricsResult):
            self._metrics(result.values)
        elif isinstance(result, DepthDebug):
            self._add("lidar_points_in_image", len(result.scan_depth))

    def close(self) -> None:
        pass

    # ---- gathering -------------------------------------------------------------------------------------------
    def _add(self, name: str, value: float) -> None:
        self.lists.setdefault(name, []).append(float(value))

    def _pool(self, name: str, values: np.ndarray) -> None:
        self.pooled.setdefault(name, []).append(np.asarray(values, np.float64).ravel())

    def _tracking(self, r: TrackingResult) -> None:
        first, self._first_tracking = self._first_tracking, False
        status = getattr(r, "status", None)
        tracked = status == "tracked" if status is not None else (r.ok and not first)
        assoc = getattr(r, "association", None)
        if assoc is not None:
            self.point_tracks.add(np.asarray(assoc.point_landmark), r.is_keyframe)
            self.line_tracks.add(np.asarray(assoc.line_landmark), r.is_keyframe)
        if not first:
            self._add("lost", 0.0 if r.ok else 1.0)
            self._add("keyframe_share", float(r.is_keyframe))
        if not tracked:
            return
        n_pin, n_lin = len(r.point_inliers), len(r.line_inliers)
        # the 3D-2D correspondences PnPL and the search judged (FrontendResult); else the 2D-2D matches
        n_pc = len(r.point_inlier) if hasattr(r, "point_inlier") else r.n_point_matches
        n_lc = len(r.line_inlier) if hasattr(r, "line_inlier") else r.n_line_matches
        for name, value in (("point_matches", r.n_point_matches), ("line_matches", r.n_line_matches),
                            ("point_correspondences", n_pc), ("line_correspondences", n_lc),
                            ("point_inliers", n_pin), ("line_inliers", n_lin)):
            self._add(name, value)
        if n_pc:
            self._add("point_inlier_ratio", n_pin / n_pc)
        if n_lc:
            self._add("line_inlier_ratio", n_lin / n_lc)
        self._pool("pnpl_point_residual_px", r.pnpl_point_residuals)
        self._pool("pnpl_line_residual_px", r.pnpl_line_residuals)

    def _priors(self, p: DepthPriors) -> None:
        for kind, reason, residual, support in (("point", p.point_reason, p.point_residual, p.point_inliers),
                                                ("line", p.line_reason, p.line_residual, p.line_inliers)):
            reason = np.asarray(reason)
            if not len(reason):
                continue
            ok = reason == DEPTH_OK
            self._add(f"{kind}_prior_coverage", float(ok.mean()))
            for code, key in REASON_KEYS.items():
                self._add(f"{kind}_prior_missing_{key}", float((reason == code).mean()))
            self._pool(f"{kind}_prior_residual_m", np.asarray(residual, np.float64)[ok])
            self._pool(f"{kind}_prior_lidar_points", np.asarray(support, np.float64)[ok])

    def _metrics(self, values: Mapping[str, float]) -> None:
        if "relocalised_m" in values:
            self._add("relocalised_m", values["relocalised_m"])
        if "scale_factor" not in values:  # not the back end's per-keyframe figures (the loop closer's)
            return
        if "e_bar" in values:  # a keyframe registered (the first has nothing to register to, nor to correct)
            self._add("scale_correction_pct", 100.0 * (values["scale_factor"] - 1.0))
            self._add("scale_correction_abs_pct", 100.0 * abs(values["scale_factor"] - 1.0))
            failed = not np.isfinite(values["e_bar"])
            self._add("registration_failed", float(failed))
            for key, name in (("e_hat", "registration_e_hat_m"), ("e_bar", "registration_e_bar_m"),
                              ("zeta", "registration_zeta"), ("ndt_fitness", "registration_fitness")):
                if not failed:
                    self._add(name, values[key])
        if "ba_initial_cost" in values:
            c0, c1 = values["ba_initial_cost"], values["ba_final_cost"]
            self._add("ba_initial_cost", c0)
            self._add("ba_final_cost", c1)
            self._add("ba_iterations", values.get("ba_iterations", np.nan))
            if c0 > 0:
                self._add("ba_cost_ratio", c1 / c0)

    # ---- the statistics --------------------------------------------------------------------------------------
    def summary(self) -> dict[str, dict[str, Any]]:
        """Statistic name -> describe() entry, in the order of the stages (see the module doc)."""
        out: dict[str, dict[str, Any]] = {}

        def put(name: str, stage: str, unit: str, kind: str = DISTRIBUTION) -> None:
            values = (np.concatenate(self.pooled[name]) if self.pooled.get(name) else np.zeros(0)) \
                if name in _POOLED else self.lists.get(name, [])
            out[name] = describe(values, stage, unit, kind)

        put("orb_keypoints", "features", "per frame")
        put("line_segments", "features", "per frame")
        for name in ("point_matches", "line_matches", "point_correspondences", "line_correspondences",
                     "point_inliers", "line_inliers"):
            put(name, "matching", "per tracked frame")
        put("point_inlier_ratio", "matching", "inliers / correspondences")
        put("line_inlier_ratio", "matching", "inliers / correspondences")
        put("pnpl_point_residual_px", "PnPL", "px, every inlier")
        put("pnpl_line_residual_px", "PnPL", "px, every inlier")
        put("lost", "PnPL", "share of frames", SHARE)
        put("keyframe_share", "keyframes", "share of frames", SHARE)
        for kind, tracks in (("point", self.point_tracks), ("line", self.line_tracks)):
            # most landmarks are never found again after the keyframe that made them: their share, then the
            # lengths of the others (a median over all would be 1 on every run)
            seen, tracked = tracks.frames > 0, tracks.frames > 1
            out[f"{kind}_tracked_share"] = describe(tracked[seen].astype(float), "tracks",
                                                    "share of landmarks tracked beyond their first frame", SHARE)
            out[f"{kind}_track_frames"] = describe(tracks.frames[tracked], "tracks", "frames a tracked landmark")
            out[f"{kind}_track_keyframes"] = describe(tracks.keyframes[tracked], "tracks",
                                                      "keyframes a tracked landmark")
        put("lidar_points_in_image", "depth priors", "returns a keyframe")
        for kind in ("point", "line"):
            put(f"{kind}_prior_coverage", "depth priors", "share a keyframe", SHARE)
            for key in REASON_KEYS.values():
                put(f"{kind}_prior_missing_{key}", "depth priors", "share a keyframe", SHARE)
            put(f"{kind}_prior_residual_m", "depth priors", "m RMS, every prior")
            put(f"{kind}_prior_lidar_points", "depth priors", "returns a prior")
        put("registration_e_hat_m", "lidar alignment", "m a keyframe")
        put("registration_e_bar_m", "lidar alignment", "m a keyframe")
        put("registration_zeta", "lidar alignment", "a keyframe")
        put("registration_fitness", "lidar alignment", "a keyframe")
        put("registration_failed", "lidar alignment", "share of keyframes", SHARE)
        put("scale_correction_pct", "scale correction", "% a keyframe", SIGNED)
        put("scale_correction_abs_pct", "scale correction", "% a keyframe")
        put("ba_initial_cost", "bundle adjustment", "a keyframe")
        put("ba_final_cost", "bundle adjustment", "a keyframe")
        put("ba_cost_ratio", "bundle adjustment", "final / initial")
        put("ba_iterations", "bundle adjustment", "a keyframe")
        put("relocalised_m", "bundle adjustment", "m a relocalised keyframe")
        return out


_POOLED = {"pnpl_point_residual_px", "pnpl_line_residual_px", "point_prior_residual_m", "line_prior_residual_m",
           "point_prior_lidar_points", "line_prior_lidar_points"}


def backend_moves(stage_steps: Iterable[StageSteps]) -> dict[str, dict[str, Any]]:
    """The back end's stage record (RunOutput.stage_steps: per keyframe, stage -> T_prev_new (4,4)) -> how far the
    scale correction moved the newest keyframe relative to the previous one (from the tracker's), and how far the
    bundle adjustment moved it (from the scale correction's, else the tracker's), in m and deg."""
    moves: dict[str, list[float]] = {"scale_move_m": [], "scale_move_deg": [], "ba_move_m": [], "ba_move_deg": []}
    for entry in stage_steps:
        steps = entry.steps
        before = steps.get("tracker")
        for stage in ("scale", "ba"):
            after = steps.get(stage)
            if before is not None and after is not None:
                d = se3.inv(np.asarray(before)) @ np.asarray(after)
                moves[f"{stage}_move_m"].append(float(np.linalg.norm(np.asarray(after)[:3, 3]
                                                                     - np.asarray(before)[:3, 3])))
                moves[f"{stage}_move_deg"].append(float(np.degrees(se3.rotation_angle(d))))
            if after is not None:
                before = after
    stages = {"scale": "scale correction", "ba": "bundle adjustment"}
    return {name: describe(v, stages[name.split("_")[0]], "m a keyframe" if name.endswith("_m") else "deg a keyframe")
            for name, v in moves.items()}


_DRIFT_FIELDS = (("yaw_deg_per_100m", "deg / 100 m", FIGURE), ("scale_pct", "%", FIGURE),
                 ("pitch_deg_per_100m", "deg / 100 m", FIGURE), ("yaw_bias_deg_per_100m", "deg / 100 m", SIGNED),
                 ("scale_bias_pct", "%", SIGNED))


def drift_stats(drift: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """plvo_eval.stage_drift's stage -> summary -> drift_<stage>_<field> entries (n: the steps it stands on)."""
    out = {}
    for stage, summary in drift.items():
        for key, unit, kind in _DRIFT_FIELDS:
            out[f"drift_{stage}_{key}"] = figure(summary.get(key), int(summary.get("steps", 0)), f"drift: {stage}",
                                                 unit, kind)
    return out
