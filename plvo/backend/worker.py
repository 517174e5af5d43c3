"""The back end as the System runs it (paper II-D, II-E): one job a keyframe, a pure function of the jobs in order.

For each keyframe K_i: register its scan to K_{i-1}'s (NDT seeded by the tracker's relative pose) -> a
relative-pose factor with information zeta diag(1/sigma_t^2 x3, 1/sigma_r^2 x3) (BackendConfig
sigma_relative_pose, sigma_relative_rotation_deg); scale correction of K_i alone (older keyframes fixed); then a
point-line bundle adjustment over the last `window_keyframes` keyframes (the oldest fixed). A result that moves a
keyframe further than a registration may jump (RegistrationConfig.max_jump_*) is discarded.

The back end never touches the map. The System reads the window at the keyframe (`LandmarkMap.window_data`) into a
`BackendJob`; `BackendCore.process` returns a `BackendOutput` whose `MapCorrection` (window poses before and after,
refined landmarks, the new registration edge) the System applies at a fixed frame (plvo.runtime.system). The core keeps
only the previous keyframe's prepared scan, the next registration's target, so it can run inline, in a thread or in
a worker process (plvo.runtime.workers) and give the same result.

Why the relative-pose factor's base sigma is so small: the tracker's keyframe-to-keyframe translation is ~1 % too
long (depth-prior scale), NDT's is right to 0.1 %; with a 0.05 m / 0.05 rad base sigma the relative-pose factor
weighs ~1e-3 of the 0.1 px reprojection factors, so the BA keeps the visual scale and only adds noise (1.22 / 1.12 /
1.04 % on seq 04 against odometry's 1.05 / 0.90 / 0.84 %). With 0.5 mm it follows the registration's scale (0.73 /
0.57 / 0.40 %; KISS-ICP 0.74 / 0.63 / 0.55 %; docs/results/defaults.md).

The scale correction runs before the bundle adjustment, as in the paper, and gives it its start; weighing the same
registration factor, the adjustment would fix the scale itself (ablation no_scale_step). Without the registration
(`registration = False`, with the scale correction the paper's Ours (#)) there are no relative-pose factors.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from plvo.backend.bundle_adjustment import optimize
from plvo.backend.problem import BAProblem, BAResult, depth_prior_sigmas, relative_pose_information
from plvo.backend.scale_correction import correct_scale, scale_factor
from plvo.config import BackendConfig, BackendSections, RegistrationConfig
from plvo.geometry import se3
from plvo.lidar.local_map import LocalMap
from plvo.lidar.registration import PreparedScan, RegistrationResult, SparseScan, align, prepare
from plvo.results import EdgeKind
from plvo.tracking.corrections import BACKEND, GraphEdge, MapCorrection, WindowData
from plvo.types import Calibration

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BackendJob:
    """One keyframe for the back end: its id and frame, its registration scan (lidar frame, deskewed where the
    data needs it (plvo.runtime.system), None without registration) and the window of the map ending at it (read when
    the keyframe was made)."""

    kf_id: int
    frame_index: int
    scan: np.ndarray | None
    window: WindowData

    def with_scan(self, scan: np.ndarray) -> BackendJob:
        """The job with its registration scan replaced (by the deskewed one); a job without a scan as it is."""
        return self if self.scan is None else dataclasses.replace(self, scan=scan)


@dataclass(frozen=True)
class BackendStep:
    """What one keyframe cost and changed (also sent as MetricsResult)."""

    kf_id: int
    registration: RegistrationResult | None
    scale: float
    ba: BAResult | None
    seconds: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class BackendOutput:
    """The back end's answer for one job: the correction for the map (None when nothing changed), what it did, the
    window's refined landmarks (points (P,3), lines (L,2,3), world, for the viewers) and its metrics."""

    kf_id: int
    frame_index: int
    correction: MapCorrection | None
    step: BackendStep
    points: np.ndarray
    lines: np.ndarray
    metrics: dict[str, float]
    # the previous and the newest keyframe's T_world_cam ((2,4,4)) as each stage left them: "tracker" (the window's,
    # before the back end), "scale" (after the scale correction), "ba" (after the bundle adjustment); a stage that
    # did not run or whose result was discarded is absent. Their relative motion is what the stage made of the
    # newest keyframe step; the evaluation's per-stage drift reads it. stage_kf_ids: those two keyframes' ids.
    stage_poses: dict[str, np.ndarray] = field(default_factory=dict)
    stage_kf_ids: tuple[int, ...] = ()


