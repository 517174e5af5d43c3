"""A fake run for the app tests: frames, calibration and one result of every kind, without any dataset."""

from __future__ import annotations

import numpy as np

from plvo.geometry.se3 import exp
from plvo.recording import RunInfo
from plvo.results import (EDGE_LOOP, EDGE_ODOMETRY, GraphResult, KeyframeResult, LoopResult, MapResult,
                          TimingResult, TrackingResult)
from plvo.types import Calibration, DepthPriors, FeatureSet, Frame

K = np.array([[700.0, 0, 600], [0, 700, 180], [0, 0, 1]])
T_CAM_VELO = np.array([[0, -1, 0, 0], [0, 0, -1, -0.08], [1, 0, 0, -0.27], [0, 0, 0, 1]], float)
CALIB = Calibration(K=K, T_cam_velo=T_CAM_VELO, width=1200, height=360)


def pose(i: int) -> np.ndarray:
    """A curving drive: 1 m forward a frame and a yaw that grows, so rotations are far from symmetric."""
    return exp(np.array([0.2 * i, 0.0, 1.0 * i, 0.1, 0.03 * i, 0.05]))


def frame(i: int, rng: np.random.Generator) -> Frame:
    image = (rng.random((360, 1200)) * 60 + 100).astype(np.uint8)
    image[100:260, 200 + 20 * i: 400 + 20 * i] = 240
    scan = np.concatenate([rng.uniform(-30, 30, (5000, 3)) * [1, 1, 0.05], rng.random((5000, 1))], 1)
    return Frame(i, 0.1 * i, image, scan.astype(np.float32), CALIB, pose(i))


def features(rng: np.random.Generator, n: int = 50) -> FeatureSet:
    kp = rng.uniform([0, 0], [1200, 360], (n, 2))
    seg = np.concatenate([kp[:10], kp[:10] + 60], 1)
    raw = np.concatenate([seg, seg + 1])
    return FeatureSet(kp, np.zeros(n, int), np.zeros(n), np.ones(n), np.zeros((n, 32), np.uint8), seg,
                      np.zeros((10, 32), np.uint8), raw, tuple(np.array([j, j + 10]) for j in range(10)), (1200, 360))


def depth(n_points: int = 50) -> DepthPriors:
    d = np.full(n_points, 10.0)
    reason = np.zeros(n_points, int)
    reason[::2] = 1
    lines = np.tile(np.array([[0, 0, 10], [1, 0, 10]], float), (10, 1, 1))
    return DepthPriors(d, reason, np.zeros(n_points), np.full(n_points, 5), np.full((n_points, 4), np.nan),
                       lines, np.zeros(10, int), np.zeros(10), np.full(10, 8))


def run_info(n: int, has_odometry: bool = True) -> RunInfo:
    gt = np.array([pose(i) for i in range(n)])
    return RunInfo("fake_run", "fake", CALIB, tuple(range(n)), gt, {"orb": {"n_features": 50}}, "0.1.0", "abc123",
                   "plvo-viz --seq fake", {"config_toml": "[orb]\nn_features = 50\n", "has_odometry": has_odometry})


def drive(recorder, n: int = 9, every: int = 3) -> None:
    """Feed `recorder` n frames of every result kind; keyframes every `every` frames, a loop at the end."""
    rng = np.random.default_rng(0)
    recorder.on_run_start(run_info(n))
    kf_ids: list[int] = []
    for i in range(n):
        recorder.on_frame(frame(i, rng))
        recorder.on_stage(i, features(rng))
        is_kf = i % every == 0
        recorder.on_stage(i, TrackingResult(i, pose(i), 40, 8, np.arange(0, 50, 2), np.arange(5), is_kf, True,
                                            "ok"))
        if is_kf:
            kf_ids.append(len(kf_ids))
            recorder.on_stage(i, KeyframeResult(i, kf_ids[-1], pose(i), "every 3"))
            recorder.on_stage(i, depth())
            poses = np.array([pose(every * k) for k in kf_ids])
            edges = np.array([[k, k + 1] for k in range(len(kf_ids) - 1)], int).reshape(-1, 2)
            recorder.on_stage(i, GraphResult(i, np.array(kf_ids), poses, edges, np.full(len(edges), EDGE_ODOMETRY),
                                             np.linspace(0, 1, len(edges)), 1.0))
            pts = rng.uniform(-20, 20, (200 * len(kf_ids), 3))
            recorder.on_stage(i, MapResult(i, pts, pts[:30].reshape(-1, 2, 3)))
        recorder.on_stage(i, TimingResult(i, {"features": 0.05, "total": 0.08}))
    last = n - 1
    recorder.on_stage(last, LoopResult(last, kf_ids[-1], 0, True, 0.5, 40, np.eye(4), "verified"))
    recorder.on_stage(last, GraphResult(last, np.array(kf_ids), np.array([pose(every * k) for k in kf_ids]),
                                        np.array([[len(kf_ids) - 1, 0]]), np.array([EDGE_LOOP]), np.array([1.0])))
