"""PNG figures of a Report (matplotlib, Agg backend): trajectories from above against ground truth, error by
segment length and error by speed (the devkit's plots: translation % and rotation deg/m, segments of all
sequences pooled per setting). Sequences shorter than 100 m have no devkit segment; the length and speed plots
then use the short segments (10/20/40 m, every frame a start) and say so in their titles.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from plvo.atomic import atomic_path
from plvo_eval.kitti_metric import DEVKIT_LENGTHS, SHORT_LENGTHS, SegmentErrors
from plvo_eval.report import LABELS, Report, pooled_label

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

SPEED_BINS_MPS = np.arange(2.0, 25.0, 2.0)  # devkit: bins centred every 2 m/s, +-2 m/s wide
GT_STYLE = {"color": "black", "linewidth": 2.0, "label": "ground truth"}


def _pyplot() -> ModuleType:
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Figure, path: Path) -> Path:
    """Save a matplotlib figure as PNG atomically and close it."""
    plt = _pyplot()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


def _segments(report: Report) -> tuple[dict[str, SegmentErrors], tuple[float, ...], str]:
    """Pooled segments per setting: devkit lengths when any setting has some, else the short lengths."""
    evs = {s: e for s, e in report.evaluations.items() if e is not None}
    if any(e.kitti.n_segments for e in evs.values()):
        return {s: e.kitti.segments for s, e in evs.items()}, DEVKIT_LENGTHS, "100-800 m segments"
    lengths = tuple(e.length_m for e in next(iter(evs.values())).short.per_length) if evs else SHORT_LENGTHS
    return {s: e.short.segments for s, e in evs.items()}, lengths, "short segments, every frame a start"


def plot_trajectories(report: Report, sequence: str, path: Path) -> Path:
    """Top view (x right, z forward of cam0 at frame 0) of every setting's estimate against ground truth."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 7))
    drawn_gt = False
    for setting in report.settings:
        pair = report.poses[setting].get(sequence)
        if pair is None:
            continue
        gt, est = pair
        if not drawn_gt:
            ax.plot(gt[:, 0, 3], gt[:, 2, 3], **GT_STYLE)
            ax.plot(gt[0, 0, 3], gt[0, 2, 3], "ks", label="start")
            drawn_gt = True
        ax.plot(est[:, 0, 3], est[:, 2, 3], linewidth=1.2, label=LABELS.get(setting, setting))
    if not drawn_gt:
        ax.text(0.5, 0.5, "no finished run", ha="center", transform=ax.transAxes)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("z [m]")
    ax.set_title(f"sequence {sequence}: trajectories from above")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    return save_figure(fig, path)


def _binned(values: np.ndarray, keys: np.ndarray, centres: Sequence[float] | np.ndarray, half_width: float
            ) -> np.ndarray:
    out = np.full(len(centres), np.nan)
    for k, c in enumerate(centres):
        mask = np.abs(keys - c) < half_width
        if mask.any():
            out[k] = values[mask].mean()
    return out


def _two_panels(title: str, xlabel: str) -> tuple[Figure, np.ndarray]:
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, ylabel in zip(axes, ("translation error [%]", "rotation error [deg/m]")):
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(True, alpha=0.3)
    fig.suptitle(title)
    return fig, axes


def _log_if_spread(axes: Iterable[Axes]) -> None:
    """A log y axis on panels whose curves span more than 20x: one failing method (KISS-ICP on the synthetic
    town, ~100 %) would otherwise flatten every other curve onto zero."""
    for ax in axes:
        y = np.concatenate([line.get_ydata() for line in ax.get_lines()] or [np.zeros(0)]).astype(float)
        y = y[np.isfinite(y) & (y > 0)]
        if len(y) and y.max() > 20 * y.min():
            ax.set_yscale("log")


def plot_error_by_length(report: Report, path: Path) -> Path:
    """Mean translation and rotation error per segment length, one line per setting."""
    segs, lengths, what = _segments(report)
    fig, axes = _two_panels(f"error by segment length ({what})", "segment length [m]")
    for setting, seg in segs.items():
        # the devkit matches a segment to a length within 1 m
        t = _binned(seg.t_err * 100.0, seg.length, lengths, 1.0)
        r = _binned(np.degrees(seg.r_err), seg.length, lengths, 1.0)
        label = pooled_label(report, setting)
        axes[0].plot(lengths, t, "o-", label=label)
        axes[1].plot(lengths, r, "o-", label=label)
    _log_if_spread(axes)
    axes[0].legend(fontsize=8)
    return save_figure(fig, path)


def plot_error_by_speed(report: Report, path: Path) -> Path:
    """Mean translation and rotation error per speed bin (devkit: 2..24 m/s, +-2 m/s), one line per setting."""
    segs, _lengths, what = _segments(report)
    fig, axes = _two_panels(f"error by speed ({what})", "speed [km/h]")
    for setting, seg in segs.items():
        t = _binned(seg.t_err * 100.0, seg.speed, SPEED_BINS_MPS, 2.0)
        r = _binned(np.degrees(seg.r_err), seg.speed, SPEED_BINS_MPS, 2.0)
        keep = np.isfinite(t)
        label = pooled_label(report, setting)
        axes[0].plot(SPEED_BINS_MPS[keep] * 3.6, t[keep], "o-", label=label)
        axes[1].plot(SPEED_BINS_MPS[keep] * 3.6, r[keep], "o-", label=label)
    _log_if_spread(axes)
    axes[0].legend(fontsize=8)
    return save_figure(fig, path)


def write_plots(report: Report, out_dir: Path) -> dict[str, Path]:
    """Every figure of a report as PNG under out_dir; returns name -> path."""
    out_dir = Path(out_dir)
    paths = {
        f"trajectory_{seq}": plot_trajectories(report, seq, out_dir / f"trajectory_{_safe(seq)}.png")
        for seq in report.sequences
    }
    if any(e is not None for e in report.evaluations.values()):
        paths["error_by_length"] = plot_error_by_length(report, out_dir / "error_by_length.png")
        paths["error_by_speed"] = plot_error_by_speed(report, out_dir / "error_by_speed.png")
    return paths
