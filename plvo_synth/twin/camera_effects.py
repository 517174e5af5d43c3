"""What a real KITTI camera makes of a twin's rendered scene: exposure, blur, vignetting, response, noise,
rectification.

KITTI's cam0 is a Point Grey Flea2 FL2-14S3M (Sony ICX267 CCD, global shutter, 8 bit) cropped to 1392x512, triggered
when the lidar faces forward, its shutter set by auto exposure up to 2 ms (Geiger et al., IJRR 2013; KITTI's setup
page). Its images reach users rectified: the raw image (f ~ 984 px, strong barrel distortion) resampled bilinearly to
a pinhole image of f ~ 721 px, with a calibration that leaves a residual. So a rectified pixel near the image's centre
is 1.36 raw pixels wide, and near its left and right edges only 0.73 raw pixels radially: the real images are
sharp in the middle and blurred radially at the sides, and their noise is correlated. CameraRealism holds each
effect's setting; the defaults are KITTI's, measured on the real clips by scripts/camera_stats.py (docs/twins.md
has the figures) or taken from those sources. IDEAL_CAMERA reproduces the twins' images as they were before any of
this, byte for byte.

develop() runs the physical order on the frame's linear radiance (rendered on the rectified pinhole grid): motion
blur over the exposure (each pixel's image motion from its depth and the camera's motion from the frame's time to
the shutter's close), vignetting, auto exposure (meters the image, sets the gain, with the controller's lag error);
then on the raw sensor's grid (KITTI cam0's raw calibration, RAW_*): the optics' blur, the linear response, shot and
read noise, the ADC's clip and 8-bit quantisation; then the rectification back to the pinhole grid (bilinear, with
the calibration's residual warp) and its 8-bit rounding. IDEAL_CAMERA keeps the old order on the pinhole grid (tone
curve, then the blur, then white noise from the renderer's noise bank), which is why "shoulder" exists.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from plvo.errors import SynthError

RESPONSES = ("linear", "shoulder")
NOISE_MODELS = ("sensor", "bank")
SHOULDER = 0.6  # "shoulder" response: linear up to here, then a soft roll-off towards 1
# KITTI cam0's raw camera, calib_cam_to_cam.txt of 2011-09-26 (the raw recording day of odometry 03 and drive 0009):
# S_00, K_00 (fx, fy, cx, cy), D_00 (k1, k2, p1, p2, k3) and R_rect_00 (raw camera -> rectified camera). The other
# days' lens is the same model; these stand for every twin.
RAW_SIZE = (1392, 512)
RAW_K = np.array([[9.842439e02, 0.0, 6.900000e02], [0.0, 9.808141e02, 2.331966e02], [0.0, 0.0, 1.0]])
RAW_DISTORTION = np.array([-3.728755e-01, 2.037299e-01, 2.219027e-03, 1.383707e-03, -7.233722e-02])
RAW_R_RECT = np.array([[9.999239e-01, 9.837760e-03, -7.445048e-03], [-9.869795e-03, 9.999421e-01, -4.278459e-03],
                       [7.402527e-03, 4.351614e-03, 9.999631e-01]])
MOTION_SAMPLES_PER_PX = 2.0  # samples along each pixel's motion, per pixel of its length
MAX_MOTION_SAMPLES = 32
MIN_METERED_SHARE = 0.2  # a mover covering more of the metered area than 80 %: meter it all
MAX_MOTION_PX = 40.0  # a blur longer than this (a point a few cm from the lens) is cut to it


@dataclass(frozen=True)
class CameraRealism:
    """A camera's imperfections, each with the magnitude KITTI's cam0 has (sources in docs/twins.md).

    target_grey: auto exposure brings the mean of the image below the principal point's row to this (linear, full
    scale 1); gain_range: the gain it may set. The real controller lags the scene (tenths of a second to seconds);
    each frame is rendered on its own, so the lag is modelled in two parts: ae_ignore_movers meters the static
    scene alone (a passing car is gone before a lagging controller has followed it), and ae_wander is its error on
    slow changes, a seeded process of the twin's time (log gain, knots every ae_knot_s seconds, each within
    +-ae_wander, linear between, a knot repeating the previous one with chance ae_hold_share): the real clips'
    exposure ramps and holds.
    shutter_s: the exposure time (motion blur from the frame's time to the shutter's close).
    vignetting_b1, vignetting_b2: log V(r) = b1 r^2 + b2 r^4, r the distance from the principal point over f.
    raw_sensor: form the image on KITTI cam0's raw sensor grid (RAW_*) and rectify it as KITTI did; False: on the
    rectified grid itself. optics_blur_px: Gaussian sigma of the lens and the pixel's area, in the pixels of that
    grid. response: "linear" (the CCD's, to full scale, clipped by the ADC) or "shoulder" (the old soft roll-off,
    applied before the blur). noise_model: "sensor" (fresh shot and read noise a frame) or "bank" (the renderer's
    white read noise bank, the old images); read_noise_grey: read noise (grey levels, 1 sigma); shot_noise_grey:
    shot noise variance per grey level of signal (grey^2 / grey), both per pixel of the grid the image forms on.
    rectification_residual_px: RMS over the image of the smooth warp the rectification leaves (a seeded residual
    radial and tangential distortion, fixed for the twin; rectified pixels)."""

    # measured on KITTI 04 and raw drive 0009, frames 0-50 (scripts/camera_stats.py), unless a source is named
    target_grey: float = 0.35  # real mean grey below the principal row: 89.9 and 88.3 of 255
    gain_range: tuple[float, float] = (0.5, 2.5)  # the old twins' (not measured)
    ae_ignore_movers: bool = True
    ae_wander: float = 0.08  # with ae_knot_s, ae_hold_share: the real tracked exposure steps' ramps (up to 1-4 % a
    ae_knot_s: float = 2.0  # frame for 1-2.5 s) and holds (0009 frames 29-35: under 0.03 % a frame)
    ae_hold_share: float = 0.3
    shutter_s: float = 2.0e-3  # KITTI's shutter cap (Geiger et al., IJRR 2013); the real sides' blur needs it
    vignetting_b1: float = -0.24  # V(0.5) 0.950, V(0.85) 0.907: real 0.962 / 0.898 (04), 0.939 / 0.915 (0009)
    vignetting_b2: float = 0.144
    raw_sensor: bool = True  # calib_cam_to_cam.txt: 1392x512 raw, f 984 px, k1 -0.37, rectified to f ~ 721 px
    optics_blur_px: float = 0.5  # raw px: edge spread 0.75 rectified px (real 0.73 / 0.78), 1.0 at the sides
    response: str = "linear"  # a CCD's; real skies clip hard (3 % and 9 % of pixels at 255); noise grows as shot
    noise_model: str = "sensor"
    read_noise_grey: float = 0.5  # raw px: with shot_noise_grey, the real noise against brightness (0.6 grey in the
    shot_noise_grey: float = 0.12  # dark, 1.3-1.7 at mid-grey as the rectified frames read it)
    rectification_residual_px: float = 0.3  # typical checkerboard calibration residual; not measurable here

    @property
    def is_ideal(self) -> bool:
        return self == IDEAL_CAMERA

    def check(self) -> None:
        """SynthError naming the first setting out of its range."""
        if self.response not in RESPONSES:
            raise SynthError(f"camera.response {self.response!r}: choose from {', '.join(RESPONSES)}")
        if self.noise_model not in NOISE_MODELS:
            raise SynthError(f"camera.noise_model {self.noise_model!r}: choose from {', '.join(NOISE_MODELS)}")
        for flag in ("raw_sensor", "ae_ignore_movers"):
            if not isinstance(getattr(self, flag), bool):
                raise SynthError(f"camera.{flag} {getattr(self, flag)!r}: expected true or false")
        if self.raw_sensor and (self.response != "linear" or self.noise_model != "sensor"):
            raise SynthError("camera.raw_sensor needs camera.response 'linear' and camera.noise_model 'sensor' (the "
                             "shoulder and the noise bank are the old pinhole camera's)")
        if not isinstance(self.gain_range, (tuple, list)) or len(self.gain_range) != 2:
            raise SynthError(f"camera.gain_range {self.gain_range!r}: expected two numbers, lowest first")
        lo = _number("camera.gain_range[0]", self.gain_range[0], 0.01, 100.0)
        if lo > _number("camera.gain_range[1]", self.gain_range[1], 0.01, 100.0):
            raise SynthError(f"camera.gain_range {self.gain_range!r}: the first must not exceed the second")
        for name, a, b in (("target_grey", 0.01, 1.0), ("ae_wander", 0.0, 1.0), ("ae_knot_s", 0.1, 60.0),
                           ("ae_hold_share", 0.0, 0.95), ("shutter_s", 0.0, 0.05), ("optics_blur_px", 0.0, 5.0),
                           ("vignetting_b1", -3.0, 3.0), ("vignetting_b2", -3.0, 3.0), ("read_noise_grey", 0.0, 20.0),
                           ("shot_noise_grey", 0.0, 5.0), ("rectification_residual_px", 0.0, 5.0)):
            _number(f"camera.{name}", getattr(self, name), a, b)


def _number(name: str, value: object, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not lo <= float(value) <= hi:
        raise SynthError(f"realism {name} = {value!r}: expected a number in [{lo}, {hi}]")
    return float(value)


IDEAL_CAMERA = CameraRealism(target_grey=0.40, ae_ignore_movers=False, ae_wander=0.0, shutter_s=0.0,
                             vignetting_b1=0.0, vignetting_b2=0.0, raw_sensor=False, optics_blur_px=0.6,
                             response="shoulder", noise_model="bank", read_noise_grey=1.5, shot_noise_grey=0.0,
                             rectification_residual_px=0.0)


# ---------------------------------------------------------------------------------------------- exposure


def shoulder(x: np.ndarray) -> np.ndarray:
    """Linear up to SHOULDER, then a soft roll-off towards 1 (a bright sky keeps its gradient instead of clipping)."""
    over = np.maximum(x - SHOULDER, 0.0)
    return np.minimum(x, SHOULDER) + (1.0 - SHOULDER) * (1.0 - np.exp(-over / (1.0 - SHOULDER)))


def metered_gain(image: np.ndarray, horizon_row: int, camera: CameraRealism,
                 static: np.ndarray | None = None) -> float:
    """The gain that brings the mean below the principal point's row (over the `static` pixels, (H,W) bool, when
    given and camera.ae_ignore_movers) to camera.target_grey, within gain_range."""
    rows = slice(horizon_row if horizon_row < len(image) else 0, None)  # a principal point below the image: all
    lower = image[rows]
    if camera.ae_ignore_movers and static is not None:
        keep = static[rows]
        if keep.sum() >= MIN_METERED_SHARE * keep.size:
            lower = lower[keep]
    return float(np.clip(camera.target_grey / max(float(lower.mean()), 1e-3), *camera.gain_range))


def exposure_error(time: float, camera: CameraRealism, seed: int) -> float:
    """Log gain the exposure controller is off by at `time` (s): linear between seeded knots every ae_knot_s, a
    knot repeating the one before it with chance ae_hold_share. The same for every frame of one seed, whatever
    order the frames are rendered in."""
    if camera.ae_wander <= 0.0:
        return 0.0
    x = time / camera.ae_knot_s
    k = math.floor(x)
    return (1.0 - (x - k)) * _knot(k, camera, seed) + (x - k) * _knot(k + 1, camera, seed)


def _knot(k: int, camera: CameraRealism, seed: int) -> float:
    while True:  # a held knot takes the value of the last one drawn before it
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 64, k + (1 << 20)]))
        hold, value = rng.random(), rng.uniform(-camera.ae_wander, camera.ae_wander)
        if hold >= camera.ae_hold_share:
            return float(value)
        k -= 1


def vignetting(shape: tuple[int, int], K: np.ndarray, camera: CameraRealism) -> np.ndarray:
    """(H,W) float32 relative illumination V(r) = exp(b1 r^2 + b2 r^4), r = |pixel - principal point| / f."""
    h, w = shape
    x = (np.arange(w, dtype=np.float64) - K[0, 2]) / K[0, 0]
    y = (np.arange(h, dtype=np.float64) - K[1, 2]) / K[1, 1]
    r2 = x[None, :] ** 2 + y[:, None] ** 2
    return np.exp(camera.vignetting_b1 * r2 + camera.vignetting_b2 * r2 * r2).astype(np.float32)


# ---------------------------------------------------------------------------------------------- motion


def exposure_motion(depth: np.ndarray, K: np.ndarray, T_start: np.ndarray,
                    T_end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H,W) du, dv (px): where each pixel's surface point (z-depth `depth`, inf: the sky, seen by rotation
    alone) moves in the image while the camera goes from T_start to T_end (4x4 poses of the camera in one world
    frame, x right, y down, z forward). Movers are taken as standing still."""
    h, w = depth.shape
    T = np.linalg.inv(T_end) @ T_start  # start camera frame -> end camera frame
    R, t = T[:3, :3], T[:3, 3]
    x = ((np.arange(w, dtype=np.float64) - K[0, 2]) / K[0, 0])[None, :]
    y = ((np.arange(h, dtype=np.float64) - K[1, 2]) / K[1, 1])[:, None]
    # the ray (x, y, 1) rotated, plus the translation over the depth (0 for the sky)
    inv_z = np.where(np.isfinite(depth), 1.0 / np.maximum(depth.astype(np.float64), 1e-3), 0.0)
    X = R[0, 0] * x + R[0, 1] * y + R[0, 2] + t[0] * inv_z
    Y = R[1, 0] * x + R[1, 1] * y + R[1, 2] + t[1] * inv_z
    Z = np.maximum(R[2, 0] * x + R[2, 1] * y + R[2, 2] + t[2] * inv_z, 1e-3)  # a point the camera passes: cut below
    du = K[0, 0] * (X / Z - x)
    dv = K[1, 1] * (Y / Z - y)
    cut = np.minimum(1.0, MAX_MOTION_PX / np.maximum(np.hypot(du, dv), 1e-9))
    return (du * cut).astype(np.float32), (dv * cut).astype(np.float32)


