"""The camera-lidar time offset, estimated from the data: when the lidar's scans are taken offset_s after the images
(a driver's clock, a pairing one frame off), the lidar's rotation between two scans is the camera's rotation
between the two images' times plus offset_s.

At constant velocity an offset cannot be told from a shift of the extrinsic along the road, and nothing shows it;
where the turn rate changes (a turn's start and end), the lidar's rotation over an interval runs ahead of (or
behind) the camera's by the change of rate times the offset. So the estimate compares, for every interval the
tracker checked against the lidar (plvo.tracking.lidar_check), the lidar's rotation with the camera's over the
same interval shifted by a trial offset, the camera's orientation interpolated between its frames (rotations only:
the images alone fix them, the lidar's depth does not enter), and takes the offset of least squared angle:
a grid of 5 ms over +-max_s, refined by a parabola. Its standard deviation follows from the fit's curvature and
its residual; the estimate is observable when that is below `crosscheck.offset_sigma_s` (a straight road at
steady speed never is: the estimate is then withheld, not guessed).
"""

from __future__ import annotations

from bisect import bisect_left
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

_GRID_S = 0.005
_MIN_INTERVALS = 8
# Intervals near a frame whose pose was not the camera's own (the lidar's, the motion model's, the camera matched
# again from the lidar's) are left out: there the camera's orientation is the lidar's or a guess, and for this long
# after it the tracker settles on landmarks made anew. With them, on the realistic twin of KITTI 08 (the camera
# overruled by the lidar at frames 1, 11 and 15-35, then a turn), the camera's rotation 0.2 deg off at single
# intervals of frames 36-60 held the estimate at +42 ms +- 5 (the offset is -3 ms); named, the run started again
# with it and ended 3.5x less accurate over 400 frames. Without them the first estimates there are -5 and -4 ms.
_SETTLE_S = 1.0
_FRAME_S = 0.2  # beyond a frame period of every camera the tracker takes (10-20 Hz)
# The newest intervals kept: an offset is constant, and a bounded window bounds an estimate's cost over a long run
# (~600 frames at a keyframe every 3)
_WINDOW = 200
# The camera's turn rate, averaged over half a second, must vary by this much (its spread, deg/s) for an offset to
# be told: on a straight road the frame-to-frame jitter of the rotations (~0.05 deg) alone "fits" an offset of tens
# of ms with a standard deviation of a few (real KITTI 04: -17 +- 4.5 ms at no offset, 165 +- 8 ms at 100 ms), where
# a turn's start and end (a town's corner: tens of deg/s) pin it to a few ms.
MIN_RATE_SPREAD_DEG_S = 3.0
_SMOOTH_S = 0.5


@dataclass(frozen=True)
class OffsetEstimate:
    """offset_s: the lidar's scans are taken this long after the images (s; negative: before); sigma_s its
    standard deviation; n_intervals: intervals used; observable: sigma_s below the config's bound."""

    offset_s: float
    sigma_s: float
    n_intervals: int
    observable: bool
    rate_spread_deg_s: float = 0.0  # how much the turn rate varied (MIN_RATE_SPREAD_DEG_S)

    def departs_from(self, stated_s: float, by_s: float, sigmas: float) -> bool:
        """Observable, and farther than by_s from the stated offset by `sigmas` standard deviations: worth naming.
        Farther than by_s alone is not enough: an estimate from few intervals can be that far by chance."""
        return self.observable and abs(self.offset_s - stated_s) - sigmas * self.sigma_s > by_s

    def as_dict(self) -> dict:
        return {"offset_s": round(self.offset_s, 4), "sigma_s": round(self.sigma_s, 4),
                "n_intervals": self.n_intervals, "observable": self.observable,
                "rate_spread_deg_s": round(self.rate_spread_deg_s, 2)}