class BackendCore:
    """Registration, scale correction and bundle adjustment of each keyframe's window (see the module doc)."""

    def __init__(self, calib: Calibration, config: BackendSections):
        self.cfg = config
        self.K = np.asarray(calib.K, dtype=float)
        self.T_cam_velo = np.asarray(calib.T_cam_velo, dtype=float)
        self.use_lines = not (config.tracking.points_only or not config.tracking.use_depth_priors)
        self._last: tuple[int, PreparedScan] | None = None  # the previous keyframe's id and prepared scan
        # {kf_id: (the window pose it was given, the pose this core answered)} for the last window's keyframes: the
        # map applies an answer at a fixed frame, which can come after the next keyframe's window is read (a keyframe
        # every frame while the tracker is lost), so a window may still hold poses this core has already corrected
        self._answered: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._frame_of: dict[int, int] = {}  # the window keyframes' frame indices (for the lidar's own prediction)
        b = config.backend
        self._local_map = LocalMap(b.local_map_keyframes, b.local_map_voxel_m, config.registration,
                                   b.local_map_source_points) \
            if b.lidar_target == "local_map" else None

    def idle(self) -> None:
        """Work for the next job done while no job waits (plvo.runtime.workers calls it between a worker process's
        jobs): the newest keyframe's scan downsampled for the local map, which the next registration would do first."""
        if self._local_map is not None:
            self._local_map.prepare()

    def process(self, job: BackendJob) -> BackendOutput:
        """Register, correct scale, bundle-adjust one window -> BackendOutput (the map is not touched)."""
        seconds: dict[str, float] = {}
        w = job.window
        t = time.perf_counter()
        reg, edge = None, None
        in_window = set(w.kf_ids.tolist())
        self._frame_of = {k: f for k, f in self._frame_of.items() if k in in_window}
        self._frame_of[int(job.kf_id)] = int(job.frame_index)
        known = self._known_poses(w)
        scan = None
        if self.cfg.backend.registration and job.scan is not None:
            try:
                scan = prepare(job.scan, self.cfg.registration, f"frame {job.frame_index} scan")
            except SparseScan as exc:  # this keyframe goes without a lidar factor; the next ones register again
                log.warning("back end: keyframe %d: %s; not registered", job.kf_id, exc)
        if scan is not None:
            if self._local_map is not None:
                reg, edge = self._register_to_map(w, job.kf_id, scan, known)
                seconds["registration"] = time.perf_counter() - t
            elif self._last is not None and self._last[0] in in_window:
                reg, edge = self._register(w, self._last, (job.kf_id, scan))
                seconds["registration"] = time.perf_counter() - t
            self._last = (job.kf_id, scan)
        scale, ba, after = 1.0, None, None
        stage_poses: dict[str, np.ndarray] = {"tracker": w.T_world_cam[-2:].copy()} \
            if len(w.kf_ids) >= 2 else {}
        problem = _problem(w, self.K, self.cfg.backend, (edge,) if edge is not None else ()) if len(w.kf_ids) >= 2 \
            else None
        if problem is not None:
            newest = len(w.kf_ids) - 1
            if self.cfg.backend.scale_correction and reg is not None:
                t = time.perf_counter()
                before = problem.T_world_cam[newest].copy()
                res = correct_scale(problem, newest, self.cfg.backend, **self._opt_kwargs())
                if _sane(problem, res, self.cfg.registration):
                    problem = _with_values(problem, res)
                    scale = scale_factor(before, res.T_world_cam[newest], problem.T_world_cam[newest - 1])
                    after = res
                    stage_poses["scale"] = res.T_world_cam[newest - 1:newest + 1].copy()
                seconds["scale_correction"] = time.perf_counter() - t
            t = time.perf_counter()
            ba = optimize(problem, self.cfg.backend, **self._opt_kwargs())
            seconds["bundle_adjustment"] = time.perf_counter() - t
            if _sane(problem, ba, self.cfg.registration):
                after = ba
                stage_poses["ba"] = ba.T_world_cam[newest - 1:newest + 1].copy()
            else:
                ba = None
        if "bundle_adjustment" in seconds:  # the design's budget is for the two together
            seconds["scale_correction_ba"] = seconds.get("scale_correction", 0.0) + seconds["bundle_adjustment"]
        seconds["backend"] = seconds.get("registration", 0.0) + seconds.get("scale_correction_ba", 0.0)
        step = BackendStep(job.kf_id, reg, scale, ba, seconds)
        correction = self._correction(w, after, edge)
        self._remember(w, in_window, known, after, reg)
        if after is not None:
            points, lines = after.points[after.point_used], after.lines[after.line_used]
        else:
            points, lines = w.points, w.lines
        return BackendOutput(job.kf_id, job.frame_index, correction, step, points, lines, _metrics(step), stage_poses,
                             tuple(int(k) for k in w.kf_ids[-2:]))

    def _known_poses(self, w: WindowData) -> np.ndarray:
        """The window's poses (K,4,4) as this core knows them: a keyframe whose window pose is still the one it was
        given last time takes the pose answered then (the map has not applied that answer yet); the keyframes after
        it that were not answered (the newest) move with it, since the tracker placed them relative to it."""
        T = np.array(w.T_world_cam, float)
        carry = None  # identity: nothing is multiplied, so a window the map is up to date with stays bit for bit
        for r, k in enumerate(w.kf_ids):
            seen = self._answered.get(int(k))
            if seen is None:
                if carry is not None:
                    T[r] = carry @ T[r]
            elif np.array_equal(T[r], seen[0]) and not np.array_equal(seen[0], seen[1]):
                T[r], carry = seen[1], seen[1] @ se3.inv(seen[0])
            else:  # up to date: the answer applied (or a loop's correction since), or nothing to apply
                carry = None
        return T

    def _remember(self, w: WindowData, in_window: set[int], known: np.ndarray, after: BAResult | None,
                  reg: RegistrationResult | None) -> None:
        """What this job answered for its window's keyframes: the optimised poses, or without an optimisation the
        newest keyframe's registered pose from the previous one's known pose (a window without landmarks, while the
        tracker is lost)."""
        if after is not None:
            self._answered = {int(k): (w.T_world_cam[r].copy(), after.T_world_cam[r].copy())
                              for r, k in enumerate(w.kf_ids)}
            return
        self._answered = {k: v for k, v in self._answered.items() if k in in_window}
        if reg is not None and reg.converged and reg.method == "local_map" and len(w.kf_ids) >= 2:
            self._answered[int(w.kf_ids[-1])] = (w.T_world_cam[-1].copy(), known[-2] @ reg.T_camdst_camsrc)

    def _opt_kwargs(self) -> dict:
        return {"use_depth_priors": self.cfg.tracking.use_depth_priors, "use_lines": self.use_lines,
                "stereo_baseline_m": self.cfg.backend.stereo_baseline_m}

    def _register(self, w: WindowData, src_i: tuple[int, PreparedScan], src_j: tuple[int, PreparedScan]
                  ) -> tuple[RegistrationResult, GraphEdge]:
        """Align keyframe j's scan to keyframe i's, seeded by the window's poses -> result and graph edge."""
        (i, scan_i), (j, scan_j) = src_i, src_j
        row = {int(k): r for r, k in enumerate(w.kf_ids)}
        T_ci_cj = se3.inv(w.T_world_cam[row[i]]) @ w.T_world_cam[row[j]]
        T_vi_vj = se3.inv(self.T_cam_velo) @ T_ci_cj @ self.T_cam_velo
        reg = align(scan_j, scan_i, T_vi_vj, self.cfg.registration, self.T_cam_velo)
        zeta = reg.zeta if reg.converged else 0.0
        log.debug("registration kf %d -> %d: %s, e_hat %.3f e_bar %.3f zeta %.3f (%.0f ms)", j, i, reg.method,
                  reg.e_hat, reg.e_bar, zeta, 1e3 * reg.time_s)
        return reg, registration_edge(i, j, reg.T_camdst_camsrc, zeta, reg.e_bar, self.cfg.backend)

    def _register_to_map(self, w: WindowData, kf_id: int, scan: PreparedScan, T_world_cam: np.ndarray
                         ) -> tuple[RegistrationResult | None, GraphEdge | None]:
        """Align the newest keyframe's scan to the local map of the recent keyframes' scans, placed at the window's
        poses as this core knows them (T_world_cam, _known_poses), from the tracker's pose (and from the lidar's
        constant-velocity prediction when that alignment moved it suspiciously far, LocalMap.align_best) -> the
        result and the graph edge from the window's previous keyframe, which the map holds at its pose (so the edge
        says where the map puts the new keyframe); then the scan joins the map at the registered pose (at the
        tracker's when the alignment failed)."""
        lmap = self._local_map
        assert lmap is not None
        T_cv = self.T_cam_velo
        T_world_lidar = T_world_cam @ T_cv
        lmap.place(w.kf_ids, T_world_lidar)
        init = T_world_lidar[-1]
        reg = edge = None
        prev = len(w.kf_ids) - 2
        if len(lmap) and prev >= 0 and int(w.kf_ids[prev]) in set(lmap.kf_ids):
            al = lmap.align_best(np.asarray(scan.cloud.points), [init, *self._constant_velocity(w, T_world_lidar)])
            T_prev_new = se3.inv(T_world_lidar[prev]) @ al.T_world_lidar
            reg = RegistrationResult(
                T_dst_src=T_prev_new, T_camdst_camsrc=se3.conjugate(T_cv, T_prev_new), e_hat=al.e_hat,
                e_bar=al.e_bar, zeta=al.zeta, method="local_map", converged=al.converged, fitness=al.fitness,
                time_s=al.time_s)
            if not al.converged:
                log.info("registration of keyframe %d to the local map failed: %s", kf_id, al.why)
            edge = registration_edge(int(w.kf_ids[prev]), kf_id, reg.T_camdst_camsrc,
                                     al.zeta if al.converged else 0.0, al.e_bar, self.cfg.backend)
            log.debug("local map kf %d: e_hat %.3f e_bar %.3f zeta %.3f fitness %.2f (%.0f ms, %d map points)", kf_id,
                      al.e_hat, al.e_bar, al.zeta, al.fitness, 1e3 * al.time_s, al.n_map)
            if al.converged:
                init = al.T_world_lidar
        lmap.add(kf_id, np.asarray(scan.fine.points), init)
        return reg, edge

    def _constant_velocity(self, w: WindowData, T_world_lidar: np.ndarray) -> list[np.ndarray]:
        """The newest keyframe's lidar pose as the two keyframes before it predict it (their motion a frame,
        continued over the frames since) -> [T_world_lidar], or [] without three window keyframes of known frames."""
        if len(w.kf_ids) < 3:
            return []
        f = [self._frame_of.get(int(k), -1) for k in w.kf_ids[-3:]]
        if not 0 <= f[0] < f[1] < f[2]:
            return []
        step = se3.log(se3.inv(T_world_lidar[-3]) @ T_world_lidar[-2]) / (f[1] - f[0])
        return [T_world_lidar[-2] @ se3.exp(step * (f[2] - f[1]))]

    def _correction(self, w: WindowData, res: BAResult | None, edge: GraphEdge | None) -> MapCorrection | None:
        edges = (edge,) if edge is not None else ()
        if res is None:
            if not edges:
                return None
            return MapCorrection(BACKEND, np.zeros(0, np.int64), np.zeros((0, 4, 4)), np.zeros((0, 4, 4)),
                                 edges=edges, base_version=w.version)
        return MapCorrection(
            BACKEND, w.kf_ids, w.T_world_cam, res.T_world_cam,
            point_ids=w.point_ids[res.point_used], point_positions=res.points[res.point_used],
            line_ids=w.line_ids[res.line_used], line_endpoints=res.lines[res.line_used], edges=edges,
            base_version=w.version)


