"""Motion compensation of a spinning lidar's sweep ("deskewing"): every return moved to the frame's instant.

A spinning lidar takes its returns over a whole sweep (0.1 s at 10 Hz) and most drivers deliver each return in the
sensor frame at its own time: at 14 m/s the returns at the sweep's end are 1.4 m from where the start's would put
them, and a registration of such a scan bends the trajectory. With the sensor's motion over the sweep known, each
return p taken t seconds after the reference instant (the frame's time, when the camera was triggered) is moved to
the sensor frame at that instant: p_ref = exp(t xi) p, with xi the sensor's body twist (rho, phi: metres and
radians a second, in its own frame) under constant velocity, as KISS-ICP and CT-ICP deskew.

The twist comes from the visual odometry: the tracker has solved the frame's pose before the scan is needed, so
the camera's motion from the previous frame to this one (`twist_from_motion`) gives it without any lidar step, and
the back end's job waits one frame for the motion to the next one, which the returns after the frame's time follow
(`Sweep`).

The returns' times are the data's own where it has them (ROS PointCloud2 `t`/`time`/`offset_time`, as
`Frame.scan_time`, seconds relative to the frame's time) and otherwise follow from the azimuth (`azimuth_times`):
a lidar turning clockwise seen from above once a frame, facing forward (azimuth 0) at the frame's time, as KITTI's
HDL-64E is triggered and as the KITTI twins' sweep is simulated (plvo_synth.twin.lidars).

numpy only: the tracking thread deskews a keyframe's registration scan once, for both workers that register it
(plvo.runtime.system), when the motion after the frame is known.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plvo.errors import ConfigError, PlvoError
from plvo.geometry import se3
from plvo.types import Frame

SWEEP_S = 0.1  # a 10 Hz lidar's sweep


def azimuth_times(points: np.ndarray, sweep_s: float = SWEEP_S) -> np.ndarray:
    """(N,>=2) lidar-frame points (x forward, y left) -> (N,) seconds after the frame's time at which each was taken,
    for a clockwise sweep facing forward at the frame's time: -sweep/2 (behind, start) to +sweep/2 (behind, end)."""
    p = np.asarray(points)
    a = np.arctan2(p[:, 1].astype(np.float64), p[:, 0].astype(np.float64))
    return -a / (2.0 * np.pi) * sweep_s


def twist_from_motion(T_prev_cur: np.ndarray, dt: float, T_cam_velo: np.ndarray) -> np.ndarray:
    """The camera's relative motion (4,4) from the previous frame to this one, dt seconds apart, and the lidar's
    extrinsic T_cam_velo (4,4) -> (6,) the lidar's body twist (rho, phi) per second, constant velocity assumed."""
    if not dt > 0:
        raise PlvoError(f"deskew: frames must be a positive time apart, got {dt} s")
    T_lidar = se3.inv(T_cam_velo) @ np.asarray(T_prev_cur, float) @ T_cam_velo
    return se3.log(T_lidar) / dt


def deskew(scan: np.ndarray, times: np.ndarray, twist: np.ndarray) -> np.ndarray:
    """(N,3|4) lidar-frame returns (extra columns such as intensity kept), (N,) seconds after the reference instant,
    (6,) body twist (rho, phi) -> a copy with every return in the sensor frame at the reference instant."""
    pts = np.asarray(scan)
    t = np.asarray(times, np.float64)
    if pts.ndim != 2 or pts.shape[1] < 3 or t.shape != (len(pts),):
        raise PlvoError(f"deskew: scan (N,3|4) and times (N,) expected, got {pts.shape} and {t.shape}")
    xi = np.asarray(twist, np.float64).reshape(6)
    out = np.array(pts, copy=True)
    if not np.any(xi):
        return out
    rho, phi = xi[:3], xi[3:]
    theta = np.linalg.norm(phi)
    p = pts[:, :3].astype(np.float64)
    # exp(t xi) applied to p, written out per point (Rodrigues for the rotation, the SE(3) left Jacobian for the
    # translation): one numpy pass over the scan instead of a 4x4 matrix per return
    if theta < 1e-12:
        moved = p + np.outer(t, rho)
    else:
        k = phi / theta
        a = t * theta  # each return's rotation angle
        c, s = np.cos(a), np.sin(a)
        K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        # Rodrigues, R(a) p = p + sin a (K p) + (1 - cos a) (K^2 p), with K p and K^2 p as two (N,3)x(3,3) products;
        # the SE(3) left Jacobian's translation V(t phi) t rho = t rho + (1 - cos a)/theta K rho
        # + (a - sin a)/theta K^2 rho
        Kr, KKr = K @ rho, K @ K @ rho
        # summed in place, term by term in the order written above (the same roundings as one expression, without
        # an (N,3) temporary for every term)
        moved = p @ K.T
        moved *= s[:, None]
        moved += p
        term = p @ (K @ K).T
        one_minus_c = 1.0 - c
        term *= one_minus_c[:, None]
        moved += term
        for weight, vector in ((t, rho), (one_minus_c / theta, Kr), ((a - s) / theta, KKr)):
            np.multiply(weight[:, None], vector, out=term)
            moved += term
    out[:, :3] = moved.astype(out.dtype, copy=False)
    return out


@dataclass(frozen=True)
class Sweep:
    """How one scan is deskewed: the sensor's body twist (6,) (rho, phi per second) before the frame's time (over the
    step from the previous frame) and after it (over the step to the next frame), either None while unknown, and
    the returns' times (N,) relative to the frame's time (None: from the azimuth, `azimuth_times`).

    A return taken before the frame's time moves with the motion before it, one taken after with the motion after
    it: the sweep spans half a step on each side, and a vehicle's roll and pitch rates change from one step to the
    next (on the twins, whose truth has KITTI's roll and pitch, one twist for the whole sweep left 0.02-0.04 deg rms
    of roll and pitch in each local-map alignment, against 0.005-0.011 deg with both). With one side known, its
    twist serves the whole sweep; with none, the scan is left as it is."""

    before: np.ndarray | None
    after: np.ndarray | None = None
    times: np.ndarray | None = None

    def with_after(self, twist: np.ndarray) -> Sweep:
        """The same sweep once the motion to the next frame is known."""
        return Sweep(self.before, np.asarray(twist, float), self.times)

    def apply(self, scan: np.ndarray) -> np.ndarray:
        """(N,3|4) the scan the times belong to (same rows, e.g. plvo.lidar.scan.registration_scan's) -> deskewed."""
        if self.before is None and self.after is None:
            return np.array(scan, copy=True)
        times = azimuth_times(scan) if self.times is None else np.asarray(self.times, np.float64)
        if len(times) != len(scan):
            raise PlvoError(f"deskew: {len(times)} return times for a scan of {len(scan)} returns")
        if self.before is None or self.after is None:
            known = self.after if self.before is None else self.before
            assert known is not None
            return deskew(scan, times, known)
        out = np.array(scan, copy=True)
        early = times <= 0.0
        out[early] = deskew(scan[early], times[early], self.before)
        out[~early] = deskew(scan[~early], times[~early], self.after)
        return out


def needs_deskew(frame: Frame, mode: str) -> bool:
    """Whether a frame's scan is deskewed under RegistrationConfig.deskew: "auto" when the source says it is not
    motion-compensated (Frame.scan_compensated), "on" always, "off" never."""
    if mode == "auto":
        return not frame.scan_compensated
    if mode in ("on", "off"):
        return mode == "on"
    raise ConfigError(f"config key 'registration.deskew' must be auto, on or off, got {mode!r}")
