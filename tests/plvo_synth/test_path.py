"""Synthetic town trajectories and settings, without rendering: speed, height, turns, stops, loops, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from plvo.errors import SynthError
from plvo_synth import SynthSettings, exposure_gains, generate_sequence, plan_trajectory
from plvo_synth import path as paths
from plvo_synth.sensors import CAMERA_HEIGHT_M


def _yaw(T_world_cam: np.ndarray) -> np.ndarray:
    """Heading of each camera in the world's x-z plane (rad)."""
    z = T_world_cam[:, :3, 2]
    return np.unwrap(np.arctan2(z[:, 0], z[:, 2]))


@pytest.mark.parametrize("speed", [5.0, 10.0, 15.0])
def test_constant_speed_level_camera_and_right_angle_turns(speed):
    traj = plan_trajectory(SynthSettings(n_frames=900, seed=4, speed_mps=speed))
    T = traj.T_world_cam
    steps = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, speed * 0.1, rtol=3e-3)  # chords on 8 m arcs are slightly short
    np.testing.assert_allclose(T[:, 1, 3], 0.0, atol=1e-9)  # same height as frame 0 throughout
    T_town_cam = traj.T_town_world @ T
    np.testing.assert_allclose(T_town_cam[:, 2, 3], CAMERA_HEIGHT_M, atol=1e-9)
    yaw = _yaw(T)
    assert np.abs(np.diff(yaw)).sum() >= np.pi / 2 - 1e-6, "a 450 m+ route turns at some crossing"
    # Straight legs run along the street grid; turns are arcs of TURN_RADIUS_M driven at the same speed.
    on_grid = np.abs(yaw / (np.pi / 2) - np.rint(yaw / (np.pi / 2))) < 1e-9
    assert on_grid.mean() > 0.7
    assert np.abs(np.diff(yaw)).max() == pytest.approx(speed * 0.1 / paths.TURN_RADIUS_M, rel=1e-6)


def test_staircase_route_never_revisits():
    T = plan_trajectory(SynthSettings(n_frames=1500, seed=2, speed_mps=12.0)).T_world_cam
    p = T[::5, [0, 2], 3]
    d = np.linalg.norm(p[:, None] - p[None], axis=2)
    gap = np.abs(np.arange(len(p))[:, None] - np.arange(len(p))[None])
    assert d[gap > 10].min() > 20.0


def test_loop_revisits_the_first_street():
    settings = SynthSettings(n_frames=320, seed=0, speed_mps=10.0, loop=True)
    traj = plan_trajectory(settings)
    T = traj.T_world_cam
    assert 0 < traj.lap_m <= traj.s[-1] - paths.LOOP_MIN_OVERLAP_M
    lap_frames = int(round(traj.lap_m / 1.0))  # 1 m a frame
    for i in (0, 5, 10):  # on the first street, before the first turn
        j = i + lap_frames
        assert np.linalg.norm(T[j, :3, 3] - T[i, :3, 3]) < 0.51  # the same place one lap later
        np.testing.assert_allclose(T[j, :3, :3], T[i, :3, :3], atol=1e-9)  # with the same heading
    yaw = _yaw(T)
    assert abs(yaw[lap_frames] - yaw[0]) == pytest.approx(2 * np.pi, abs=1e-9)  # four quarter turns


def test_stops_hold_still_for_whole_frames():
    traj = plan_trajectory(SynthSettings(n_frames=150, seed=0, speed_mps=10.0, stops=True))
    steps = np.linalg.norm(np.diff(traj.T_world_cam[:, :3, 3], axis=0), axis=1)
    still = np.flatnonzero(steps == 0.0)
    assert len(still) == paths.STOP_HOLD_FRAMES - 1  # 20 frames at one pose: 19 zero steps
    assert np.all(np.diff(still) == 1)
    np.testing.assert_array_equal(traj.T_world_cam[still[0]], traj.T_world_cam[still[-1] + 1])
    assert steps[0] == pytest.approx(1.0) and steps[-1] == pytest.approx(1.0, abs=0.05)
    assert steps.max() <= 1.0 + 1e-9
    # Braking at 4 m/s^2: the step shrinks by 0.04 m a frame before the stop.
    brake = np.diff(steps[still[0] - 10:still[0] - 1])
    np.testing.assert_allclose(brake, -0.04, atol=1e-9)


def test_seed_decides_the_trajectory():
    a = plan_trajectory(SynthSettings(n_frames=800, seed=1)).T_world_cam
    b = plan_trajectory(SynthSettings(n_frames=800, seed=1)).T_world_cam
    c = plan_trajectory(SynthSettings(n_frames=800, seed=2)).T_world_cam
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_exposure_gains_swing_by_the_amplitude():
    g = exposure_gains(SynthSettings(n_frames=200, seed=3, exposure_change=0.2))
    assert g.min() == pytest.approx(0.8, abs=0.01) and g.max() == pytest.approx(1.2, abs=0.01)
    assert np.abs(np.diff(g)).max() < 0.04  # a smooth swing, not flicker
    np.testing.assert_array_equal(exposure_gains(SynthSettings(n_frames=5)), 1.0)


@pytest.mark.parametrize(
    ("kwargs", "named"),
    [
        ({"n_frames": 1}, "n_frames"),
        ({"n_frames": 2.5}, "n_frames"),
        ({"n_frames": True}, "n_frames"),
        ({"seed": -1}, "seed"),
        ({"speed_mps": 0.0}, "speed_mps"),
        ({"speed_mps": 45.0}, "speed_mps"),
        ({"speed_mps": float("nan")}, "speed_mps"),
        ({"n_frames": 40_000, "speed_mps": 30.0}, "n_frames x speed_mps"),
        ({"exposure_change": 0.8}, "exposure_change"),
        ({"exposure_change": -0.1}, "exposure_change"),
        ({"n_frames": 50, "loop": True}, "loop"),
        ({"n_frames": 40, "stops": True}, "stops"),
        ({"sequence": "7"}, "sequence"),
        ({"sequence": "ab"}, "sequence"),
    ],
)
def test_impossible_settings_raise_synth_error_naming_the_setting(tmp_path, kwargs, named):
    kwargs = {"n_frames": 5, **kwargs}
    with pytest.raises(SynthError, match=named):
        generate_sequence(tmp_path / "out", **kwargs)
    assert not (tmp_path / "out").exists()  # nothing written


def test_out_root_that_is_a_file_is_refused(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(SynthError, match="out_root"):
        generate_sequence(tmp_path / "f", n_frames=3)