def residual_weight(e_bar: float, b: BackendConfig, power: float | None = None) -> float:
    """The information factor of a registration edge whose alignment left a residual of e_bar metres (its mean
    point-to-plane distance): (relative_pose_residual_m / e_bar)^(2 power), so that the factor's standard
    deviations are sigma_relative_pose (power: relative_pose_residual_power, the default) or
    sigma_relative_rotation_deg (relative_rotation_residual_power) times (e_bar / relative_pose_residual_m)^power;
    1 where e_bar is unknown (a failed alignment, whose zeta is 0)."""
    power = b.relative_pose_residual_power if power is None else power
    if not (np.isfinite(e_bar) and e_bar > 0) or power == 0:
        return 1.0
    return float((b.relative_pose_residual_m / e_bar) ** (2.0 * power))


def registration_edge(i: int, j: int, T_i_j: np.ndarray, zeta: float, e_bar: float, b: BackendConfig) -> GraphEdge:
    """The odometry edge of a registration, its translation and rotation weighed by the alignment's residual."""
    return GraphEdge(i, j, T_i_j, zeta, EdgeKind.ODOMETRY, residual_weight(e_bar, b),
                     residual_weight(e_bar, b, b.relative_rotation_residual_power))


def edge_information(edges: Sequence[GraphEdge], b: BackendConfig) -> np.ndarray:
    """BAProblem.rel_weight of the edges' factors, beside their `information` (zeta * weight): one row each, its
    rotation's scaled by the edge's rotation_ratio."""
    return relative_pose_information(b.sigma_relative_pose, b.sigma_relative_rotation_deg,
                                     [e.rotation_ratio for e in edges])


