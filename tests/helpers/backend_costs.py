"""One bundle-adjustment window's cost both ways, the fast solver's (bundle_adjustment._evaluate) and gtsam's graph's,
for the tests that hold the two solvers to the same factors."""

from __future__ import annotations

import dataclasses

import numpy as np

from plvo.backend import bundle_adjustment as ba
from plvo.backend import factors
from plvo.backend.problem import BAProblem, make_synthetic_problem
from plvo.config import BackendConfig
from plvo.geometry import se3
from plvo.geometry.lines import plucker_from_points, plucker_to_orth


def perturbed_window() -> BAProblem:
    """A 4-keyframe synthetic window off its truth: poses by ~0.01, points and lines by 5 cm; zeta 0.7."""
    truth = make_synthetic_problem(n_kf=4, n_points=60, n_lines=15, seed=5, prior_fraction=0.5)
    rng = np.random.default_rng(5)
    T = truth.T_world_cam.copy()
    for k in range(1, 4):
        T[k] = T[k] @ se3.exp(rng.normal(0, 0.01, 6))
    return dataclasses.replace(truth, T_world_cam=T, points=truth.points + rng.normal(0, 0.05, truth.points.shape),
                               lines=truth.lines + rng.normal(0, 0.05, truth.lines.shape), rel_zeta=np.full(3, 0.7))


def costs(p: BAProblem, cfg: BackendConfig, use_lines: bool = True) -> tuple[float, float, np.ndarray]:
    """-> (the fast solver's cost, gtsam's graph error, the lines gtsam used (L,) bool) at p's values."""
    graph, values, pt_ok, ln_ok, _ = factors.build_graph(p, cfg, use_lines=use_lines)
    ln_used = ln_ok if use_lines else np.zeros(p.n_lines, bool)
    lay, sel = ba._Layout(p, pt_ok, ln_used), ba._select(p, pt_ok, ln_used, True)
    sel["origin"] = np.zeros((p.n_lines, 3))
    U, W = plucker_to_orth(plucker_from_points(p.lines[:, 0], p.lines[:, 1]))
    T_cw = np.stack([se3.inv(t) for t in p.T_world_cam])
    ours = ba._evaluate(p, T_cw, p.points, U, W, lay, sel, cfg, factors.DEFAULT_STEREO_BASELINE_M).cost()
    return ours, graph.error(values), ln_used
