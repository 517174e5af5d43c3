"""What two independent systems' errors share on one sequence: a floor under both that neither made.

plvo (camera and lidar) and KISS-ICP (lidar alone) estimate their motions independently. Over a segment, each one's
error against the truth is its own error plus whatever both share: an error of the truth itself (a GPS/INS's short-
term wander, above all in height) or something both read in the same scans. Their shared part shows as the
covariance of their segment errors: with e_a = s + n_a and e_b = s + n_b and independent n_a, n_b, mean(e_a e_b) =
mean(s^2), per axis. On KITTI 04's real frames the two correlate 0.8-0.9 in height over 10-20 m where on a twin of the
same stretch, with exact truth, they do not correlate at all: the share is the truth's, and it is a floor under every
system that reads the real clips (docs/results/real_vs_twin/).

`shared_error` gives, per segment length, the shared part's rms per axis, each system's own part (its mean squared
error less the shared one) and the correlation, in the segments' own frame (x right, y down, z ahead), per cent of
the length; the heading offset of each estimate against the truth taken out first, as the metric's second reading.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from plvo_eval.kitti_metric import SHORT_LENGTHS, _inv, fit_heading_offset, remove_heading_offset, segment_errors


def segment_translation_errors(gt: np.ndarray, est: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """(N,4,4) gt and est -> (first frames (S,), the error of each segment's translation in its first truth frame
    (S,3), per cent of the length), every frame a start, with est's heading offset against gt taken out."""
    theta = fit_heading_offset(gt, est)
    if np.isfinite(theta):
        est = remove_heading_offset(est, theta)
    seg = segment_errors(gt, est, (length,), 1)
    if len(seg) == 0:
        return seg.first_frame, np.zeros((0, 3))
    d_gt = _inv(gt[seg.first_frame]) @ gt[seg.last_frame]
    d_est = _inv(est[seg.first_frame]) @ est[seg.last_frame]
    return seg.first_frame, (d_gt[:, :3, 3] - d_est[:, :3, 3]) / length * 100.0


def shared_error(gt: np.ndarray, est_a: np.ndarray, est_b: np.ndarray,
                 lengths: Sequence[float] = SHORT_LENGTHS) -> dict[str, dict[str, object]]:
    """(N,4,4) truth and two systems' estimates of the same frames -> length (m, as text) -> {"segments", "shared_rms"
    (3,) per cent by axis, "own_a", "own_b" (3,) and "own_a_norm", "own_b_norm", "total_a_norm", "total_b_norm"
    (root mean square over segments), "correlation" (3,)}; lengths without a segment are left out."""
    out: dict[str, dict[str, object]] = {}
    for length in lengths:
        first_a, e_a = segment_translation_errors(gt, est_a, length)
        first_b, e_b = segment_translation_errors(gt, est_b, length)
        if len(e_a) < 3 or not np.array_equal(first_a, first_b):
            continue
        cov = np.mean(e_a * e_b, axis=0)
        shared = np.clip(cov, 0.0, None)  # a negative covariance shares nothing
        ms_a, ms_b = np.mean(e_a**2, axis=0), np.mean(e_b**2, axis=0)
        own_a, own_b = np.sqrt(np.clip(ms_a - shared, 0.0, None)), np.sqrt(np.clip(ms_b - shared, 0.0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = [float(np.corrcoef(e_a[:, k], e_b[:, k])[0, 1]) for k in range(3)]
        out[f"{length:g}"] = {
            "segments": int(len(e_a)),
            "shared_rms": np.sqrt(shared).round(5).tolist(),
            "own_a": own_a.round(5).tolist(), "own_b": own_b.round(5).tolist(),
            "own_a_norm": round(float(np.linalg.norm(own_a)), 5), "own_b_norm": round(float(np.linalg.norm(own_b)), 5),
            "total_a_norm": round(float(np.sqrt(ms_a.sum())), 5), "total_b_norm": round(float(np.sqrt(ms_b.sum())), 5),
            "correlation": [round(c, 4) if np.isfinite(c) else None for c in corr],
        }
    return out
