"""The twins' motion compensation as KITTI's: the motion it removes spans whole GPS/INS record periods, measured back
at the sweep's seam as on KITTI's scans (plvo.lidar.seam, scripts/kitti_compensation_stats.py); rings of one turn
each, as KITTI's files hold them; the exact compensation, and so IDEAL, as before.

In-process on one twin world (04, frames 0:4, no traffic, no lidar effects but the compensation's)."""

from __future__ import annotations

import numpy as np
import pytest

from plvo.errors import SynthError
from plvo.lidar.seam import ring_turns, seam_ground_split, storage_rings
from plvo_synth import sensors
from plvo_synth.twin.follow import PoseInterpolator
from plvo_synth.twin.generate import TwinSettings, build_twin
from plvo_synth.twin.lidars import SWEEP_S, LidarEffects, lidar_model
from plvo_synth.twin.realism import IDEAL, IDEAL_LIDAR, LidarRealism, Realism
from plvo_synth.twin.scenery_realism import IDEAL_SCENERY

SEQ = "04"
KITTI_RECORDS = LidarRealism().compensation_records_a_sweep
# every effect off but the compensation's record clock (the ring order of a scan with effects is kept)
QUIET = LidarRealism(range_noise_m=0.0, beam_elevation_sigma_deg=0.0, beam_range_sigma_m=0.0,
                     elevation_offset_deg=0.0, dropout_floor=0.0, dropout_dark=0.0, dropout_glass=0.0,
                     foliage_scatter=0.0, ego_occlusion=False)
EXACT = LidarRealism(**{**QUIET.__dict__, "compensation_records_a_sweep": 0.0})


@pytest.fixture(scope="module")
def world(kitti_root):
    settings = TwinSettings(str(kitti_root / "poses" / f"{SEQ}.txt"), "0:4", traffic=0,
                            realism=Realism(scenery=IDEAL_SCENERY))
    return build_twin(settings, SEQ)


def _scan(world, lidar: LidarRealism, t: float, compensate: bool = True) -> np.ndarray:
    r = world.renderer
    r.lidar_effects = LidarEffects(r.lidar, lidar, world.seed)
    poses = PoseInterpolator(world.path.T_town_cam)
    scan, _ = r.scan_twin(poses, t, world.T_cam_velo, np.random.default_rng(5), np.random.default_rng(6), compensate)
    return scan


def _sweep_motion_x(world, t: float) -> float:
    """The lidar's motion over the sweep facing forward at t, along its x at t (m)."""
    T0, T, T1 = PoseInterpolator(world.path.T_town_cam)(t + np.array([-0.5, 0.0, 0.5]) * SWEEP_S) @ world.T_cam_velo
    return float((np.linalg.inv(T)[:3, :3] @ (T1[:3, 3] - T0[:3, 3]))[0])


def test_the_gain_follows_the_record_clock():
    fx = LidarEffects(lidar_model("hdl64"), QUIET, seed=3)
    gains = np.array([fx.compensation_gain(t) for t in np.arange(2000) * sensors.FRAME_DT])
    values = {10 / KITTI_RECORDS, 11 / KITTI_RECORDS}
    assert all(min(abs(g - v) for v in values) < 1e-12 for g in gains)
    # a record period a sweep of 10.41: the 11th record falls inside 41 % of the sweeps, the motion removed
    # averages the sweep's
    assert np.mean(gains > 1) == pytest.approx(0.41, abs=0.01)
    assert np.mean(gains) == pytest.approx(1.0, abs=0.002)
    assert LidarEffects(lidar_model("hdl64"), EXACT, seed=3).compensation_gain(0.7) == 1.0


def test_the_residual_is_measured_back_at_the_seam(world):
    """The seam of a scan compensated over whole records against the same sweep compensated exactly: the ground's
    split differs by the share of the sweep's motion that the records miss or add (KITTI 04: -6 / +7 cm)."""
    fx = LidarEffects(world.renderer.lidar, QUIET, world.seed)
    times = np.arange(1, 30) * 0.1 * sensors.FRAME_DT  # the sweeps of frames 0-3 at 29 instants
    picked = {}
    for t in times:
        picked.setdefault(fx.compensation_gain(t) > 1, t)
    assert set(picked) == {False, True}
    for t in picked.values():
        gain = fx.compensation_gain(t)
        real = seam_ground_split(_scan(world, QUIET, t))
        exact = seam_ground_split(_scan(world, EXACT, t))
        assert len(real) == len(exact) >= 10
        motion = _sweep_motion_x(world, t)
        assert motion > 1.2  # 04's 13 m/s
        expected = (gain - 1.0) * motion
        assert abs(expected) > 0.05
        assert np.median(real - exact) == pytest.approx(expected, abs=0.005)


