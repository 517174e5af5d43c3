"""The twins' camera (plvo_synth.twin.camera_effects): each imperfection measured back on developed images
against its setting — noise level, motion blur length at a known speed and depth, vignetting, exposure steps, the
rectification's residual warp and its resampling — and IDEAL_CAMERA byte for byte the old renderer's camera."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from plvo.errors import SynthError
from plvo_synth import sensors
from plvo_synth.twin import camera_effects as ce
from plvo_synth.twin.camera_effects import IDEAL_CAMERA, CameraRealism, Exposure, develop
from plvo_synth.twin.follow import PoseInterpolator

# every effect off, linear response, gain fixed at 1 (radiance 1 -> 255 grey): each test turns on what it measures
QUIET = dataclasses.replace(IDEAL_CAMERA, response="linear", noise_model="sensor", read_noise_grey=0.0,
                            optics_blur_px=0.0, gain_range=(1.0, 1.0))
K_SMALL = np.array([[200.0, 0.0, 99.5], [0.0, 200.0, 59.5], [0.0, 0.0, 1.0]])  # 200x120 images
K_KITTI = sensors.K_CAM0  # 1241x376, for the raw sensor's grid
KITTI_HW = (sensors.IMAGE_HEIGHT, sensors.IMAGE_WIDTH)


def _rng(k: int = 0) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([2024, k]))


def _texture(shape: tuple[int, int], sigma_px: float = 2.0, seed: int = 0) -> np.ndarray:
    """Smooth random radiance in about [0.1, 0.7]."""
    t = cv2.GaussianBlur(_rng(seed).standard_normal(shape).astype(np.float32), (0, 0), sigma_px)
    return (0.4 + 0.3 * t / (3.0 * t.std())).clip(0.05, 0.95).astype(np.float32)


def _old_camera(radiance: np.ndarray, K: np.ndarray, bank: np.ndarray, start: int) -> tuple[np.ndarray, float]:
    """The twins' camera as it was before camera_effects (twin.render at 5dba58f), written out."""
    lower = radiance[int(K[1, 2]):]
    gain = float(np.clip(0.40 / max(float(lower.mean()), 1e-3), 0.5, 2.5))
    x = radiance * np.float32(gain)
    over = np.maximum(x - 0.6, 0.0)
    toned = np.minimum(x, 0.6) + 0.4 * (1.0 - np.exp(-over / 0.4))
    blurred = cv2.GaussianBlur(toned * np.float32(255.0), (0, 0), 0.6)
    blurred += bank[start:start + blurred.size].reshape(blurred.shape)
    return np.clip(np.rint(blurred), 0, 255).astype(np.uint8), gain


def test_ideal_camera_is_the_old_camera_byte_for_byte():
    h, w = 120, 200
    radiance = _texture((h, w))
    radiance[:30] = 0.9  # a bright sky on the shoulder
    bank = _rng(1).standard_normal(h * w + 1000, dtype=np.float32) * np.float32(1.5)
    for start, scale in ((0, 1.0), (517, 0.3), (999, 2.0)):  # gains inside and at both ends of the range
        rad = (radiance * np.float32(scale)).astype(np.float32)
        old, old_gain = _old_camera(rad, K_SMALL, bank, start)
        new, gain = develop(rad, IDEAL_CAMERA, Exposure(K_SMALL, 0.3, 7, noise_bank=bank, bank_start=start))
        assert gain == old_gain
        assert new.dtype == np.uint8 and np.array_equal(new, old)


