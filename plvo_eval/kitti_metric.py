"""The KITTI odometry metric, faithful to the official devkit (evaluate_odometry.cpp), plus ATE and short RPE.

Devkit (calcSequenceErrors): path distances along the ground truth (trajectoryDistances, accumulated in float32
as the devkit does, so segment ends match it), a segment start every 10 frames, lengths 100..800 m, the segment
end is the first frame whose distance exceeds start + length (lastFrameFromSegmentLength), and the error pose is
inv(delta_est) * delta_gt with delta = inv(T_first) * T_last. Its translation norm / length and rotation angle /
length (rotationError: acos of (trace - 1) / 2, clamped) are averaged over all segments, reported here in % and
deg/m. Averaging the segments of several sequences together gives the devkit's total (pooled) figure.
Note: inv(delta_gt) * delta_est is the inverse pose of the devkit's, with the same angle and translation norm.

Short relative error: the same segments and error on short lengths (default 10, 20, 40 m) with every frame a
start, for snippets far shorter than 100 m. As in the devkit, errors are divided by the nominal length, while a
segment ends at the first frame strictly beyond it: at 14 m/s (1.4 m a frame) a 10 m segment may be up to 14 %
longer, which scales its error up by as much (a scale error s reads as |1-s| * chord / nominal length).
ATE: RMSE of camera positions after a least-squares SE(3) or Sim(3) (Umeyama) alignment of the estimate onto the
ground truth.

Heading-aligned reading: every relative error is also given with one constant heading offset against the truth taken
out. Real ground truth can carry such an offset against the sensors' frame (KITTI 04's truth 0.25-0.3 deg; the GPS/INS
truth of raw drive 2011_09_26_drive_0009 ~1.45 deg), and it lays a floor of about that angle in radians (0.5 % at
0.3 deg, 2.5 % at 1.45 deg) under every segment's translation error, for every system alike. If the truth's body
frame is the camera's turned by a constant R (G_i = C_i R, the world re-based on frame 0), every true relative motion
is the camera's conjugated by R, its translation the camera's rotated by R^-1, which the best camera path misses. The
reading evaluates est' = R_y(th) @ est @ R_y(th)^T instead (th about cam0's vertical axis y; a first pose at the
identity stays there), with th fitted per run: the rotation about y that maps the estimated segment translations
onto the true ones in least squares, over the short segments and the devkit segments (each translation divided by the
segment's nominal length, so that every segment weighs alike). th > 0: the truth runs to the right (+x) of the
estimate. ATE aligns the whole trajectory anyway and is the same in both readings. A fitted angle can absorb part of
an estimate's own heading drift, so the devkit reading stays the figure to compare with published results.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from plvo.errors import TrajectoryError

DEVKIT_LENGTHS: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
DEVKIT_STEP = 10  # a segment start every 10 frames (one second at 10 Hz)
SHORT_LENGTHS: tuple[float, ...] = (10.0, 20.0, 40.0)
FRAME_RATE_HZ = 10.0  # the devkit's speed assumes 10 Hz


@dataclass(frozen=True)
class SegmentErrors:
    """Every evaluated segment: first_frame, last_frame (S,) int; length (S,) m; t_err (S,) m/m; r_err (S,) rad/m;
    speed (S,) m/s as the devkit computes it (length / (0.1 * frames))."""

    first_frame: np.ndarray
    last_frame: np.ndarray
    length: np.ndarray
    t_err: np.ndarray
    r_err: np.ndarray
    speed: np.ndarray

    def __len__(self) -> int:
        return int(len(self.length))


@dataclass(frozen=True)
class LengthError:
    """Mean errors of the segments of one length (NaN when there is none)."""

    length_m: float
    n_segments: int
    t_err_pct: float
    r_err_deg_per_m: float


@dataclass(frozen=True)
class RelativeError:
    """Errors averaged over all segments (t_err in %, r_err in deg/m; NaN without segments) and per length."""

    t_err_pct: float
    r_err_deg_per_m: float
    n_segments: int
    per_length: tuple[LengthError, ...]
    segments: SegmentErrors


@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error after aligning the estimate onto the ground truth.

    rmse_m, mean_m, median_m, max_m: statistics of the position errors (N,) errors_m; scale: Sim(3) scale (1 for
    SE(3)); T_gt_est: (4,4) the alignment (with the scale in its upper-left block for Sim(3)).
    """

    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    scale: float
    T_gt_est: np.ndarray
    errors_m: np.ndarray