def motion_blur(image: np.ndarray, du: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """The image integrated over the exposure: pixel p collects what the still image shows along p - s (du, dv),
    s uniform in [0, 1] (the scene point that reaches p at the shutter's close was at p - (du, dv) when it opened)."""
    longest = float(np.sqrt(np.max(du * du + dv * dv))) if du.size else 0.0
    if longest < 1e-3:
        return image
    n = int(min(MAX_MOTION_SAMPLES, max(2, math.ceil(longest * MOTION_SAMPLES_PER_PX))))
    h, w = image.shape
    u0 = np.arange(w, dtype=np.float32)[None, :]
    v0 = np.arange(h, dtype=np.float32)[:, None]
    out = np.zeros((h, w), np.float32)
    for k in range(n):
        s = np.float32((k + 0.5) / n)
        out += cv2.remap(image, u0 - s * du, v0 - s * dv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out / np.float32(n)


# ---------------------------------------------------------------------------------------------- geometry


def rectification_residual(shape: tuple[int, int], K: np.ndarray, camera: CameraRealism,
                           seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(H,W) float32 du, dv (rectified px): the real image at pixel p shows what the pinhole image shows at
    p + (du, dv). A residual lens model (radial k1 r^2 + k2 r^4 and tangential p1, p2, in normalised coordinates,
    seeded and fixed for the twin) scaled to an RMS displacement of camera.rectification_residual_px."""
    h, w = shape
    if camera.rectification_residual_px <= 0.0:
        return np.zeros(shape, np.float32), np.zeros(shape, np.float32)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 65]))
    k1, k2, p1, p2 = rng.standard_normal(4) * np.array([1.0, 0.5, 0.2, 0.2])
    x = ((np.arange(w, dtype=np.float64) - K[0, 2]) / K[0, 0])[None, :]
    y = ((np.arange(h, dtype=np.float64) - K[1, 2]) / K[1, 1])[:, None]
    r2 = x * x + y * y
    radial = k1 * r2 + k2 * r2 * r2
    du = (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)) * K[0, 0]
    dv = (y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y) * K[1, 1]
    s = camera.rectification_residual_px / max(math.sqrt(float(np.mean(du * du + dv * dv))), 1e-12)
    return (du * s).astype(np.float32), (dv * s).astype(np.float32)


def warp(image: np.ndarray, du: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """image sampled at p + (du, dv) (bilinear; the border repeats)."""
    h, w = image.shape
    u = np.arange(w, dtype=np.float32)[None, :] + du
    v = np.arange(h, dtype=np.float32)[:, None] + dv
    return cv2.remap(image, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def rectified_to_raw(u: np.ndarray, v: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rectified pixel coordinates (pinhole K) -> KITTI cam0's raw pixel coordinates (RAW_K, RAW_DISTORTION)."""
    x = (np.asarray(u, np.float64) - K[0, 2]) / K[0, 0]
    y = (np.asarray(v, np.float64) - K[1, 2]) / K[1, 1]
    R = RAW_R_RECT.T  # rectified camera -> raw camera
    z = R[2, 0] * x + R[2, 1] * y + R[2, 2]
    xr = (R[0, 0] * x + R[0, 1] * y + R[0, 2]) / z
    yr = (R[1, 0] * x + R[1, 1] * y + R[1, 2]) / z
    k1, k2, p1, p2, k3 = RAW_DISTORTION
    r2 = xr * xr + yr * yr
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xr * radial + 2.0 * p1 * xr * yr + p2 * (r2 + 2.0 * xr * xr)
    yd = yr * radial + p1 * (r2 + 2.0 * yr * yr) + 2.0 * p2 * xr * yr
    return RAW_K[0, 0] * xd + RAW_K[0, 2], RAW_K[1, 1] * yd + RAW_K[1, 2]


_RAW_MAPS: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def raw_to_rectified_map(K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(512,1392) float32 maps: the rectified pixel coordinates each raw pixel sees (cached per K). OpenCV's
    inverse map, refined by Newton steps on rectified_to_raw (its iteration leaves ~0.1 px at the corners). KITTI's
    rectified images lie inside the raw frame; a wider one would repeat the raw frame's border."""
    key = tuple(np.round(np.asarray(K, np.float64).ravel(), 9))
    if key not in _RAW_MAPS:
        w, h = RAW_SIZE
        m1, m2 = cv2.initInverseRectificationMap(RAW_K, RAW_DISTORTION, RAW_R_RECT, np.asarray(K, np.float64),
                                                 (w, h), cv2.CV_32FC1)
        u, v = m1.astype(np.float64), m2.astype(np.float64)
        qu = np.arange(w, dtype=np.float64)[None, :]
        qv = np.arange(h, dtype=np.float64)[:, None]
        for _ in range(3):
            fu, fv = rectified_to_raw(u, v, K)
            au, av = rectified_to_raw(u + 0.5, v, K)
            bu, bv = rectified_to_raw(u, v + 0.5, K)
            j11, j21, j12, j22 = (au - fu) / 0.5, (av - fv) / 0.5, (bu - fu) / 0.5, (bv - fv) / 0.5
            ru, rv = qu - fu, qv - fv
            det = j11 * j22 - j12 * j21
            u = u + (j22 * ru - j12 * rv) / det
            v = v + (j11 * rv - j21 * ru) / det
        _RAW_MAPS[key] = (u.astype(np.float32), v.astype(np.float32))
    return _RAW_MAPS[key]


# ---------------------------------------------------------------------------------------------- noise


def sensor_noise(signal_grey: np.ndarray, camera: CameraRealism, rng: np.random.Generator) -> np.ndarray:
    """(H,W) float32 shot and read noise (grey) for a signal (grey), white over the grid's pixels."""
    var = np.float32(camera.read_noise_grey ** 2) + np.float32(camera.shot_noise_grey) * np.maximum(signal_grey, 0.0)
    return rng.standard_normal(signal_grey.shape, dtype=np.float32) * np.sqrt(var)


def _noise(signal: np.ndarray, camera: CameraRealism, frame: Exposure, rng: np.random.Generator | None) -> np.ndarray:
    if camera.noise_model == "bank":
        if frame.noise_bank is None or frame.bank_start + signal.size > len(frame.noise_bank):
            raise SynthError("camera.noise_model 'bank': the renderer's noise bank is missing or too short for "
                             f"a {signal.shape[1]}x{signal.shape[0]} image")
        return frame.noise_bank[frame.bank_start:frame.bank_start + signal.size].reshape(signal.shape)
    if rng is None:
        raise SynthError("camera.noise_model 'sensor': no random generator was given for the noise")
    return sensor_noise(signal, camera, rng)


# ---------------------------------------------------------------------------------------------- the pipeline


@dataclass(frozen=True)
class Exposure:
    """What develop() needs of the frame beyond its radiance. K: (3,3) intrinsics of the rectified image; time: the
    frame's time (s); seed: the twin's (residual warp and exposure error are fixed per twin); depth: (H,W) z-depth
    (m, inf: sky); T_start, T_end: the camera's pose when the shutter opens and closes (motion blur); static: (H,W)
    bool, the pixels that see no mover (metering); noise_bank, bank_start: the renderer's white noise bank and the
    frame's start in it (noise_model "bank")."""

    K: np.ndarray
    time: float
    seed: int
    depth: np.ndarray | None = None
    T_start: np.ndarray | None = None
    T_end: np.ndarray | None = None
    static: np.ndarray | None = None
    noise_bank: np.ndarray | None = None
    bank_start: int = 0


def develop(radiance: np.ndarray, camera: CameraRealism, frame: Exposure,
            rng: np.random.Generator | None = None) -> tuple[np.ndarray, float]:
    """(H,W) float32 linear radiance on the rectified grid -> (H,W) uint8 image and the gain auto exposure set.

    rng: the camera's own draws (noise_model "sensor"); unused with the bank. Each effect whose setting is zero is
    skipped, so IDEAL_CAMERA's image is the old renderer's to the byte."""
    img: np.ndarray = np.ascontiguousarray(radiance, dtype=np.float32)
    if camera.shutter_s > 0.0:
        if frame.depth is None or frame.T_start is None or frame.T_end is None:
            raise SynthError("camera.shutter_s > 0: motion blur needs the frame's depth and the camera's poses "
                             "when the shutter opens and closes")
        img = motion_blur(img, *exposure_motion(frame.depth, frame.K, frame.T_start, frame.T_end))
    if camera.vignetting_b1 != 0.0 or camera.vignetting_b2 != 0.0:
        img = img * vignetting(img.shape, frame.K, camera)
    gain = metered_gain(img, int(frame.K[1, 2]), camera, frame.static)
    gain *= math.exp(exposure_error(frame.time, camera, frame.seed))
    if camera.raw_sensor:
        return _develop_raw(img, gain, camera, frame, rng), gain
    if camera.rectification_residual_px > 0.0:
        img = warp(img, *rectification_residual(img.shape, frame.K, camera, frame.seed))
    signal: np.ndarray
    if camera.response == "linear":
        if camera.optics_blur_px > 0.0:
            img = cv2.GaussianBlur(img, (0, 0), camera.optics_blur_px)
        signal = img * np.float32(gain * 255.0)  # grey levels, full scale at 255 (clipped by the ADC below)
    else:  # the old camera: the tone curve on the exposed radiance, then the blur
        signal = shoulder(img * np.float32(gain)) * np.float32(255.0)
        if camera.optics_blur_px > 0.0:
            signal = cv2.GaussianBlur(signal, (0, 0), camera.optics_blur_px)
    signal += _noise(signal, camera, frame, rng)
    return np.clip(np.rint(signal), 0, 255).astype(np.uint8), gain


def _develop_raw(img: np.ndarray, gain: float, camera: CameraRealism, frame: Exposure,
                 rng: np.random.Generator | None) -> np.ndarray:
    """The exposed image taken to the raw sensor (optics, response, noise, 8-bit ADC) and rectified back."""
    h, w = img.shape
    mu, mv = raw_to_rectified_map(frame.K)
    raw: np.ndarray = cv2.remap(img, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if camera.optics_blur_px > 0.0:
        raw = cv2.GaussianBlur(raw, (0, 0), camera.optics_blur_px)
    raw = raw * np.float32(gain * 255.0)
    raw += _noise(raw, camera, frame, rng)
    raw = np.clip(np.rint(raw), 0, 255)  # the camera's 8-bit image
    du, dv = rectification_residual((h, w), frame.K, camera, frame.seed)
    u = np.arange(w, dtype=np.float64)[None, :] + du
    v = np.arange(h, dtype=np.float64)[:, None] + dv
    ru, rv = rectified_to_raw(u, v, frame.K)  # KITTI's rectification, with the residual its calibration leaves
    rect = cv2.remap(raw, ru.astype(np.float32), rv.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    return np.clip(np.rint(rect), 0, 255).astype(np.uint8)