def _problem(w: WindowData, K: np.ndarray, b: BackendConfig, new_edges: tuple[GraphEdge, ...]) -> BAProblem | None:
    """The window as a BAProblem (its first keyframe fixed), with the graph's and the new relative-pose edges."""
    if len(w.point_ids) == 0:
        return None
    args = dict(K=K, T_world_cam=w.T_world_cam, fixed=np.arange(len(w.kf_ids)) == 0, points=w.points,
                pt_kf=w.pt_kf, pt_idx=w.pt_idx, pt_uv=w.pt_uv, pt_depth=w.pt_depth,
                pt_depth_sigma=depth_prior_sigmas(w.pt_depth_rms, b.depth_prior_rms_factor))
    if len(w.line_ids):
        args.update(lines=w.lines, ln_kf=w.ln_kf, ln_idx=w.ln_idx, ln_seg=w.ln_seg, ln_prior=w.ln_prior)
    row = {int(k): r for r, k in enumerate(w.kf_ids)}
    edges = [e for e in (*w.edges, *new_edges) if e.kind == EdgeKind.ODOMETRY and e.i in row and e.j in row]
    if edges:
        args.update(
            rel_ij=np.array([[row[e.i], row[e.j]] for e in edges], int),
            rel_T=np.stack([e.T_i_j for e in edges]), rel_zeta=np.array([e.information for e in edges]),
            rel_weight=edge_information(edges, b),
        )
    return BAProblem(**args)


