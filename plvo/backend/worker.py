"""The back end as the System runs it (paper II-D, II-E): one call a keyframe, in a worker thread or inline.

For each keyframe K_i: register its scan to K_{i-1}'s (NDT seeded by the tracker's relative pose) -> a
relative-pose factor with information zeta diag(1/sigma_t^2 x3, 1/sigma_r^2 x3) (BackendConfig
sigma_relative_pose, sigma_relative_rotation_deg); scale correction of K_i alone (older keyframes fixed); then a
point-line bundle adjustment over the last `window_keyframes` keyframes (the oldest fixed). The refined poses and
landmarks are written into the shared LandmarkMap in one `apply_update`; the tracker follows them. A result that
moves a keyframe further than a registration may jump (RegistrationConfig.max_jump_*) is discarded.

Why the back end made seq 04 worse before issue 8's fixes, and what changed: the tracker's keyframe-to-keyframe
translation is ~1 % too long (depth-prior scale), NDT's is right to 0.1 %; but with the old 0.05 m / 0.05 rad base
sigma the relative-pose factor weighed ~1e-3 of the 0.1 px reprojection factors, so the BA kept the visual scale
and only added noise (1.22 / 1.12 / 1.04 % vs odometry's 1.05 / 0.90 / 0.84 %). With 0.5 mm / 0.5 mrad the BA
follows the registration's scale (0.73 / 0.57 / 0.40 %; KISS-ICP 0.74 / 0.63 / 0.55 %).

The scale correction runs before the bundle adjustment, as in the paper; in the concurrent back end its result
is written into the map at once, so the tracker has the corrected keyframe while the adjustment runs. Inline
(`concurrent = False`) the adjustment follows before the next frame and, weighing the same registration factor,
fixes the scale itself: there the step only gives it its start (ablation no_scale_step). Without the registration
(`registration = False`, with the scale correction the paper's Ours (#)) there are no relative-pose factors.

Thread, not process: the map is shared in memory and the heavy parts (open3d's NDT/ICP, scipy's SuperLU, numpy
on large arrays) release the GIL, so a thread overlaps with the tracker without copying the map. With
`BackendConfig.concurrent = False` the keyframe is processed before the tracker sees the next frame, which makes
a run deterministic (what the evaluation and most tests use).

Keyframes the tracker made while the worker was busy are moved rigidly with the newest optimised keyframe, and so
are the landmarks they created, so that the map never holds two inconsistent frames.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from plvo.backend.bundle_adjustment import optimize
from plvo.backend.problem import BAProblem, BAResult
from plvo.backend.scale_correction import correct_scale, scale_factor
from plvo.config import SystemConfig
from plvo.geometry import se3
from plvo.lidar.registration import PreparedScan, RegistrationResult, align, prepare
from plvo.results import EDGE_LOOP, EDGE_ODOMETRY, GraphResult, MapResult, MetricsResult
from plvo.tracking.keyframes import KeyframeInfo
from plvo.tracking.map import LandmarkMap
from plvo.types import Calibration
from plvo.workers import KeyframeWorker

log = logging.getLogger(__name__)


@dataclass
class _Edge:
    i: int  # keyframe ids
    j: int
    T_i_j: np.ndarray  # measured T_cam_i_cam_j
    zeta: float
    registration: RegistrationResult


@dataclass
class _KfData:
    """What the back end keeps of a keyframe: its scan for the next registration and its depth priors."""

    frame_index: int
    scan: PreparedScan | None  # downsampled once: the source of this keyframe's registration, the next one's target
    point_depth: np.ndarray | None  # (N,) z per feature, NaN none
    line_prior: np.ndarray | None  # (M,2,3) camera-frame endpoints per segment, NaN none


@dataclass(frozen=True)
class BackendStep:
    """What one keyframe cost and changed (also sent as MetricsResult)."""

    kf_id: int
    registration: RegistrationResult | None
    scale: float
    ba: BAResult | None
    seconds: dict[str, float] = field(default_factory=dict)


class Backend(KeyframeWorker):
    """Registration, scale correction and bundle adjustment of each keyframe against the shared map."""

    name = "back end"

    def __init__(self, calib: Calibration, config: SystemConfig, landmark_map: LandmarkMap):
        self.calib = calib
        self.cfg = config
        self.map = landmark_map
        self.K = np.asarray(calib.K, dtype=float)
        self.T_cam_velo = np.asarray(calib.T_cam_velo, dtype=float)
        self._kfs: dict[int, _KfData] = {}
        self._edges: list[_Edge] = []
        self._last_kf: int | None = None
        self.steps: list[BackendStep] = []
        self.loop_edges: list[tuple[int, int]] = []  # (match, query) keyframe ids, filled by the loop closer
        self.use_lines = not (config.tracking.points_only or not config.tracking.use_depth_priors)
        super().__init__(threaded=config.backend.concurrent)

    # ---- one keyframe ----------------------------------------------------------------------------------------
    def process(self, kf: KeyframeInfo) -> BackendStep:
        """Register, correct scale, bundle-adjust, write back into the map; returns what it did."""
        seconds: dict[str, float] = {}
        priors = kf.depth_priors
        t = time.perf_counter()
        registering = self.cfg.backend.registration
        self._kfs[kf.kf_id] = _KfData(
            kf.frame_index,
            prepare(kf.registration_scan, self.cfg.registration, f"frame {kf.frame_index} scan")
            if registering else None,
            None if priors is None else priors.point_depth, None if priors is None else priors.line_endpoints,
        )
        reg = None
        if registering and self._last_kf is not None:
            reg = self._register(self._last_kf, kf.kf_id)
            seconds["registration"] = time.perf_counter() - t
        prev_kf = self._last_kf
        self._forget_scan(prev_kf)
        self._last_kf = kf.kf_id
        scale, ba = 1.0, None
        window = self._window(kf.kf_id)
        if len(window) >= 2:
            problem, ids = self._problem(window)
            if problem is not None:
                newest = len(window) - 1
                if self.cfg.backend.scale_correction and reg is not None:
                    t = time.perf_counter()
                    before = problem.T_world_cam[newest].copy()
                    res = correct_scale(problem, newest, self.cfg.backend, **self._opt_kwargs())
                    if _sane(problem, res, self.cfg.registration):
                        problem = _with_values(problem, res)
                        scale = scale_factor(before, res.T_world_cam[newest], problem.T_world_cam[newest - 1])
                        if self.threaded:
                            # The paper corrects the scale before the keyframe reaches the bundle adjustment;
                            # here both run in this worker, so the tracker gets the corrected keyframe now
                            # rather than after the adjustment (100-200 ms, 1-2 frames, later).
                            self._write_back(window, ids, res)
                    seconds["scale_correction"] = time.perf_counter() - t
                t = time.perf_counter()
                ba = optimize(problem, self.cfg.backend, **self._opt_kwargs())
                seconds["bundle_adjustment"] = time.perf_counter() - t
                if _sane(problem, ba, self.cfg.registration):
                    self._write_back(window, ids, ba)
                else:
                    ba = None
        if "bundle_adjustment" in seconds:  # the design's budget is for the two together
            seconds["scale_correction_ba"] = seconds.get("scale_correction", 0.0) + seconds["bundle_adjustment"]
        seconds["backend"] = seconds.get("registration", 0.0) + seconds.get("scale_correction_ba", 0.0)
        step = BackendStep(kf.kf_id, reg, scale, ba, seconds)
        self.steps.append(step)
        self.add_timing(seconds)
        self.emit(kf.frame_index, *self._results_of(step, kf.frame_index))
        return step

    def registration_edges(self) -> list[tuple[int, int, np.ndarray, float]]:
        """Every relative-pose factor so far: (keyframe i, keyframe j, T_cam_i_cam_j, zeta) (for the global BA)."""
        return [(e.i, e.j, e.T_i_j, e.zeta) for e in list(self._edges)]

    def _opt_kwargs(self) -> dict:
        return {"use_depth_priors": self.cfg.tracking.use_depth_priors, "use_lines": self.use_lines,
                "stereo_baseline_m": self.cfg.backend.stereo_baseline_m}

    def _forget_scan(self, kf_id: int | None) -> None:
        # Only the newest scan is needed for the next registration; older ones would cost ~1 MB a keyframe.
        if kf_id is not None and kf_id in self._kfs:
            self._kfs[kf_id].scan = None

    def _register(self, i: int, j: int) -> RegistrationResult:
        """Align keyframe j's scan to keyframe i's, seeded by the tracker; record the relative-pose factor."""
        T_i, T_j = self.map.keyframe_pose(i), self.map.keyframe_pose(j)
        T_ci_cj = se3.inv(T_i) @ T_j
        T_vi_vj = se3.inv(self.T_cam_velo) @ T_ci_cj @ self.T_cam_velo
        reg = align(self._kfs[j].scan, self._kfs[i].scan, T_vi_vj, self.cfg.registration, self.T_cam_velo)
        zeta = reg.zeta if reg.converged else 0.0
        self._edges.append(_Edge(i, j, reg.T_camdst_camsrc, zeta, reg))
        log.debug("registration kf %d -> %d: %s, e_hat %.3f e_bar %.3f zeta %.3f (%.0f ms)", j, i, reg.method,
                  reg.e_hat, reg.e_bar, zeta, 1e3 * reg.time_s)
        return reg

    def _window(self, newest: int) -> list[int]:
        n = max(2, self.cfg.backend.window_keyframes)
        return [k for k in range(max(0, newest - n + 1), newest + 1) if k in self._kfs]

    # ---- the optimisation problem from the map ---------------------------------------------------------------
    def _problem(self, window: list[int]) -> tuple[BAProblem | None, dict]:
        """The window's keyframes, the landmarks they observe and their observations, as a BAProblem."""
        kf_row = {k: r for r, k in enumerate(window)}
        with self.map.lock:
            T = np.stack([self.map.keyframe_pose(k) for k in window])
            pobs = self.map.point_observations()
            lobs = self.map.line_observations() if self.use_lines else None
            pm = np.isin(pobs.keyframe, window)
            pt_ids = np.unique(pobs.landmark[pm])
            pts = self.map.point_positions(pt_ids)
            ln_ids = np.zeros(0, np.int64)
            lines = np.zeros((0, 2, 3))
            if lobs is not None:
                lm = np.isin(lobs.keyframe, window)
                ln_ids = np.unique(lobs.landmark[lm])
                lines = self.map.line_endpoints(ln_ids)
        if len(pt_ids) == 0:
            return None, {}
        pt_kf = np.array([kf_row[k] for k in pobs.keyframe[pm]], int)
        pt_depth = np.array([self._point_depth(k, f) for k, f in zip(pobs.keyframe[pm], pobs.feature[pm])])
        args = dict(
            K=self.K, T_world_cam=T, fixed=np.arange(len(window)) == 0, points=pts,
            pt_kf=pt_kf, pt_idx=np.searchsorted(pt_ids, pobs.landmark[pm]), pt_uv=pobs.measurement[pm],
            pt_depth=pt_depth,
        )
        if lobs is not None and len(ln_ids):
            lm = np.isin(lobs.keyframe, window)
            args.update(
                lines=lines, ln_kf=np.array([kf_row[k] for k in lobs.keyframe[lm]], int),
                ln_idx=np.searchsorted(ln_ids, lobs.landmark[lm]), ln_seg=lobs.measurement[lm],
                ln_prior=np.stack([self._line_prior(k, f) for k, f in zip(lobs.keyframe[lm], lobs.feature[lm])]),
            )
        edges = [e for e in self._edges if e.i in kf_row and e.j in kf_row]
        if edges:
            b = self.cfg.backend
            args.update(
                rel_ij=np.array([[kf_row[e.i], kf_row[e.j]] for e in edges], int),
                rel_T=np.stack([e.T_i_j for e in edges]), rel_zeta=np.array([e.zeta for e in edges]),
                rel_weight=np.r_[np.full(3, b.sigma_relative_pose**-2),
                                 np.full(3, np.radians(b.sigma_relative_rotation_deg) ** -2)],
            )
        return BAProblem(**args), {"points": pt_ids, "lines": ln_ids}

    def _point_depth(self, kf: int, feature: int) -> float:
        d = self._kfs[kf].point_depth
        return float(d[feature]) if d is not None and feature < len(d) else float("nan")

    def _line_prior(self, kf: int, feature: int) -> np.ndarray:
        p = self._kfs[kf].line_prior
        return p[feature] if p is not None and feature < len(p) else np.full((2, 3), np.nan)

    def _write_back(self, window: list[int], ids: dict, ba: BAResult) -> None:
        """Write the window into the map; move keyframes (and their landmarks) made meanwhile rigidly along."""
        with self.map.lock:
            # The window's first keyframe was held fixed. If the loop closer moved it while we optimised, the
            # result is rebased onto its new pose rather than undoing the loop correction.
            rebase = self.map.keyframe_pose(window[0]) @ se3.inv(ba.T_world_cam[0])
            ba_poses = rebase @ ba.T_world_cam
            newest = window[-1]
            correction = ba_poses[-1] @ se3.inv(self.map.keyframe_pose(newest))
            later = list(range(newest + 1, self.map.n_keyframes))
            kf_ids = window + later
            poses = list(ba_poses) + [correction @ self.map.keyframe_pose(k) for k in later]
            pt_ids, pts = ids["points"][ba.point_used], se3.transform_points(rebase, ba.points[ba.point_used])
            ln_ids = ids["lines"][ba.line_used]
            lns = se3.transform_points(rebase, ba.lines[ba.line_used].reshape(-1, 3)).reshape(-1, 2, 3)
            if later:
                new_p, new_l = self.map.landmarks_first_seen_after(newest)
                pt_ids = np.r_[pt_ids, new_p]
                pts = np.r_[pts, se3.transform_points(correction, self.map.point_positions(new_p))]
                ln_ids = np.r_[ln_ids, new_l]
                moved = se3.transform_points(correction, self.map.line_endpoints(new_l).reshape(-1, 3))
                lns = np.r_[lns, moved.reshape(-1, 2, 3)]
            self.map.apply_update(pt_ids, pts, ln_ids, lns, np.array(kf_ids), np.stack(poses))

    # ---- what the recorders see ------------------------------------------------------------------------------
    def _results_of(self, step: BackendStep, frame_index: int) -> list[object]:
        snap = self.map.snapshot()
        pairs = [(e.i, e.j) for e in self._edges] + list(self.loop_edges)
        kinds = [EDGE_ODOMETRY] * len(self._edges) + [EDGE_LOOP] * len(self.loop_edges)
        zeta = [e.zeta for e in self._edges] + [np.nan] * len(self.loop_edges)
        graph = GraphResult(
            frame_index=frame_index, keyframe_ids=snap.keyframe_ids, T_world_cam=snap.keyframe_T_world_cam,
            edges=np.array(pairs, int).reshape(-1, 2), edge_kind=np.array(kinds, int), zeta=np.array(zeta),
            scale=step.scale,
        )
        values = {f"backend_{k}_ms": 1e3 * v for k, v in step.seconds.items()}
        values["scale_factor"] = step.scale
        if step.registration is not None:
            r = step.registration
            values.update(zeta=r.zeta, e_hat=r.e_hat, e_bar=r.e_bar, ndt_fitness=r.fitness)
        if step.ba is not None:
            values.update(ba_initial_cost=step.ba.initial_cost, ba_final_cost=step.ba.final_cost,
                          ba_iterations=step.ba.iterations)
        # The local map (the window's landmarks, refined): the whole map every keyframe would make a recording of
        # a long sequence grow quadratically.
        if step.ba is not None:
            local = MapResult(frame_index, step.ba.points[step.ba.point_used], step.ba.lines[step.ba.line_used])
        else:
            local = MapResult(frame_index, snap.point_positions, snap.line_endpoints)
        return [graph, local,
                MetricsResult(frame_index, values)]


def _sane(problem: BAProblem, res: BAResult, reg_cfg) -> bool:
    """False (and a warning) when an optimisation moved a keyframe further than a registration may jump
    (max_jump_m / max_jump_deg) or produced non-finite values: such a result is discarded, not written."""
    ok = bool(np.all(np.isfinite(res.T_world_cam)) and np.all(np.isfinite(res.points[res.point_used])))
    for T0, T1 in zip(problem.T_world_cam, res.T_world_cam) if ok else ():
        move = se3.inv(T0) @ T1
        if np.linalg.norm(move[:3, 3]) > reg_cfg.max_jump_m or np.degrees(se3.rotation_angle(move)) > reg_cfg.max_jump_deg:
            ok = False
            break
    if not ok:
        log.warning("back end: an optimisation moved a keyframe by more than %.1f m / %.0f deg or diverged; discarded",
                    reg_cfg.max_jump_m, reg_cfg.max_jump_deg)
    return ok


def _with_values(problem: BAProblem, res: BAResult) -> BAProblem:
    return dataclasses.replace(problem, T_world_cam=res.T_world_cam, points=res.points, lines=res.lines)
