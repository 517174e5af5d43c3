"""The end of a run in figures: summary.json in the results folder and the terminal's last lines.

Where the data carries ground truth (KITTI odometry and raw, the synthetic town and the twins, a folder with
poses.txt) the run is scored as `plvo eval metric` scores it, on the same poses as poses.txt: ATE after SE(3) and
Sim(3) alignment, the relative error over 10/20/40 m (every frame a start), the KITTI devkit figure where the path
holds a 100 m segment, and the rotation errors beside them; then speed and the tracked share. The truth of the frames
run is written beside the poses (truth.txt, cam0, first frame at identity, in poses.txt's format), so that
`plvo eval metric --est results/<run>` and evo find both. A run without truth still gets summary.json (status,
frames, speed), with `"accuracy": null`.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

# the names of a results folder's files, for the run that writes them and `plvo eval metric --est` that reads them
POSES_FILE = "poses.txt"
SUMMARY_FILE = "summary.json"
TRUTH_FILE = "truth.txt"
LATEST_LINK = "latest"


def truth_cam0(dataset) -> Any:
    """(N,4,4) ground truth of cam0 over the frames run, first frame at identity (as poses.txt), or None."""
    import numpy as np

    gt = getattr(dataset, "gt_T_world_cam", None)  # the Dataset protocol has it; a bare source may not
    if gt is None:
        return None
    cam0 = gt @ np.linalg.inv(dataset.calib.T_cam0_cam)
    return np.linalg.inv(cam0[0]) @ cam0


def _number(value: float, digits: int) -> float | None:
    return round(float(value), digits) if math.isfinite(value) else None


def _relative_json(rel) -> dict[str, Any]:
    return {f"{e.length_m:g}m": {"t_err_pct": _number(e.t_err_pct, 4), "r_err_deg_per_m": _number(e.r_err_deg_per_m, 6),
                                 "segments": e.n_segments} for e in rel.per_length}


def accuracy(truth, poses) -> dict[str, Any]:
    """The figures of an estimate against its truth (both (N,4,4), cam0), as summary.json holds them."""
    from plvo_eval.kitti_metric import evaluate_sequence

    ev = evaluate_sequence(truth, poses)
    devkit = None
    if ev.kitti.n_segments:
        devkit = {"t_err_pct": _number(ev.kitti.t_err_pct, 4), "r_err_deg_per_m": _number(ev.kitti.r_err_deg_per_m, 6),
                  "segments": ev.kitti.n_segments}
    return {
        "path_length_m": round(ev.path_length_m, 3),
        "ate_se3_m": _number(ev.ate_se3.rmse_m, 4),
        "ate_sim3_m": _number(ev.ate_sim3.rmse_m, 4),
        "sim3_scale": _number(ev.ate_sim3.scale, 5),
        "ate_max_m": _number(ev.ate_se3.max_m, 4),
        "relative": _relative_json(ev.short),
        "devkit": devkit,
        "heading_offset_deg": _number(ev.heading_offset_deg, 3),
    }


def build_summary(*, run: str, sequence: str, status: str, reason: str, frame_indices, frames_done: int,
                  frames_tracked: int, fps: float, poses_file: Path | None, pose_format: str,
                  truth_source: str | None, truth_file: Path | None, figures: dict | None) -> dict[str, Any]:
    """summary.json's object: what ran, how it ended, how fast, and (with truth and poses) how accurate."""
    return {
        "run": run,
        "sequence": sequence,
        "status": status,
        "reason": reason,
        "frames_total": len(frame_indices),
        "frames_done": frames_done,
        "frames_tracked": frames_tracked,
        "tracked_share": round(frames_tracked / frames_done, 4) if frames_done else 0.0,
        "frames_per_second": round(fps, 3),
        "poses": None if poses_file is None else poses_file.name,
        "format": pose_format,
        "truth": None if truth_file is None else truth_file.name,
        "truth_source": truth_source,
        "accuracy": figures,
        "frame_indices": [int(f) for f in frame_indices],
    }


def summary_lines(summary: dict[str, Any]) -> list[str]:
    """The terminal's account of a scored run (empty without figures): a few lines a user reads at a glance."""
    acc = summary.get("accuracy")
    if not acc:
        return []
    lines = [f"accuracy against the truth ({summary['truth_source']}), {summary['frames_total']} frames, "
             f"{acc['path_length_m']:.1f} m:"]
    sim3 = (f", {acc['ate_sim3_m']:.3f} m after Sim(3) (scale {acc['sim3_scale']:.4f})"
            if acc["ate_sim3_m"] is not None else "")
    lines.append(f"  ATE {acc['ate_se3_m']:.3f} m after SE(3){sim3}")
    parts = [f"{k[:-1]} m: {_pct(v['t_err_pct'])} {_rot(v['r_err_deg_per_m'])}" for k, v in acc["relative"].items()]
    lines.append("  relative error  " + " | ".join(parts))
    dk = acc["devkit"]
    lines.append(f"  KITTI devkit (100..800 m): {_pct(dk['t_err_pct'])} {_rot(dk['r_err_deg_per_m'])}" if dk else
                 "  KITTI devkit: no figure (the path holds no 100 m segment)")
    if acc["heading_offset_deg"] is not None:
        lines.append(f"  the truth's heading sits {acc['heading_offset_deg']:.2f} deg off the estimate's "
                     "(plvo eval metric gives the errors with it taken out)")
    return lines


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f} %"


def _rot(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f} deg/m"


def point_latest(results_folder: Path) -> Path | None:
    """Point `latest` beside a run's results folder at it (a relative symbolic link, replaced atomically); a
    `latest` that is not a link is the user's and is left alone (None)."""
    link = results_folder.parent / LATEST_LINK
    if link.exists() and not link.is_symlink():
        return None
    tmp = results_folder.parent / f".{LATEST_LINK}.{os.getpid()}"
    try:
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(results_folder.name, target_is_directory=True)
        os.replace(tmp, link)
    except OSError:
        tmp.unlink(missing_ok=True)
        return None
    return link