@dataclass(frozen=True)
class SequenceEvaluation:
    """All figures of one sequence: the devkit metric, ATE after SE(3) and Sim(3) alignment, short relative error;
    and the devkit and short errors with the heading offset taken out (kitti_aligned, short_aligned: of est' =
    remove_heading_offset(est, heading_offset), heading_offset_deg fitted by fit_heading_offset; NaN without any
    segment to fit)."""

    name: str
    n_frames: int
    path_length_m: float
    kitti: RelativeError
    ate_se3: AteResult
    ate_sim3: AteResult
    short: RelativeError
    heading_offset_deg: float
    kitti_aligned: RelativeError
    short_aligned: RelativeError


@dataclass(frozen=True)
class Evaluation:
    """Per-sequence results and the pooled devkit figures (all segments of all sequences averaged together), as
    they are and with each sequence's own heading offset taken out (kitti_aligned, short_aligned)."""

    sequences: tuple[SequenceEvaluation, ...]
    kitti: RelativeError
    short: RelativeError
    kitti_aligned: RelativeError
    short_aligned: RelativeError


def _check_pair(gt: np.ndarray, est: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gt, est = np.asarray(gt, dtype=np.float64), np.asarray(est, dtype=np.float64)
    for name, poses in (("ground truth", gt), ("estimate", est)):
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise TrajectoryError(f"{name}: poses must be (N,4,4), got {poses.shape}")
    if len(gt) != len(est):
        raise TrajectoryError(f"ground truth has {len(gt)} poses but the estimate {len(est)}")
    if len(gt) == 0:
        raise TrajectoryError("no poses to evaluate")
    return gt, est


def trajectory_distances(poses: np.ndarray) -> np.ndarray:
    """(N,4,4) poses -> (N,) float32 path length from frame 0, accumulated in float32 like the devkit."""
    t = np.asarray(poses, dtype=np.float64)[:, :3, 3]
    d = (t[:-1] - t[1:]).astype(np.float32)  # devkit: float dx = double - double
    step = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
    return np.concatenate([np.zeros(1, np.float32), np.cumsum(step, dtype=np.float32)])


def last_frame_from_segment_length(dist: np.ndarray, first_frame: int, length: float) -> int:
    """First frame whose distance exceeds dist[first_frame] + length (float32 comparison), or -1."""
    target = np.float32(dist[first_frame]) + np.float32(length)
    i = int(np.searchsorted(dist, target, side="right"))
    return i if i < len(dist) else -1


def rotation_error(pose_error: np.ndarray) -> np.ndarray:
    """(...,4,4) error poses -> (...) rotation angle in radians, acos((trace - 1) / 2) clamped as the devkit."""
    d = 0.5 * (pose_error[..., 0, 0] + pose_error[..., 1, 1] + pose_error[..., 2, 2] - 1.0)
    return np.arccos(np.clip(d, -1.0, 1.0))


def translation_error(pose_error: np.ndarray) -> np.ndarray:
    """(...,4,4) error poses -> (...) translation norm in metres."""
    return np.linalg.norm(pose_error[..., :3, 3], axis=-1)


def _inv(T: np.ndarray) -> np.ndarray:
    """Inverse of (...,4,4) matrices: a general inverse as the devkit's Matrix::inv, since poses read from text
    (and estimates chained from them) are only nearly rigid and a transpose-based inverse would differ."""
    return np.linalg.inv(T)


def segment_errors(
    gt: np.ndarray, est: np.ndarray, lengths: Sequence[float] = DEVKIT_LENGTHS, step: int = DEVKIT_STEP
) -> SegmentErrors:
    """(N,4,4) gt and est T_world_cam -> errors of every segment, in the devkit's order (by start, then length)."""
    gt, est = _check_pair(gt, est)
    dist = trajectory_distances(gt)
    firsts, lasts, lens = [], [], []
    for first in range(0, len(gt), step):
        for length in lengths:
            last = last_frame_from_segment_length(dist, first, length)
            if last != -1:
                firsts.append(first)
                lasts.append(last)
                lens.append(float(length))
    first_a, last_a = np.asarray(firsts, dtype=np.int64), np.asarray(lasts, dtype=np.int64)
    length_a = np.asarray(lens, dtype=np.float64)
    delta_gt = _inv(gt[first_a]) @ gt[last_a]
    delta_est = _inv(est[first_a]) @ est[last_a]
    pose_error = _inv(delta_est) @ delta_gt
    return SegmentErrors(
        first_frame=first_a,
        last_frame=last_a,
        length=length_a,
        t_err=translation_error(pose_error) / length_a if len(length_a) else np.zeros(0),
        r_err=rotation_error(pose_error) / length_a if len(length_a) else np.zeros(0),
        speed=length_a / ((last_a - first_a + 1) / FRAME_RATE_HZ) if len(length_a) else np.zeros(0),
    )


def _concat(parts: Iterable[SegmentErrors]) -> SegmentErrors:
    parts = list(parts)
    fields = ("first_frame", "last_frame", "length", "t_err", "r_err", "speed")
    if not parts:
        return SegmentErrors(*(np.zeros(0) for _ in fields))
    return SegmentErrors(*(np.concatenate([getattr(p, f) for p in parts]) for f in fields))


def summarize(segments: SegmentErrors, lengths: Sequence[float]) -> RelativeError:
    """Mean errors over all segments and per length (devkit's saveStats and per-length averages)."""
    per_length = []
    for length in lengths:
        # the devkit matches lengths with |len - length| < 1
        mask = np.abs(segments.length - float(length)) < 1.0
        per_length.append(
            LengthError(
                length_m=float(length),
                n_segments=int(mask.sum()),
                t_err_pct=_mean(segments.t_err[mask]) * 100.0,
                r_err_deg_per_m=float(np.degrees(_mean(segments.r_err[mask]))),
            )
        )
    return RelativeError(
        t_err_pct=_mean(segments.t_err) * 100.0,
        r_err_deg_per_m=float(np.degrees(_mean(segments.r_err))),
        n_segments=len(segments),
        per_length=tuple(per_length),
        segments=segments,
    )


def _mean(values: np.ndarray) -> float:
    return float(np.mean(values)) if len(values) else float("nan")


def kitti_metric(
    gt: np.ndarray, est: np.ndarray, lengths: Sequence[float] = DEVKIT_LENGTHS, step: int = DEVKIT_STEP
) -> RelativeError:
    """(N,4,4) gt and est -> the devkit's translation (%) and rotation (deg/m) errors, overall and per length."""
    return summarize(segment_errors(gt, est, lengths, step), lengths)


def pooled_kitti_metric(
    pairs: Iterable[tuple[np.ndarray, np.ndarray]],
    lengths: Sequence[float] = DEVKIT_LENGTHS,
    step: int = DEVKIT_STEP,
) -> RelativeError:
    """[(gt, est), ...] of several sequences -> the devkit's total: all their segments averaged together."""
    return summarize(_concat(segment_errors(gt, est, lengths, step) for gt, est in pairs), lengths)


def short_relative_error(
    gt: np.ndarray, est: np.ndarray, lengths: Sequence[float] = SHORT_LENGTHS
) -> RelativeError:
    """(N,4,4) gt and est -> the devkit's error on short lengths (m) with every frame a segment start."""
    return kitti_metric(gt, est, lengths, step=1)


def heading_rotation(theta_rad: float) -> np.ndarray:
    """(4,4) rotation by theta_rad about the camera's vertical axis y (KITTI: x right, y down, z forward); a
    positive angle turns z (ahead) towards +x (right)."""
    c, s = np.cos(theta_rad), np.sin(theta_rad)
    R = np.eye(4)
    R[0, 0], R[0, 2], R[2, 0], R[2, 2] = c, s, -s, c
    return R


def fit_heading_offset(
    gt: np.ndarray, est: np.ndarray, short_lengths: Sequence[float] = SHORT_LENGTHS
) -> float:
    """(N,4,4) gt and est T_world_cam -> the constant heading offset th (radians) of the truth against the estimate:
    the rotation about y that best maps the estimate's segment translations onto the truth's in least squares, over
    the short segments (every frame a start) and the devkit ones (a start every 10 frames), each translation divided
    by the segment's nominal length. NaN when the path has no segment (shorter than the shortest length)."""
    gt, est = _check_pair(gt, est)
    seg = _concat([segment_errors(gt, est, short_lengths, 1), segment_errors(gt, est)])
    if len(seg) == 0:
        return float("nan")
    g = (_inv(gt[seg.first_frame]) @ gt[seg.last_frame])[:, :3, 3] / seg.length[:, None]
    e = (_inv(est[seg.first_frame]) @ est[seg.last_frame])[:, :3, 3] / seg.length[:, None]
    # sum g . R_y(th) e = cos(th) * den + sin(th) * num, largest at atan2(num, den)
    num = np.sum(g[:, 0] * e[:, 2] - g[:, 2] * e[:, 0])
    den = np.sum(g[:, 0] * e[:, 0] + g[:, 2] * e[:, 2])
    return float(np.arctan2(num, den))


def remove_heading_offset(est: np.ndarray, theta_rad: float) -> np.ndarray:
    """(N,4,4) est T_world_cam -> R_y(th) @ est @ R_y(th)^T: each body frame turned by th about y (what the relative
    errors see), and the world with it so that a first pose at the identity stays there."""
    R = heading_rotation(theta_rad)
    return R @ np.asarray(est, dtype=np.float64) @ R.T


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """(N,3) src, dst points -> R (3,3), t (3,), s minimising sum |dst - (s R src + t)|^2 (Umeyama 1991)."""
    src, dst = np.asarray(src, dtype=np.float64), np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = float(np.mean(np.sum(xs * xs, axis=1)))
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale and var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


STILL_M = 1e-3  # a truth whose positions all lie within this of their mean does not move (for a Sim(3) fit)


def _moves(p: np.ndarray) -> bool:
    return bool(len(p) >= 2 and np.linalg.norm(p - p.mean(axis=0), axis=1).max() > STILL_M)


def absolute_trajectory_error(gt: np.ndarray, est: np.ndarray, with_scale: bool = False) -> AteResult:
    """(N,4,4) gt and est -> RMSE etc. of camera positions after SE(3) (or Sim(3) with_scale) alignment."""
    gt, est = _check_pair(gt, est)
    p_gt, p_est = gt[:, :3, 3], est[:, :3, 3]
    if with_scale and not _moves(p_gt):
        # a truth that stands still is best fitted by shrinking the estimate to a point: a perfect score from a
        # degenerate alignment. Undefined (NaN), said so by `plvo eval metric`.
        nan = float("nan")
        return AteResult(nan, nan, nan, nan, nan, np.full((4, 4), nan), np.full(len(gt), nan))
    if len(gt) < 3:  # too few points to fix a rotation: align the first positions only
        R, t, s = np.eye(3), p_gt[0] - p_est[0], 1.0
    else:
        R, t, s = umeyama(p_est, p_gt, with_scale)
    errors = np.linalg.norm(p_gt - (s * p_est @ R.T + t), axis=1)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = s * R, t
    return AteResult(
        rmse_m=float(np.sqrt(np.mean(errors**2))),
        mean_m=float(np.mean(errors)),
        median_m=float(np.median(errors)),
        max_m=float(np.max(errors)),
        scale=s,
        T_gt_est=T,
        errors_m=errors,
    )


def evaluate_sequence(
    gt: np.ndarray, est: np.ndarray, name: str = "", short_lengths: Sequence[float] = SHORT_LENGTHS
) -> SequenceEvaluation:
    """(N,4,4) gt and est T_world_cam of one sequence -> every figure of it."""
    gt, est = _check_pair(gt, est)
    # fitted on the default short lengths whatever lengths are shown, so that the angle is the run's alone
    theta = fit_heading_offset(gt, est)
    aligned = remove_heading_offset(est, theta) if np.isfinite(theta) else est
    return SequenceEvaluation(
        name=name,
        n_frames=len(gt),
        path_length_m=float(trajectory_distances(gt)[-1]),
        kitti=kitti_metric(gt, est),
        ate_se3=absolute_trajectory_error(gt, est, with_scale=False),
        ate_sim3=absolute_trajectory_error(gt, est, with_scale=True),
        short=short_relative_error(gt, est, short_lengths),
        heading_offset_deg=float(np.degrees(theta)),
        kitti_aligned=kitti_metric(gt, aligned),
        short_aligned=short_relative_error(gt, aligned, short_lengths),
    )


def evaluate(
    pairs: Mapping[str, tuple[np.ndarray, np.ndarray]], short_lengths: Sequence[float] = SHORT_LENGTHS
) -> Evaluation:
    """{name: (gt, est)} of several sequences -> per-sequence figures and the pooled devkit figures."""
    sequences = tuple(evaluate_sequence(gt, est, name, short_lengths) for name, (gt, est) in pairs.items())
    return Evaluation(
        sequences=sequences,
        kitti=summarize(_concat(s.kitti.segments for s in sequences), DEVKIT_LENGTHS),
        short=summarize(_concat(s.short.segments for s in sequences), tuple(short_lengths)),
        kitti_aligned=summarize(_concat(s.kitti_aligned.segments for s in sequences), DEVKIT_LENGTHS),
        short_aligned=summarize(_concat(s.short_aligned.segments for s in sequences), tuple(short_lengths)),
    )


def _json_number(value: float) -> float | None:
    return None if not np.isfinite(value) else float(value)


def _per_length_json(rel: RelativeError) -> dict[str, dict]:
    return {
        f"{e.length_m:g}": {
            "n_segments": e.n_segments,
            "t_err_pct": _json_number(e.t_err_pct),
            "r_err_deg_per_m": _json_number(e.r_err_deg_per_m),
        }
        for e in rel.per_length
    }


def evaluation_json(ev: SequenceEvaluation) -> dict:
    """The figures of `plvo eval metric --json` (NaN as null): devkit figures at the top level, `segments` and
    `short` keyed by length in metres; `heading_aligned` the same relative errors with the heading offset taken out,
    and the fitted angle `heading_offset_deg`."""
    return {
        "n_frames": ev.n_frames,
        "path_length_m": ev.path_length_m,
        "t_err_pct": _json_number(ev.kitti.t_err_pct),
        "r_err_deg_per_m": _json_number(ev.kitti.r_err_deg_per_m),
        "n_segments": ev.kitti.n_segments,
        "ate_m": ev.ate_se3.rmse_m,
        "ate_sim3_m": _json_number(ev.ate_sim3.rmse_m),
        "sim3_scale": _json_number(ev.ate_sim3.scale),
        "segments": _per_length_json(ev.kitti),
        "short": _per_length_json(ev.short),
        "short_t_err_pct": _json_number(ev.short.t_err_pct),
        "short_r_err_deg_per_m": _json_number(ev.short.r_err_deg_per_m),
        "heading_aligned": {
            "heading_offset_deg": _json_number(ev.heading_offset_deg),
            "t_err_pct": _json_number(ev.kitti_aligned.t_err_pct),
            "r_err_deg_per_m": _json_number(ev.kitti_aligned.r_err_deg_per_m),
            "n_segments": ev.kitti_aligned.n_segments,
            "segments": _per_length_json(ev.kitti_aligned),
            "short": _per_length_json(ev.short_aligned),
            "short_t_err_pct": _json_number(ev.short_aligned.t_err_pct),
            "short_r_err_deg_per_m": _json_number(ev.short_aligned.r_err_deg_per_m),
        },
    }