def _metrics(step: BackendStep) -> dict[str, float]:
    values = {f"backend_{k}_ms": 1e3 * v for k, v in step.seconds.items()}
    values["scale_factor"] = step.scale
    if step.registration is not None:
        r = step.registration
        values.update(zeta=r.zeta, e_hat=r.e_hat, e_bar=r.e_bar, ndt_fitness=r.fitness)
    if step.ba is not None:
        values.update(ba_initial_cost=step.ba.initial_cost, ba_final_cost=step.ba.final_cost,
                      ba_iterations=step.ba.iterations)
    return values


def _sane(problem: BAProblem, res: BAResult, reg_cfg: RegistrationConfig) -> bool:
    """False (and a warning) when an optimisation moved a keyframe further than a registration may jump
    (max_jump_m / max_jump_deg) or produced non-finite values: such a result is discarded, not written."""
    ok = bool(np.all(np.isfinite(res.T_world_cam)) and np.all(np.isfinite(res.points[res.point_used])))
    for T0, T1 in zip(problem.T_world_cam, res.T_world_cam) if ok else ():
        move = se3.inv(T0) @ T1
        jump_deg = np.degrees(se3.rotation_angle(move))
        if np.linalg.norm(move[:3, 3]) > reg_cfg.max_jump_m or jump_deg > reg_cfg.max_jump_deg:
            ok = False
            break
    if not ok:
        log.warning("back end: an optimisation moved a keyframe by more than %.1f m / %.0f deg or diverged; discarded",
                    reg_cfg.max_jump_m, reg_cfg.max_jump_deg)
    return ok


def _with_values(problem: BAProblem, res: BAResult) -> BAProblem:
    return dataclasses.replace(problem, T_world_cam=res.T_world_cam, points=res.points, lines=res.lines)
