"""A drive with its truth and a noisy, scaled estimate, and results folders as plvo-viz leaves them: the inputs of
the `plvo eval metric` tests (tests/plvo_app/test_eval_metric_inputs.py, tests/plvo_eval/test_metric_plots.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from plvo.data.trajectory import write_poses
from plvo.geometry import se3

N = 150
TIMES = 1000.0 + 0.1037 * np.arange(N)  # KITTI-like: not exactly 10 Hz, and far from 0


def weaving_drive(n: int = N) -> np.ndarray:
    """1 m a frame in KITTI's cam0 (x right, y down, z ahead), weaving left and right, gently up and down."""
    poses, p = [], np.zeros(3)
    for k in range(n):
        R = se3.so3_exp(np.array([0.0, 0.6 * np.sin(k / 25.0), 0.0])) @ se3.so3_exp(
            np.array([0.02 * np.sin(k / 13.0), 0.0, 0.0]))
        poses.append(se3.from_rt(R, p.copy()))
        p = p + R @ np.array([0.0, 0.0, 1.0])
    return np.stack(poses)


def noisy_estimate(gt: np.ndarray, seed: int = 1, scale: float = 1.01) -> np.ndarray:
    rng = np.random.default_rng(seed)
    est = gt.copy()
    est[:, :3, 3] *= scale
    noise = rng.normal(0.0, 1.0, (len(gt), 6)) * np.array([0.05, 0.05, 0.05, 0.002, 0.002, 0.002])
    return np.stack([T @ se3.exp(xi) for T, xi in zip(est, noise)])


GT = weaving_drive()
EST = noisy_estimate(GT)


def results_folder(folder: Path, frames, fmt: str = "kitti", truth: bool = True, est: np.ndarray = EST,
                   **summary) -> Path:
    """A results folder as plvo-viz leaves it: poses.txt, summary.json and truth.txt of the run's frames."""
    idx = list(frames)
    folder.mkdir(parents=True)
    first = se3.inv(est[idx[0]])  # plvo's poses start at the identity
    write_poses(folder / "poses.txt", first @ est[idx], TIMES[idx], fmt)
    if truth:
        write_poses(folder / "truth.txt", GT[idx], TIMES[idx], fmt)
    data = {"run": folder.name, "sequence": "00", "frame_indices": idx, "status": "complete", **summary}
    (folder / "summary.json").write_text(json.dumps(data))
    return folder
