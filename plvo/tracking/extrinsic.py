"""The camera-lidar extrinsic's rotation, checked from the data.

The lidar's motion between two scans, registered scan to scan and put into the camera's frame through the stated
extrinsic S = D T (T the true one, D its error, a small rotation in the camera's frame), is D A D^-1 where A is the
camera's motion: its translation is the camera's turned by D, its rotation axis likewise. So for every interval the
tracker checked against the lidar (plvo.tracking.lidar_check) while keeping the camera's own pose, the camera's
translation and rotation vector against the lidar's give D^-1: along a straight road the direction of travel fixes
its pitch and yaw, and turns (their axes) its pitch and roll. Each pair (a, b) gives a - b = -[b]x theta to first
order in theta (D^-1 = exp(theta)); theta is the weighted least-squares solution with a zero-mean prior of
`crosscheck.extrinsic_prior_deg` a component, so that an axis nothing excited stays at the stated calibration
instead of fitting the noise; its spread is the larger of the posterior's and a grouped jackknife's (few intervals
measure their own weights badly, and the posterior then calls a chance fit certain).

The camera's own motion is not free of S: its depth priors are the scan seen through it, so it follows the stated
extrinsic in part and an error is read short or long (0.5-1.6x its size on the synthetic town and the realistic twin
of 04), and a bias of the registrations' own reads as one (real KITTI 04: +0.2 deg of pitch in the lidar's direction
of travel against the truth's, where the camera's is within 0.07): docs/crosscheck.md, which is why only a gross
error is named. Only the scan-to-scan registration carries D: a registration to a map of scans placed at the
camera's poses through S cancels it (the map is turned as the scan is).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from plvo.geometry import se3
from plvo.geometry.lines import hat_batch

_MIN_INTERVALS = 8
_MIN_STEP_M = 0.5  # a shorter step's direction is the registrations' noise, not the travel's
_WINDOW = 300  # the newest intervals kept: the extrinsic is constant, and a bounded window bounds the cost
_JACKKNIFE_GROUPS = 10  # an estimate's spread is also read from 10 solves, each without a tenth of the intervals


@dataclass(frozen=True)
class ExtrinsicEstimate:
    """correction_deg: the rotation vector (degrees, camera frame) C that turns the stated extrinsic into the one the
    motions agree with (T_cam_velo <- C T_cam_velo); sigma_deg its standard deviation a component (the larger of the
    posterior's and the grouped jackknife's); n_intervals the intervals used; translation_rms_m / rotation_rms_deg
    what the pairs left after it."""

    correction_deg: tuple[float, ...]  # three
    sigma_deg: tuple[float, ...]
    n_intervals: int
    translation_rms_m: float
    rotation_rms_deg: float

    def departs(self, by_deg: float, sigmas: float) -> bool:
        """Some component farther than by_deg from the stated extrinsic by `sigmas` standard deviations: worth
        naming (an estimate that far by chance is not)."""
        c, s = np.abs(self.correction_deg), np.asarray(self.sigma_deg)
        return bool(np.any(c - sigmas * s > by_deg))

    def as_dict(self) -> dict:
        return {"correction_deg": [round(float(v), 4) for v in self.correction_deg],
                "sigma_deg": [round(float(v), 4) for v in self.sigma_deg], "n_intervals": self.n_intervals,
                "translation_rms_m": round(self.translation_rms_m, 4),
                "rotation_rms_deg": round(self.rotation_rms_deg, 4)}


class ExtrinsicEstimator:
    """Checked intervals in (the camera's motion and the lidar's, both T_prev_cur in the camera's frame through the
    stated extrinsic), an ExtrinsicEstimate out."""

    def __init__(self, prior_deg: float):
        self.prior_rad = float(np.radians(prior_deg))
        self._pairs: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=_WINDOW)
        self._n = 0

    @property
    def n_intervals(self) -> int:
        return self._n

    def interval(self, T_camera: np.ndarray, T_lidar: np.ndarray) -> None:
        A, L = np.asarray(T_camera, float), np.asarray(T_lidar, float)
        if not (np.isfinite(A).all() and np.isfinite(L).all()):
            return
        self._pairs.append((A, L))
        self._n += 1

    def estimate(self) -> ExtrinsicEstimate | None:
        """The correction, or None while fewer than _MIN_INTERVALS intervals moved far enough."""
        pairs = [(A, L) for A, L in self._pairs if np.linalg.norm(L[:3, 3]) >= _MIN_STEP_M]
        if len(pairs) < _MIN_INTERVALS:
            return None
        A = np.asarray([p[0] for p in pairs])
        L = np.asarray([p[1] for p in pairs])
        # the camera's step scaled to the lidar's length: a scale error is no direction error (and lies along b,
        # where [b]x theta has no component anyway)
        ta = A[:, :3, 3] * (np.linalg.norm(L[:, :3, 3], axis=1) / np.maximum(np.linalg.norm(A[:, :3, 3], axis=1),
                                                                            1e-9))[:, None]
        tb = L[:, :3, 3]
        ra = Rotation.from_matrix(A[:, :3, :3]).as_rotvec()
        rb = Rotation.from_matrix(L[:, :3, :3]).as_rotvec()
        # solved on all, then again without the worst tenth of the intervals (a registration gone wrong)
        theta, _, _, _, sig_t, sig_r = self._solve(ta, tb, ra, rb)
        turned = Rotation.from_rotvec(theta)
        bad = (((ta - turned.apply(tb)) / sig_t) ** 2).sum(axis=1) + \
            (((ra - turned.apply(rb)) / sig_r) ** 2).sum(axis=1)
        keep = bad <= np.quantile(bad, 0.9)
        if keep.sum() < _MIN_INTERVALS:
            return None
        ta, tb, ra, rb = ta[keep], tb[keep], ra[keep], rb[keep]
        theta, cov, res_t, res_r, _, _ = self._solve(ta, tb, ra, rb)
        sigma = np.maximum(np.sqrt(np.diag(cov)), self._jackknife_sigma(ta, tb, ra, rb))
        return ExtrinsicEstimate(tuple(float(v) for v in np.degrees(theta)),
                                 tuple(float(v) for v in np.degrees(sigma)), int(keep.sum()),
                                 float(np.sqrt(np.mean(res_t ** 2))), float(np.degrees(np.sqrt(np.mean(res_r ** 2)))))

    def _jackknife_sigma(self, ta: np.ndarray, tb: np.ndarray, ra: np.ndarray, rb: np.ndarray) -> np.ndarray:
        """(3,) each component's standard deviation from a grouped jackknife: solved again without each of
        _JACKKNIFE_GROUPS runs of consecutive intervals. The posterior's covariance trusts the weights, which few
        intervals measure badly: on the realistic twin of KITTI 03 run with a keyframe every 2 frames, 9 intervals of a
        nearly straight road (turns of 0.1-0.3 deg) gave a roll of 4.1 +- 0.67 deg, which leave-one-out solves spread
        from -0.4 to 3.4 deg; the twin's extrinsic is 0.05 deg off in roll. Kept the larger of the two spreads."""
        n = len(ta)
        groups = np.array_split(np.arange(n), min(_JACKKNIFE_GROUPS, n))
        thetas = []
        for g in groups:
            keep = np.ones(n, bool)
            keep[g] = False
            thetas.append(self._solve(ta[keep], tb[keep], ra[keep], rb[keep])[0])
        th = np.asarray(thetas)
        k = len(th)
        return np.sqrt((k - 1) / k * np.sum((th - th.mean(axis=0)) ** 2, axis=0))

    def _solve(self, ta: np.ndarray, tb: np.ndarray, ra: np.ndarray, rb: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Gauss-Newton on theta (two steps from zero: the angles are tenths of a degree), each component of each kind
        of pair weighed by its own residual's spread (a registration's lateral step is far noisier than its
        vertical one: on real KITTI 04 ~1 deg of direction against ~0.2) -> theta, its covariance, the residuals
        and the two spreads ((3,) each)."""
        # the spreads from the residuals at the stated extrinsic, floored
        sig_t = np.maximum(_robust_sigma(ta - tb), 1e-3)
        sig_r = np.maximum(_robust_sigma(ra - rb), np.radians(0.005))
        theta = np.zeros(3)
        for _ in range(2):
            R = Rotation.from_rotvec(theta).as_matrix()
            bt, br = tb @ R.T, rb @ R.T
            et, er = ta - bt, ra - br  # (n,3) residuals at theta
            wt, wr = np.tile(1 / sig_t ** 2, len(et)), np.tile(1 / sig_r ** 2, len(er))
            Jt, Jr = -hat_batch(bt).reshape(-1, 3), -hat_batch(br).reshape(-1, 3)  # d(R b)/d(delta) = -[R b]x
            H = (Jt * wt[:, None]).T @ Jt + (Jr * wr[:, None]).T @ Jr + np.eye(3) / self.prior_rad ** 2
            g = (Jt * wt[:, None]).T @ et.ravel() + (Jr * wr[:, None]).T @ er.ravel() - theta / self.prior_rad ** 2
            delta = np.linalg.solve(H, g)
            theta = (Rotation.from_rotvec(delta) * Rotation.from_rotvec(theta)).as_rotvec()
        R = Rotation.from_rotvec(theta).as_matrix()
        res_t = np.linalg.norm(ta - tb @ R.T, axis=1)
        res_r = np.linalg.norm(ra - rb @ R.T, axis=1)
        return theta, np.linalg.inv(H), res_t, res_r, sig_t, sig_r


def _robust_sigma(e: np.ndarray) -> np.ndarray:
    """(n,3) -> (3,) each component's standard deviation from its median absolute deviation (a wrong registration
    does not inflate it)."""
    return 1.4826 * np.median(np.abs(e - np.median(e, axis=0)), axis=0)


def corrected(T_cam_velo: np.ndarray, correction_deg: Sequence[float]) -> np.ndarray:
    """The extrinsic turned by a correction (rotation vector, degrees, camera frame): C T_cam_velo, made rigid."""
    C = np.eye(4)
    C[:3, :3] = Rotation.from_rotvec(np.radians(np.asarray(correction_deg, float))).as_matrix()
    return se3.orthonormalize(C @ np.asarray(T_cam_velo, float))