def test_noise_level_measured_back_against_its_setting():
    """Flat patches of three brightnesses: the measured spread is sqrt(read^2 + shot * signal + 1/12) (the last:
    the 8-bit quantisation), within 4 % (4000 pixels a patch: ~1 % standard error)."""
    cam = dataclasses.replace(QUIET, read_noise_grey=1.2, shot_noise_grey=0.1)
    levels = (0.1, 0.3, 0.6)
    radiance = np.repeat(np.array(levels, np.float32), 100)[None, :].repeat(60, axis=0)  # 60x300, three bands
    K = np.array([[200.0, 0.0, 150.0], [0.0, 200.0, 30.0], [0.0, 0.0, 1.0]])
    img, gain = develop(radiance, cam, Exposure(K, 0.0, 0), _rng(2))
    assert gain == 1.0
    for k, level in enumerate(levels):
        patch = img[5:-5, 100 * k + 5:100 * k + 95].astype(np.float64)
        signal = 255.0 * level
        expected = math.sqrt(1.2 ** 2 + 0.1 * signal + 1.0 / 12.0)
        assert abs(patch.mean() - signal) < 0.2
        assert patch.std() == pytest.approx(expected, rel=0.04), (level, patch.std(), expected)


def _bilinear_weights(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear sampling at x: the lower sample's index and the two weights."""
    i = np.floor(x)
    return i, 1.0 - (x - i), x - i


def _overlap(xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Sum over samples of the product of the 1-D bilinear weights of sampling at xa and at xb."""
    ia, a0, a1 = _bilinear_weights(xa)
    ib, b0, b1 = _bilinear_weights(xb)
    out = np.zeros_like(xa)
    for da, wa in ((0, a0), (1, a1)):
        for db, wb in ((0, b0), (1, b1)):
            out += np.where(ia + da == ib + db, wa * wb, 0.0)
    return out


def test_raw_sensor_noise_is_resampled_as_the_rectification_resamples_it():
    """Raw mode: white raw noise (read 2 grey + the raw 8-bit step) interpolated bilinearly by the rectification
    has, per rectified pixel, variance sum(w^2) * raw variance + 1/12 and covariance with its right neighbour
    sum(w w') * raw variance (w, w': the bilinear weights, from the map): measured within 6 % and 0.02; on the
    rectified grid alone the noise stays white."""
    h, w = KITTI_HW
    cam = dataclasses.replace(QUIET, raw_sensor=True, read_noise_grey=2.0)
    radiance = np.full((h, w), 0.3, np.float32)
    img, _ = develop(radiance, cam, Exposure(K_KITTI, 0.0, 0), _rng(3))
    rows, cols = slice(130, 250), slice(420, 820)  # the centre, where a rectified pixel spans 1.36 raw pixels
    v, u = np.mgrid[rows, cols].astype(np.float64)
    ru, rv = ce.rectified_to_raw(u, v, K_KITTI)
    nu, nv = ce.rectified_to_raw(u + 1.0, v, K_KITTI)
    raw_var = 4.0 + 1.0 / 12.0
    expected_var = float((_overlap(ru, ru) * _overlap(rv, rv)).mean()) * raw_var + 1.0 / 12.0
    expected_cov = float((_overlap(ru, nu) * _overlap(rv, nv)).mean()) * raw_var
    d = img[rows, cols].astype(np.float64)
    d -= d.mean()
    assert d.var() == pytest.approx(expected_var, rel=0.06)
    corr, expected_corr = float((d[:, 1:] * d[:, :-1]).mean() / d.var()), expected_cov / expected_var
    assert corr == pytest.approx(expected_corr, abs=0.02) and expected_corr > 0.05, (corr, expected_corr)
    flat, _ = develop(radiance, dataclasses.replace(cam, raw_sensor=False), Exposure(K_KITTI, 0.0, 0), _rng(3))
    e = flat[rows, cols].astype(np.float64)
    e -= e.mean()
    assert abs(float((e[:, 1:] * e[:, :-1]).mean() / e.var())) < 0.02


def _blur_length(profile: np.ndarray) -> float:
    """Length (px) of the box that blurred a step into `profile`: the step's derivative is the box convolved with
    the bilinear sampling's tent (variance 1/6), so L = sqrt(12 (var - 1/6))."""
    d = np.abs(np.diff(profile.astype(np.float64)))
    x = np.arange(len(d), dtype=np.float64)
    mean = (d * x).sum() / d.sum()
    var = (d * (x - mean) ** 2).sum() / d.sum()
    return math.sqrt(max(12.0 * (var - 1.0 / 6.0), 0.0))


def _step_scene(h: int, w: int, column: int) -> np.ndarray:
    radiance = np.full((h, w), 0.2, np.float32)
    radiance[:, column:] = 0.6
    return radiance


def _path(velocity_cam: np.ndarray) -> PoseInterpolator:
    """Camera poses at 0 and 0.1 s (a world frame = the first camera's: x right, y down, z forward)."""
    T = np.tile(np.eye(4), (2, 1, 1))
    T[1, :3, 3] = velocity_cam * sensors.FRAME_DT
    return PoseInterpolator(T)


@pytest.mark.parametrize("speed, depth, shutter", [(10.0, 3.5, 3e-3), (14.0, 4.0, 2e-3)])
def test_motion_blur_length_sideways_at_known_speed_and_depth(speed, depth, shutter):
    """Driving sideways past a wall at depth Z: every edge is smeared over f v tau / Z pixels."""
    h, w = 40, 200
    cam = dataclasses.replace(QUIET, shutter_s=shutter)
    poses = _path(np.array([speed, 0.0, 0.0]))
    t = 0.02
    frame = Exposure(K_SMALL, t, 0, np.full((h, w), depth, np.float32), poses(np.array([t]))[0],
                     poses(np.array([t + shutter]))[0])
    img, _ = develop(_step_scene(h, w, 100), cam, frame, _rng(4))
    expected = K_SMALL[0, 0] * speed * shutter / depth
    measured = _blur_length(img[10:30].mean(axis=0)[60:140])
    assert measured == pytest.approx(expected, abs=0.25), (measured, expected)


def test_motion_blur_driving_forward_grows_with_the_distance_from_the_centre():
    """Driving forward at 14 m/s for 2 ms towards a wall 4 m ahead: a point at x (normalised) moves by
    f x d / (Z - d) pixels (d = 2.8 cm), zero at the principal point; measured on edges at two offsets."""
    h, w = 40, 200
    speed, depth, shutter = 14.0, 4.0, 2e-3
    K = np.array([[100.0, 0.0, 20.0], [0.0, 100.0, 19.5], [0.0, 0.0, 1.0]])
    cam = dataclasses.replace(QUIET, shutter_s=shutter)
    poses = _path(np.array([0.0, 0.0, speed]))
    frame = Exposure(K, 0.0, 0, np.full((h, w), depth, np.float32), poses(np.array([0.0]))[0],
                     poses(np.array([shutter]))[0])
    d = speed * shutter
    for column in (80, 170):
        img, _ = develop(_step_scene(h, w, column), cam, frame, _rng(5))
        x = (column - 0.5 - K[0, 2]) / K[0, 0]
        expected = K[0, 0] * x * d / (depth - d)
        measured = _blur_length(img[17:23].mean(axis=0)[column - 15:column + 15])
        assert measured == pytest.approx(expected, abs=0.25), (column, measured, expected)
    du, dv = ce.exposure_motion(np.full((h, w), depth, np.float32), K, frame.T_start, frame.T_end)
    assert abs(float(du[19, 20])) < 1e-3 and np.abs(dv[19]).max() < 0.03  # the focus of expansion stands still


def test_motion_blur_needs_the_camera_path():
    cam = dataclasses.replace(QUIET, shutter_s=2e-3)
    with pytest.raises(SynthError, match="shutter_s"):
        develop(np.full((20, 30), 0.3, np.float32), cam, Exposure(K_SMALL, 0.0, 0), _rng())


def test_vignetting_measured_back():
    """A uniform scene: the mean grey at distance r from the principal point over the centre's is
    exp(b1 r^2 + b2 r^4), within 0.5 %."""
    h, w = 200, 400
    K = np.array([[220.0, 0.0, 199.5], [0.0, 220.0, 99.5], [0.0, 0.0, 1.0]])
    cam = dataclasses.replace(QUIET, vignetting_b1=-0.24, vignetting_b2=0.144, read_noise_grey=1.0)
    img, _ = develop(np.full((h, w), 0.6, np.float32), cam, Exposure(K, 0.0, 0), _rng(6))
    v, u = np.mgrid[0:h, 0:w]
    r = np.hypot(u - K[0, 2], v - K[1, 2]) / K[0, 0]
    centre = img[r < 0.08].mean()
    for radius in (0.3, 0.5, 0.7, 0.85):
        ring = img[np.abs(r - radius) < 0.02].mean()
        assert ring / centre == pytest.approx(math.exp(-0.24 * radius ** 2 + 0.144 * radius ** 4), rel=0.005)


def test_exposure_steps_measured_back_on_developed_frames():
    """A still scene over 12 s at 10 Hz: each frame's brightness over the one before is exp(e(t1) - e(t0)) of the
    seeded controller error (within 0.3 %); steps stay within the knots' slope, some are holds, all within
    +-ae_wander, and the error does not depend on the order frames are developed in."""
    cam = dataclasses.replace(QUIET, gain_range=(0.5, 2.5), target_grey=0.35, ae_wander=0.1, ae_knot_s=1.0,
                              ae_hold_share=0.3)
    radiance = _texture((30, 50), 4.0)
    K = np.array([[50.0, 0.0, 24.5], [0.0, 50.0, 14.5], [0.0, 0.0, 1.0]])
    times = np.arange(120) * sensors.FRAME_DT
    means, gains = [], []
    for t in times:
        img, gain = develop(radiance, cam, Exposure(K, float(t), 11), _rng(7))
        means.append(img.astype(np.float64).mean())
        gains.append(gain)
    e = np.array([ce.exposure_error(float(t), cam, 11) for t in times])
    assert np.abs(e).max() <= 0.1 + 1e-12
    np.testing.assert_allclose(np.diff(np.log(means)), np.diff(e), atol=0.003)
    steps = np.abs(np.diff(e))
    assert steps.max() <= 2 * 0.1 * sensors.FRAME_DT / cam.ae_knot_s + 1e-12
    assert (steps < 1e-12).any() and (steps > 0.005).any()  # holds and ramps
    backwards = [ce.exposure_error(float(t), cam, 11) for t in times[::-1]][::-1]
    assert np.array_equal(e, backwards)
    assert np.ptp(np.log(gains)) == pytest.approx(np.ptp(e), abs=1e-9)  # a still scene: only the error moves


def test_auto_exposure_meters_the_static_scene():
    """A dark car filling a third of the metered area: the realistic controller keeps its gain (it meters the
    static pixels), the ideal one brightens the whole frame."""
    h, w = 120, 200
    radiance = _texture((h, w), 3.0)
    static = np.ones((h, w), bool)
    with_car = radiance.copy()
    with_car[70:, 50:150] = 0.03
    static[70:, 50:150] = False
    cam = dataclasses.replace(QUIET, gain_range=(0.5, 2.5), target_grey=0.35, ae_ignore_movers=True)
    _, g0 = develop(radiance, cam, Exposure(K_SMALL, 0.0, 0, static=np.ones((h, w), bool)), _rng())
    _, g1 = develop(with_car, cam, Exposure(K_SMALL, 0.0, 0, static=static), _rng())
    ideal = dataclasses.replace(cam, ae_ignore_movers=False)
    _, g2 = develop(with_car, ideal, Exposure(K_SMALL, 0.0, 0, static=static), _rng())
    base = 0.35 / float(radiance[int(K_SMALL[1, 2]):].mean())
    assert g0 == pytest.approx(base, rel=1e-6)
    assert g1 == pytest.approx(base, rel=0.02)
    assert g2 > 1.2 * base


def _translation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(tx, ty) with b(x + t) = a(x): ECC image alignment, translation only (sub-0.02 px on these patches)."""
    warp = np.eye(2, 3, dtype=np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6)
    _, warp = cv2.findTransformECC(a.astype(np.float32), b.astype(np.float32), warp, cv2.MOTION_TRANSLATION,
                                   criteria, None, 1)
    return warp[:, 2].astype(np.float64)


def test_rectification_residual_displacement_measured_back():
    """Raw mode, the same scene rectified with and without the residual: the content of each 64 px patch moves by
    -(du, dv) of the residual field there (the image at p shows the pinhole image's p + d), within 0.05 px (image
    alignment); the field's RMS over the image is the setting; it is the same for every frame of one seed."""
    h, w = KITTI_HW
    radiance = _texture((h, w), 2.5, seed=3)
    exact = dataclasses.replace(QUIET, raw_sensor=True, optics_blur_px=0.5)
    warped = dataclasses.replace(exact, rectification_residual_px=0.6)
    a, _ = develop(radiance, exact, Exposure(K_KITTI, 0.0, 5), _rng())
    b, _ = develop(radiance, warped, Exposure(K_KITTI, 0.3, 5), _rng())
    du, dv = ce.rectification_residual((h, w), K_KITTI, warped, 5)
    assert math.sqrt(float(np.mean(du ** 2 + dv ** 2))) == pytest.approx(0.6, rel=1e-4)
    errors, sizes = [], []
    for cy in (40, 188, 336):
        for cx in (40, 330, 620, 910, 1200):
            sl = (slice(cy - 32, cy + 32), slice(cx - 32, cx + 32))
            d = np.array([du[sl].mean(), dv[sl].mean()])
            errors.append(np.linalg.norm(_translation(a[sl], b[sl]) + d))
            sizes.append(np.linalg.norm(d))
    assert max(sizes) > 0.5  # the corners move by more than the tolerance
    assert max(errors) < 0.05, np.round(errors, 3)


def test_raw_sensor_blurs_the_sides_radially_as_kittis_rectification_does():
    """Vertical edges across the image: rectified from the raw grid, an edge near the left or right border (where a
    rectified pixel spans ~0.73 raw pixels radially, against 1.36 in the middle) is spread over a wider ramp than one
    in the middle; rendered on the rectified grid directly, the two are alike."""
    h, w = KITTI_HW
    radiance = np.full((h, w), 0.2, np.float32)
    for c in range(41, w, 80):
        radiance[:, c:c + 40] = 0.6
    rows = slice(int(K_KITTI[1, 2]) - 10, int(K_KITTI[1, 2]) + 10)

    def widths(cam: CameraRealism) -> tuple[float, float]:
        img, _ = develop(radiance, cam, Exposure(K_KITTI, 0.0, 0), _rng())
        profile = img[rows].mean(axis=0)
        side = _blur_length(profile[41 - 12:41 + 12])
        middle = _blur_length(profile[601 - 12:601 + 12])
        return side, middle

    side, middle = widths(dataclasses.replace(QUIET, raw_sensor=True, optics_blur_px=0.5))
    flat_side, flat_middle = widths(dataclasses.replace(QUIET, optics_blur_px=0.5))
    assert side > 1.4 * middle, (side, middle)
    assert flat_side == pytest.approx(flat_middle, rel=0.1)


def test_settings_out_of_range_name_the_setting():
    CameraRealism().check()
    IDEAL_CAMERA.check()
    assert IDEAL_CAMERA.is_ideal and not CameraRealism().is_ideal
    for bad, name in ((dict(response="gamma"), "camera.response"), (dict(noise_model="white"), "noise_model"),
                      (dict(shutter_s=-1e-3), "camera.shutter_s"), (dict(read_noise_grey="1"), "read_noise_grey"),
                      (dict(gain_range=(2.0, 1.0)), "gain_range"), (dict(raw_sensor=1), "camera.raw_sensor"),
                      (dict(response="shoulder"), "raw_sensor"), (dict(noise_model="bank"), "raw_sensor")):
        with pytest.raises(SynthError, match=name):
            dataclasses.replace(CameraRealism(), **bad).check()
