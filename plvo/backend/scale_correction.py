"""Scale correction of the newest keyframe (paper II-D).

The newest keyframe's pose and the point and line landmarks it sees are optimised; every other keyframe of the
window is held fixed. The factors are the relative-pose factor(s) between the newest keyframe and its neighbours
(the registration result, information zeta I) and the reprojection factors of those landmarks in every keyframe
of the window that sees them. Monocular tracking leaves the scale of the newest motion weakly determined (not at
all without depth priors), and the lidar relative pose fixes it; landmarks not seen by the newest keyframe are
returned unchanged.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from plvo.backend.bundle_adjustment import optimize
from plvo.backend.problem import BAProblem, BAResult
from plvo.config import BackendConfig
from plvo.errors import PlvoError


def scale_problem(problem: BAProblem, newest_kf: int) -> BAProblem:
    """The sub-problem of `correct_scale`: same arrays, only newest_kf free, observations of its landmarks only."""
    if not 0 <= newest_kf < problem.n_keyframes:
        raise PlvoError(f"correct_scale: newest_kf {newest_kf} outside [0, {problem.n_keyframes})")
    pts = np.zeros(problem.n_points, bool)
    pts[problem.pt_idx[problem.pt_kf == newest_kf]] = True
    lns = np.zeros(problem.n_lines, bool)
    lns[problem.ln_idx[problem.ln_kf == newest_kf]] = True
    po, lo = pts[problem.pt_idx], lns[problem.ln_idx]
    ro = np.any(problem.rel_ij == newest_kf, axis=1)
    return dataclasses.replace(
        problem, fixed=np.arange(problem.n_keyframes) != newest_kf,
        pt_kf=problem.pt_kf[po], pt_idx=problem.pt_idx[po], pt_uv=problem.pt_uv[po], pt_depth=problem.pt_depth[po],
        ln_kf=problem.ln_kf[lo], ln_idx=problem.ln_idx[lo], ln_seg=problem.ln_seg[lo], ln_prior=problem.ln_prior[lo],
        rel_ij=problem.rel_ij[ro], rel_T=problem.rel_T[ro], rel_zeta=problem.rel_zeta[ro],
        rel_weight=problem.relative_pose_weights(np.flatnonzero(ro)),
        pt_depth_sigma=None if problem.pt_depth_sigma is None else problem.pt_depth_sigma[po],
    )


def correct_scale(problem: BAProblem, newest_kf: int, cfg: BackendConfig | None = None, **kwargs: Any) -> BAResult:
    """Optimise T_world_cam[newest_kf] (4,4) and its landmarks (world), older keyframes fixed -> BAResult of the window.

    kwargs go to `bundle_adjustment.optimize` (use_depth_priors, use_lines, stereo_baseline_m).
    """
    return optimize(scale_problem(problem, newest_kf), cfg, **kwargs)


def scale_factor(T_before: np.ndarray, T_after: np.ndarray, T_prev: np.ndarray) -> float:
    """|t(prev->after)| / |t(prev->before)| for (4,4) T_world_cam poses: the scale change scale correction applied."""
    a = np.linalg.norm(T_after[:3, 3] - T_prev[:3, 3])
    b = np.linalg.norm(T_before[:3, 3] - T_prev[:3, 3])
    return float(a / b) if b > 0 else float("nan")