class TimeOffsetEstimator:
    """Frames' orientations and the lidar's checked intervals in, an OffsetEstimate out."""

    def __init__(self, max_s: float, sigma_bound_s: float):
        self.max_s = max_s
        self.sigma_bound_s = sigma_bound_s
        self._times: deque[float] = deque()
        self._rots: deque[np.ndarray] = deque()
        self._intervals: deque[tuple[float, float, np.ndarray]] = deque(maxlen=_WINDOW)
        self._untrusted: list[float] = []  # times (increasing) of frames whose orientation was not the camera's own
        self._n = 0

    def frame(self, time_s: float, R_world_cam: np.ndarray, own: bool = True) -> None:
        """A frame's orientation; own: the camera's own tracking gave it (not the lidar, nor a guess)."""
        last = max(self._times[-1] if self._times else -np.inf, self._untrusted[-1] if self._untrusted else -np.inf)
        if not time_s > last:
            return  # the interpolation and the bisections need increasing times; a repeated time adds nothing
        R = np.array(R_world_cam, float)
        if not _is_rotation(R):  # a broken pose (a fault upstream) is no orientation: left out with what reads it
            self._untrusted.append(float(time_s))
            return
        self._times.append(float(time_s))
        self._rots.append(R)
        if not own:
            self._untrusted.append(float(time_s))

    def interval(self, t_first: float, t_last: float, R_lidar: np.ndarray) -> None:
        """The lidar's rotation (camera frame, first -> last) between the scans paired with two frames' times."""
        R = np.array(R_lidar, float)
        if not t_last > t_first or not _is_rotation(R):
            return
        self._intervals.append((float(t_first), float(t_last), R))
        self._n += 1
        oldest = self._intervals[0][0] - self.max_s - 1.0
        while len(self._times) > 2 and self._times[1] < oldest:  # frames no interval in the window reaches
            self._times.popleft()
            self._rots.popleft()
        del self._untrusted[:bisect_left(self._untrusted, oldest - _SETTLE_S)]

    def _usable(self, t_first: float, t_last: float) -> bool:
        """No frame not the camera's own where the interval's shifted span reads the camera's orientation (a frame
        period beyond +-max_s), nor within _SETTLE_S before that span."""
        lo, hi = t_first - self.max_s - _SETTLE_S, t_last + self.max_s + _FRAME_S
        i = bisect_left(self._untrusted, lo)  # the first at or after lo
        return i == len(self._untrusted) or self._untrusted[i] > hi

    @property
    def n_intervals(self) -> int:
        """Intervals added so far (the estimate uses the newest _WINDOW of them)."""
        return self._n

    def estimate(self) -> OffsetEstimate | None:
        """The least-squares offset, or None while too few intervals lie inside the tracked span +- max_s."""
        if len(self._times) < 3:
            return None
        t0, t1 = self._times[0] + self.max_s, self._times[-1] - self.max_s
        use = [iv for iv in self._intervals if iv[0] >= t0 and iv[1] <= t1 and self._usable(iv[0], iv[1])]
        if len(use) < _MIN_INTERVALS:
            return None
        times = np.asarray(self._times)
        slerp = Slerp(times, Rotation.from_matrix(np.asarray(self._rots)))
        lo, hi = times[0], times[-1]
        ta = np.array([iv[0] for iv in use])
        tb = np.array([iv[1] for iv in use])
        lidar_inv = np.transpose(np.asarray([iv[2] for iv in use]), (0, 2, 1))  # (n,3,3) inverse rotations

        def residuals(offsets: np.ndarray) -> np.ndarray:
            """(G,) trial offsets -> (G,n,3) rotation vectors (rad) of the lidar's rotations against the camera's,
            every offset and interval in one call (a loop over the grid cost 0.1 s at 200 intervals)."""
            a = np.clip(ta[None, :] + offsets[:, None], lo, hi).ravel()
            b = np.clip(tb[None, :] + offsets[:, None], lo, hi).ravel()
            camera = slerp(a).inv() * slerp(b)
            lidar = Rotation.from_matrix(np.tile(lidar_inv, (len(offsets), 1, 1)))
            return (lidar * camera).as_rotvec().reshape(len(offsets), len(ta), 3)

        grid = np.linspace(-self.max_s, self.max_s, 2 * int(round(self.max_s / _GRID_S)) + 1)
        # Intervals whose residual is far larger than the rest's at every offset (a wrong registration, a camera
        # step gone wrong) are left out: the worst tenth, judged at the offset that fits the rest best
        per = (residuals(grid) ** 2).sum(axis=2)  # (grid, n)
        best = per[int(np.argmin(per.sum(axis=1)))]
        keep = best <= np.quantile(best, 0.9)
        if keep.sum() < _MIN_INTERVALS:
            return None
        ta, tb, lidar_inv = ta[keep], tb[keep], lidar_inv[keep]
        cost = per[:, keep].sum(axis=1)
        step = float(grid[1] - grid[0])
        k = int(np.clip(np.argmin(cost), 1, len(grid) - 2))
        c_m, c_0, c_p = cost[k - 1], cost[k], cost[k + 1]
        curvature = (c_m - 2 * c_0 + c_p) / step ** 2  # d2cost/doffset2 = 2 sum(dr/doffset)^2
        shift = 0.5 * (c_m - c_p) / (c_m - 2 * c_0 + c_p) * step if curvature > 0 else 0.0
        offset = float(grid[k] + np.clip(shift, -step, step))
        n = len(ta)
        residual = float((residuals(np.array([offset])) ** 2).sum())
        noise = residual / max(1, 3 * n - 1)  # per rotation-vector component
        sigma = float(np.sqrt(2 * noise / curvature)) if curvature > 0 else float("inf")
        spread = _rate_spread(times, slerp)
        return OffsetEstimate(offset, sigma, n, bool(sigma < self.sigma_bound_s and spread >= MIN_RATE_SPREAD_DEG_S),
                              spread)


def _is_rotation(R: np.ndarray) -> bool:
    """A finite proper rotation to 1e-3 (far looser than any pose's rounding; scipy's Rotation.from_matrix projects
    what is near one, but a NaN matrix fails its SVD and a left-handed one raises), so that one broken pose cannot
    end a run when its summary estimates."""
    return R.shape == (3, 3) and bool(np.isfinite(R).all()) and bool(np.abs(R @ R.T - np.eye(3)).max() < 1e-3) \
        and np.linalg.det(R) > 0


def _rate_spread(times: np.ndarray, slerp: Slerp) -> float:
    """The spread (deg/s, the norm of the per-axis standard deviations) of the camera's angular rate averaged over
    _SMOOTH_S windows: how much the turn rate changed."""
    t = np.arange(times[0], times[-1] - _SMOOTH_S, _SMOOTH_S / 2)
    if len(t) < 3:
        return 0.0
    rates = (slerp(t).inv() * slerp(t + _SMOOTH_S)).as_rotvec() / _SMOOTH_S
    return float(np.degrees(np.linalg.norm(rates.std(axis=0))))
