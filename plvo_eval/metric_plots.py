"""PNG figures of `plvo eval metric --plot` (matplotlib, Agg), like evo's: every estimate against its truth after the
SE(3) alignment that its ATE uses, from above, as the position error along the path, as x/y/z and as roll/pitch/yaw
over time (over the frame numbers when a run has no times).

Truths come in any world frame (KITTI's cam0 with y down, a z-up motion capture), so the up axis is read off the truth:
the axis it spreads least along. The top view drops it; yaw turns about it, so that a ground vehicle's heading, the
angle that wraps, is the unbounded Euler angle and pitch, the one bounded to +-90 deg, stays small.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plvo_eval.kitti_metric import AteResult, trajectory_distances
from plvo_eval.plots import GT_STYLE, _pyplot, save_figure

PLOTS: tuple[str, ...] = ("trajectory_top", "error_along_path", "xyz", "rpy")
FIGSIZE: dict[str, tuple[float, float]] = {
    "trajectory_top": (7.0, 7.0), "error_along_path": (10.0, 4.0), "xyz": (10.0, 7.5), "rpy": (10.0, 7.5)}
AXES = "xyz"
# axes spreading within this share of the largest spread count as equally flat; then y (KITTI cam0's down) is taken
# before z (a z-up world) before x, so that a straight drive, flat across two axes, is seen from above
FLAT_SHARE = 0.05
# intrinsic Euler sequence per up axis: (yaw about the up axis, pitch, roll)
EULER = {1: "YXZ", 2: "ZYX", 0: "XZY"}


@dataclass(frozen=True)
class PlottedRun:
    """One estimate and its truth, paired: gt, est (N,4,4) T_world_cam; frames (N,) frame numbers; times (N,) s or
    None; ate: the SE(3) ATE, whose T_gt_est aligns the estimate onto the truth."""

    name: str
    gt: np.ndarray
    est: np.ndarray
    frames: np.ndarray
    times: np.ndarray | None
    ate: AteResult

    @property
    def aligned(self) -> np.ndarray:
        return self.ate.T_gt_est @ self.est

    @property
    def from_origin(self) -> np.ndarray:
        """The estimate started at the truth's first pose (evo's origin alignment). Orientations are drawn so: the
        ATE's alignment fits positions only, and along a straight drive any roll about the road fits them alike
        (real KITTI 04 came out 39 deg rolled)."""
        return self.gt[0] @ np.linalg.inv(self.est[0]) @ self.est


def plot_paths(out_dir: Path) -> dict[str, Path]:
    """name -> the PNG that write_metric_plots writes there."""
    return {name: Path(out_dir) / f"{name}.png" for name in PLOTS}


def up_axis(positions: np.ndarray) -> int:
    """(N,3) truth positions -> the index of the axis they spread least along (FLAT_SHARE breaks near-ties)."""
    spread = np.ptp(np.asarray(positions, dtype=np.float64), axis=0)
    flat = spread <= spread.min() + FLAT_SHARE * spread.max()
    return next(axis for axis in (1, 2, 0) if flat[axis])


def roll_pitch_yaw(poses: np.ndarray, up: int) -> np.ndarray:
    """(N,4,4) -> (N,3) roll, pitch, yaw in degrees, yaw about the up axis, each unwrapped (no jump at +-180)."""
    from scipy.spatial.transform import Rotation  # slow to import; only this figure needs it

    yaw_pitch_roll = Rotation.from_matrix(poses[:, :3, :3]).as_euler(EULER[up])
    return np.degrees(np.unwrap(yaw_pitch_roll[:, ::-1], axis=0))


def _euler_labels(up: int) -> tuple[str, str, str]:
    seq = EULER[up].lower()
    return f"roll (about {seq[2]})", f"pitch (about {seq[1]})", f"yaw (about {seq[0]})"


def _truths(runs: Sequence[PlottedRun], abscissa: Sequence[np.ndarray]) -> list[int]:
    """Indices of the runs whose truth is drawn: one per distinct truth (runs against one truth draw it once)."""
    drawn: list[int] = []
    for k, run in enumerate(runs):
        if not any(len(runs[j].gt) == len(run.gt) and np.allclose(runs[j].gt, run.gt)
                   and np.allclose(abscissa[j], abscissa[k]) for j in drawn):
            drawn.append(k)
    return drawn


def _abscissa(runs: Sequence[PlottedRun]) -> tuple[list[np.ndarray], str]:
    """Seconds from the first time when every run has times, else frame numbers."""
    if all(r.times is not None for r in runs):
        t0 = min(float(r.times.min()) for r in runs if r.times is not None)
        return [np.asarray(r.times) - t0 for r in runs], "time [s]"
    return [np.asarray(r.frames, dtype=np.float64) for r in runs], "frame"


def _truth_style(first: bool) -> dict:
    return GT_STYLE if first else {**GT_STYLE, "label": None}


def plot_top(runs: Sequence[PlottedRun], path: Path) -> Path:
    plt = _pyplot()
    up = up_axis(np.concatenate([r.gt[:, :3, 3] for r in runs]))
    a, b = (i for i in range(3) if i != up)
    fig, ax = plt.subplots(figsize=FIGSIZE["trajectory_top"], layout="constrained")
    for n, k in enumerate(_truths(runs, [r.frames for r in runs])):
        gt = runs[k].gt
        ax.plot(gt[:, a, 3], gt[:, b, 3], **_truth_style(n == 0))
        ax.plot(gt[0, a, 3], gt[0, b, 3], "ks", label="start" if n == 0 else None)
    for k, run in enumerate(runs):
        est = run.aligned
        ax.plot(est[:, a, 3], est[:, b, 3], color=f"C{k}", linewidth=1.2,
                label=f"{run.name} (ATE {run.ate.rmse_m:.3f} m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"{AXES[a]} [m]")
    ax.set_ylabel(f"{AXES[b]} [m]")
    ax.set_title(f"trajectories seen along {AXES[up]}, estimates SE(3)-aligned onto the truth")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    return save_figure(fig, path)


def plot_error_along_path(runs: Sequence[PlottedRun], path: Path) -> Path:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=FIGSIZE["error_along_path"], layout="constrained")
    distance = [trajectory_distances(r.gt).astype(np.float64) for r in runs]
    if all(d[-1] > 0 for d in distance):
        xs, xlabel = distance, "distance travelled along the truth [m]"
    else:  # a truth standing still has no path to lay the errors along
        xs, xlabel = _abscissa(runs)
    for k, (run, x) in enumerate(zip(runs, xs)):
        ax.plot(x, run.ate.errors_m, color=f"C{k}", linewidth=1.2,
                label=f"{run.name} (RMSE {run.ate.rmse_m:.3f} m, max {run.ate.max_m:.3f} m)")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("position error [m]")
    ax.set_ylim(bottom=0.0)
    ax.set_title("position error after SE(3) alignment (ATE per frame)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    return save_figure(fig, path)


def _three_panels(kind: str, runs: Sequence[PlottedRun], series: Callable[[np.ndarray], np.ndarray],
                  ylabels: Sequence[str], title: str, path: Path, origin: bool = False) -> Path:
    """Three stacked panels over time (or frames): each run's truth (once per distinct truth) and estimate (SE(3)
    aligned, or with `origin` started at the truth's first pose); series(poses) -> (N,3) the values drawn."""
    plt = _pyplot()
    xs, xlabel = _abscissa(runs)
    fig, axes = plt.subplots(3, 1, figsize=FIGSIZE[kind], sharex=True, layout="constrained")
    for n, k in enumerate(_truths(runs, xs)):
        values = series(runs[k].gt)
        for i, ax in enumerate(axes):
            ax.plot(xs[k], values[:, i], **_truth_style(n == 0))
    for k, run in enumerate(runs):
        values = series(run.from_origin if origin else run.aligned)
        for i, ax in enumerate(axes):
            ax.plot(xs[k], values[:, i], color=f"C{k}", linewidth=1.2, label=run.name)
    for ax, ylabel in zip(axes, ylabels):
        ax.set_ylabel(ylabel)
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel(xlabel)
    axes[0].legend(loc="best", fontsize=8)
    fig.suptitle(title)
    return save_figure(fig, path)


def plot_xyz(runs: Sequence[PlottedRun], path: Path) -> Path:
    return _three_panels("xyz", runs, lambda poses: poses[:, :3, 3], [f"{a} [m]" for a in AXES],
                         "position, estimates SE(3)-aligned onto the truth", path)


def plot_rpy(runs: Sequence[PlottedRun], path: Path) -> Path:
    up = up_axis(np.concatenate([r.gt[:, :3, 3] for r in runs]))
    return _three_panels("rpy", runs, lambda poses: roll_pitch_yaw(poses, up),
                         [f"{label} [deg]" for label in _euler_labels(up)],
                         f"orientation (yaw about {AXES[up]}), estimates started at the truth's first pose", path,
                         origin=True)


def write_metric_plots(runs: Sequence[PlottedRun], out_dir: Path) -> dict[str, Path]:
    """Every figure (PLOTS) of the runs as PNG under out_dir, each written atomically; returns name -> path."""
    if not runs:
        raise ValueError("no run to plot")
    paths = plot_paths(out_dir)
    draw = {"trajectory_top": plot_top, "error_along_path": plot_error_along_path, "xyz": plot_xyz,
            "rpy": plot_rpy}
    return {name: draw[name](runs, paths[name]) for name in PLOTS}