def test_the_seam_tells_compensated_scans_from_raw_sweeps(world):
    t = 1.5 * sensors.FRAME_DT
    motion = _sweep_motion_x(world, t)
    compensated = np.median(seam_ground_split(_scan(world, EXACT, t)))
    raw = np.median(seam_ground_split(_scan(world, EXACT, t, compensate=False)))
    # the twin's ground is less even than a real road's (its heights follow the truth's), so 0.3 m, not 1 cm
    assert compensated == pytest.approx(motion, abs=0.3)
    assert raw == pytest.approx(0.0, abs=0.3)


def test_rings_hold_one_turn_as_kittis_do(world, kitti_root):
    """No overlap: each of the 64 rings one turn in storage order, its returns evenly round it, in the twin's scans
    as in KITTI's (which hold 2172 returns a ring at most: 8 % more than a turn at their median step of 0.18 deg,
    but every few firings a half step, not a second turn); both kinds of overlap are found where put in."""
    scan = _scan(world, QUIET, 1.0 * sensors.FRAME_DT)
    turns = ring_turns(scan)
    real = ring_turns(np.fromfile(kitti_root / "sequences" / "04" / "velodyne" / "000010.bin",
                                  np.float32).reshape(-1, 4))
    for t in (turns, real):
        full = t.returns > 0.9 * t.returns.max()
        assert len(t.returns) == 64 and 359.5 < t.span_deg.max() < 360.0
        assert full.sum() >= 5 and t.densest[full].max() < 1.4
    assert real.returns.max() * np.median(real.step_deg) > 385.0  # the "8 % more" read off the median step
    ring = storage_rings(scan)
    k = np.flatnonzero(ring == 20)
    head = k[: int(0.08 * len(k))]
    # continued past its turn: the ring's first 8 % stored again after its last return (storage_rings takes it into
    # the next ring's run, which then holds those azimuths twice)
    continued = ring_turns(np.concatenate([scan[: k[-1] + 1], scan[head], scan[k[-1] + 1:]]))
    assert len(continued.returns) == 64 and continued.densest[21] > 1.8
    # interleaved: the same returns half a step on, each after its twin
    again = scan[head].copy()
    turn = np.radians(0.5 * np.median(turns.step_deg))
    c, s_ = np.cos(turn), np.sin(turn)
    again[:, :2] = again[:, :2] @ np.array([[c, s_], [-s_, c]])  # clockwise, as the sweep runs
    after_its_twin = np.argsort(np.concatenate([np.arange(len(k)), np.arange(len(head)) + 0.5]), kind="stable")
    mixed = np.concatenate([scan[: k[0]], np.concatenate([scan[k], again])[after_its_twin], scan[k[-1] + 1:]])
    interleaved = ring_turns(mixed)
    assert len(interleaved.returns) == 64 and interleaved.densest[20] > 1.8


def test_exact_compensation_is_as_before(world):
    """Without the record clock (IDEAL's setting) a compensated scan is the old one bit for bit: each return of the
    raw sweep moved with the exact motion from its column's time to the frame's."""
    t = 2.0 * sensors.FRAME_DT
    raw = _scan(world, EXACT, t, compensate=False)
    new = _scan(world, EXACT, t)
    model, poses = world.renderer.lidar, PoseInterpolator(world.path.T_town_cam)
    az = np.arctan2(raw[:, 1].astype(np.float64), raw[:, 0].astype(np.float64))
    col = np.rint((np.pi - az) / (2 * np.pi) * model.azimuth_steps - 0.5).astype(int) % model.azimuth_steps
    T_cols = poses(t + model.ray_times()[:: len(model.elevations_deg)]) @ world.T_cam_velo
    rel = np.linalg.inv(poses(np.array([t]))[0] @ world.T_cam_velo)[None] @ T_cols
    p = raw[:, :3].astype(np.float64)
    old = np.einsum("kij,kj->ki", rel[col, :3, :3], p) + rel[col, :3, 3]
    assert np.array_equal(new[:, :3], old.astype(np.float32)) and np.array_equal(new[:, 3], raw[:, 3])
    assert IDEAL.lidar == IDEAL_LIDAR and IDEAL_LIDAR.compensation_records_a_sweep == 0.0 and IDEAL.is_ideal


@pytest.mark.parametrize("records", [-1.0, 0.5, 2000.0])
def test_bad_record_clock_is_one_line(records):
    with pytest.raises(SynthError, match="compensation_records_a_sweep"):
        Realism(lidar=LidarRealism(compensation_records_a_sweep=records)).check()
