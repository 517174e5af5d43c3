"""Where the heading and the scale go: the yaw and scale error each stage of the pipeline leaves, per 100 m.

The devkit's figure says how far a trajectory drifts, not which stage let it. With exact ground truth (the twins,
the towns), every keyframe step (the motion from one keyframe to the next) can be judged as each stage left it:

- `tracker`: the frame-to-frame tracker's, as the back end received the keyframe;
- `scale`: after the scale correction of the newest keyframe (II-D);
- `ba`: after the window's bundle adjustment of that keyframe (II-E);
- `final`: the reported trajectory at the end of the run: every later window's refinement and every loop
  correction and global bundle adjustment included.

A step's yaw error is the rotation between the estimated and the true motion about the world's up axis (degrees;
KITTI's world is cam0 of the first frame, y pointing down), its scale error the ratio of the estimated to the true
distance travelled, minus one. Over consecutive stretches of `segment_m` (100 m) of true path, the yaw errors of
the steps in a stretch add up to the heading the stage lost over it: `yaw_deg_per_100m` is their mean absolute
sum (what a devkit segment of 100 m sees of it; `pitch_deg_per_100m` the same about the horizontal axis across the
heading, which a hilly drive turns into height error), `yaw_bias_deg_per_100m` the signed sum over the whole run per 100
m (a systematic turn), `scale_pct` the mean absolute distance error of the stretches (per cent), `scale_bias_pct`
the whole run's. A run shorter than half a stretch has no stretch figures (None). A stage that did
not run on a step (the scale correction without a registration, a discarded adjustment) is left out for that step.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from plvo.geometry import se3
from plvo.results import StageSteps

STAGES = ("tracker", "scale", "ba", "final")
_UP_WORLD = np.array([0.0, -1.0, 0.0])  # KITTI's cam0: y down


def step_errors(T_est: np.ndarray, T_gt: np.ndarray, R_world_start: np.ndarray
                ) -> tuple[float, float, float, float]:
    """Estimated and true relative motions (4,4) of one step, the true orientation (3,3) at its start ->
    (yaw error deg, estimated distance m, true distance m, pitch error deg)."""
    err = se3.inv(T_gt) @ T_est
    up = R_world_start.T @ _UP_WORLD
    rotvec = se3.so3_log(err[:3, :3])
    # pitch: about the horizontal axis across the camera's heading (its x, right, with the up component removed)
    across = np.array([1.0, 0.0, 0.0]) - up[0] * up
    across /= max(float(np.linalg.norm(across)), 1e-12)
    return (float(np.degrees(rotvec @ up)), float(np.linalg.norm(T_est[:3, 3])), float(np.linalg.norm(T_gt[:3, 3])),
            float(np.degrees(rotvec @ across)))


def _summary(rows: list[tuple[float, float, float, float]], segment_m: float) -> dict[str, float | int | None]:
    if not rows:
        return {"steps": 0}
    yaw, est, gt, pitch = (np.array(c) for c in zip(*rows))
    path = float(gt.sum())
    stretch = np.floor(np.cumsum(gt) / segment_m).astype(int)
    full = [k for k in np.unique(stretch) if gt[stretch == k].sum() > 0.5 * segment_m]  # a short tail says little
    yaw_seg = [abs(yaw[stretch == k].sum()) * segment_m / gt[stretch == k].sum() for k in full]
    pitch_seg = [abs(pitch[stretch == k].sum()) * segment_m / gt[stretch == k].sum() for k in full]
    scale_seg = [abs(est[stretch == k].sum() / gt[stretch == k].sum() - 1.0) * 100 for k in full]
    # None where a figure has nothing to stand on: no stretch of half a segment (a short run), no path
    return {"steps": len(yaw), "path_m": round(path, 3),
            "yaw_deg_per_100m": round(float(np.mean(yaw_seg)), 5) if yaw_seg else None,
            "yaw_bias_deg_per_100m": round(float(yaw.sum() * 100.0 / path), 5) if path > 0 else None,
            "pitch_deg_per_100m": round(float(np.mean(pitch_seg)), 5) if pitch_seg else None,
            "scale_pct": round(float(np.mean(scale_seg)), 4) if scale_seg else None,
            "scale_bias_pct": round(float((est.sum() / path - 1.0) * 100), 4) if path > 0 else None}


def stage_drift(stage_steps: Iterable[StageSteps], frame_indices: Iterable[int], gt_cam0: np.ndarray,
                est_cam0: np.ndarray, T_cam0_cam: np.ndarray | None = None,
                segment_m: float = 100.0) -> dict[str, dict[str, float | int | None]]:
    """The back end's per-keyframe stage record (plvo.runtime.worker_stages.RunRecord.stage_steps: frames (prev, new)
    and stage -> T_prev_new of the tracked camera), the run's frame numbers (N,), ground-truth and final estimated cam0
    poses (N,4,4) and the tracked camera's T_cam0_cam -> stage -> summary (see the module doc)."""
    row = {int(f): k for k, f in enumerate(frame_indices)}
    C = np.eye(4) if T_cam0_cam is None else np.asarray(T_cam0_cam, float)
    C_inv = se3.inv(C)
    rows: dict[str, list[tuple[float, float, float, float]]] = {s: [] for s in STAGES}
    for entry in stage_steps:
        a, b = (int(f) for f in entry.frames)
        if a not in row or b not in row or a == b:
            continue
        Ga, Gb = gt_cam0[row[a]], gt_cam0[row[b]]
        T_gt = se3.inv(Ga) @ Gb
        for stage, T in entry.steps.items():
            if stage in rows:
                rows[stage].append(step_errors(C @ np.asarray(T) @ C_inv, T_gt, Ga[:3, :3]))
        rows["final"].append(step_errors(se3.inv(est_cam0[row[a]]) @ est_cam0[row[b]], T_gt, Ga[:3, :3]))
    return {stage: _summary(r, segment_m) for stage, r in rows.items()}
