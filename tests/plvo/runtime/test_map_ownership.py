"""One owner of the map: workers return typed corrections, only the map writes poses, and a run's result does not
depend on the workers' timing."""

from __future__ import annotations

import time

import numpy as np
import pytest

from plvo.geometry import se3
from plvo.tracking.corrections import BACKEND, LOOP, MapCorrection
from plvo.tracking.map import LandmarkMap

K = np.array([[718.856, 0.0, 607.19], [0.0, 718.856, 185.2], [0.0, 0.0, 1.0]])


def _pose(x: float, yaw: float = 0.0) -> np.ndarray:
    return se3.exp(np.array([0.0, 0.0, x, 0.0, yaw, 0.0]))


def _street(n_kf: int = 12, per_kf: int = 20):
    """A map of n_kf keyframes 1 m apart along z, each creating per_kf points in front of it (observed by it)."""
    rng = np.random.default_rng(0)
    m = LandmarkMap()
    for k in range(n_kf):
        kf = m.add_keyframe(3 * k, _pose(float(k)))
        pc = np.c_[rng.uniform(-5, 5, per_kf), rng.uniform(-2, 2, per_kf), rng.uniform(5, 20, per_kf)]
        m.add_points(se3.transform_points(m.keyframe_pose(kf), pc), np.zeros((per_kf, 32), np.uint8),
                     np.ones(per_kf, bool), kf, np.arange(per_kf), np.zeros((per_kf, 2)), pc[:, 2])
    return m


def _in_creator(m: LandmarkMap) -> np.ndarray:
    """Every point in the camera of the keyframe that created it (P,3)."""
    ids, first = m.point_ids_and_first_keyframes()
    P = m.point_positions(ids)
    return np.stack([se3.transform_points(se3.inv(m.keyframe_pose(int(k))), p[None])[0] for p, k in zip(P, first)])


def test_loop_correction_applied_while_the_back_end_optimised_an_older_window():
    """The back end reads the window 6-11, a loop correction (a different correction per keyframe, as a pose graph
    spreads it) is applied meanwhile, then the back end's result: every keyframe must carry both (the loop's
    correction and the back end's refinement of the window's shape), and every landmark must sit where the back
    end put it relative to its keyframe. (The old worker rebased the whole window on its first keyframe, so the
    window took that keyframe's loop correction and lost its own.)"""
    m = _street()
    window = m.window_data(np.arange(6, 12))
    # The back end's answer from that window: a small refinement of each keyframe and of the window's points.
    rng = np.random.default_rng(1)
    T_ba = np.stack([T @ se3.exp(rng.normal(0, 0.01, 6)) for T in window.T_world_cam])
    T_ba[0] = window.T_world_cam[0]  # the window's first keyframe is held fixed
    p_ba = window.points + rng.normal(0, 0.02, window.points.shape)
    ba = MapCorrection(BACKEND, window.kf_ids, window.T_world_cam, T_ba, point_ids=window.point_ids,
                       point_positions=p_ba, base_version=window.version)
    # Meanwhile: a loop correction, growing along the chain (0 at keyframe 0, 2 m and 2 deg at keyframe 11).
    ids = np.arange(12)
    before = m.poses()
    C = np.stack([_pose(0.0, 0.0) @ se3.exp(np.array([0.2 * k / 11, 0, 2.0 * k / 11, 0, np.radians(2) * k / 11, 0]))
                  for k in ids])
    m.apply(MapCorrection(LOOP, ids, before, C @ before))
    m.apply(ba)
    after = m.poses()
    for r, k in enumerate(window.kf_ids):
        assert np.allclose(after[k], C[k] @ T_ba[r], atol=1e-9), k
    assert np.allclose(after[:6], (C @ before)[:6], atol=1e-9)  # older keyframes: the loop's correction only
    # Each refined point, in its creating keyframe's camera, is where the back end put it.
    ids_p, first = m.point_ids_and_first_keyframes()
    row = {int(p): n for n, p in enumerate(window.point_ids)}
    for p, k in zip(ids_p, first):
        if int(p) in row and k >= 6:
            local_ba = se3.transform_points(se3.inv(T_ba[k - 6]), p_ba[row[int(p)]][None])
            local_now = se3.transform_points(se3.inv(after[k]), m.point_positions([p]))
            assert np.allclose(local_now, local_ba, atol=1e-9)


def test_keyframes_made_after_a_snapshot_move_with_the_newest_corrected_one():
    m = _street(8)
    window = m.window_data(np.arange(2, 8))
    local_before = _in_creator(m)
    for k in range(8, 11):  # the tracker goes on meanwhile
        kf = m.add_keyframe(3 * k, _pose(float(k)))
        m.add_points(se3.transform_points(m.keyframe_pose(kf), np.array([[0.0, 0, 10]])), np.zeros((1, 32), np.uint8),
                     np.ones(1, bool), kf, np.arange(1), np.zeros((1, 2)))
    T_after = window.T_world_cam.copy()
    T_after[1:] = _pose(0.0, 0.05) @ T_after[1:]
    rel_before = se3.inv(m.keyframe_pose(7)) @ m.keyframe_pose(10)
    m.apply(MapCorrection(BACKEND, window.kf_ids, window.T_world_cam, T_after))
    assert np.allclose(se3.inv(m.keyframe_pose(7)) @ m.keyframe_pose(10), rel_before, atol=1e-9)
    assert np.allclose(_in_creator(m)[: len(local_before)], local_before, atol=1e-9)  # landmarks rode along
    assert np.allclose(_in_creator(m)[-3:], [[0, 0, 10]] * 3, atol=1e-9)


def test_only_the_map_assigns_keyframe_poses():
    m = _street(3)
    with pytest.raises(ValueError):
        m._kfs["T_world_cam"][0] = np.eye(4)  # read-only outside add_keyframe and apply
    with pytest.raises(ValueError):
        m._kfs.cols["T_world_cam"][1, 0, 3] = 1.0
    m.add_keyframe(9, _pose(3.0))  # growing keeps it read-only
    with pytest.raises(ValueError):
        m._kfs["T_world_cam"][3] = np.eye(4)


def test_workers_hold_no_map_and_every_write_goes_through_apply(synth_sequence_factory, monkeypatch):
    """A concurrent run (thread workers, so that this process sees every write): the workers' cores keep no
    reference to the map, and every pose write comes from LandmarkMap.apply (or add_keyframe)."""
    import inspect

    from plvo.config import SystemConfig, merge
    from plvo.data.kitti import KittiOdometry
    from plvo.runtime.system import System

    writers: list[str] = []
    original = LandmarkMap.apply_update

    def spy(self, *args, **kwargs):
        writers.append(inspect.stack()[1].function)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(LandmarkMap, "apply_update", spy)
    ds = KittiOdometry(synth_sequence_factory(16, seed=0), "00")
    cfg = merge(SystemConfig(), {"backend": {"executor": "thread"}, "loop": {"enabled": True}})
    system = System(cfg)
    try:
        for i in range(len(ds)):
            system.step(ds[i])
        system.finish()
        assert len(system.workers) == 2  # back end and loop closer (no features process with thread workers)
        for worker in system.workers:
            assert not any(isinstance(v, LandmarkMap) for v in vars(worker._core).values())
    finally:
        system.close()
    assert writers and set(writers) == {"apply"}, set(writers)


def _run_poses(ds, cfg) -> np.ndarray:
    from plvo.runtime.run import run_dataset

    return run_dataset(ds, cfg).poses


@pytest.mark.slow
def test_concurrent_result_does_not_depend_on_worker_timing(synth_sequence_factory, monkeypatch):
    """The deployed mode (concurrent workers) gives the same trajectory whether its workers are fast, slow or in
    another process: results are applied at fixed frames, and the tracker waits for a late one."""
    import plvo.backend.worker as bw
    import plvo.loop.worker as lw
    from plvo.config import SystemConfig, merge
    from plvo.data.kitti import KittiOdometry

    ds = KittiOdometry(synth_sequence_factory(40, seed=3), "00")
    base = merge(SystemConfig(), {"loop": {"enabled": True}})
    in_process = _run_poses(ds, base)
    threaded = merge(base, {"backend": {"executor": "thread"}})
    fast = _run_poses(ds, threaded)
    rng = np.random.default_rng(0)
    for cls in (bw.BackendCore, lw.LoopCore):  # late workers: 0-300 ms more a job, at random
        process = cls.process

        def late(self, job, _process=process):
            time.sleep(float(rng.uniform(0, 0.3)))
            return _process(self, job)

        monkeypatch.setattr(cls, "process", late)
    slow = _run_poses(ds, threaded)
    inline = _run_poses(ds, merge(base, {"backend": {"concurrent": False}}))
    for other in (fast, slow):
        assert np.abs(other[:, :3, 3] - in_process[:, :3, 3]).max() < 1e-6
    # Inline (lag 0) is another fixed order of work: close to the concurrent one, not equal.
    assert np.abs(inline[:, :3, 3] - in_process[:, :3, 3]).max() > 0


def test_a_global_ba_read_before_a_later_loop_correction_is_skipped():
    """Loop jobs queued before a global BA job run first; when one of them closed another loop, the BA's data
    (read from the map before that correction) is stale: it is skipped, and the System submits a fresh one."""
    from plvo.loop.worker import GlobalBAJob, LoopCore

    m = _street(4)
    core = object.__new__(LoopCore)  # only the bookkeeping is exercised: no vocabulary, no calibration
    core._skipped = 0
    core._made = [MapCorrection(LOOP, np.arange(4), m.poses(), m.poses()),
                  MapCorrection(LOOP, np.arange(4), m.poses(), m.poses())]
    out = core.process(GlobalBAJob(30, m.global_data(), 1.0, corrections_applied=1))
    assert out.correction is None and out.rejected.startswith("superseded")


@pytest.mark.parametrize("lag", [3, 6])
def test_the_back_end_lag_decides_where_the_tracker_waits(synth_sequence_factory, monkeypatch, lag):
    """A keyframe's back-end result is applied at its frame + backend.max_lag_frames or when the next keyframe is
    made, whichever is first. With the next keyframe within the lag (6, the default), the result is applied after
    that keyframe's frame was tracked, so the frame's tracking and depth priors run while the back end works; with
    a lag equal to the keyframe spacing (3) the tracker waited for the result before tracking that frame. Each
    keyframe tracked before its predecessor's result is solved again on the refined map (BackendStage.catch_up)."""
    from plvo.config import SystemConfig, merge
    from plvo.data.kitti import KittiOdometry
    from plvo.runtime.system import System
    from plvo.runtime.worker_stages import BackendStage
    from plvo.tracking.frontend import Frontend

    events: list[tuple[str, int]] = []
    track, apply_backend = Frontend.track, BackendStage.apply

    def spy_track(self, frame, *args, **kwargs):
        out = track(self, frame, *args, **kwargs)
        events.append(("tracked", frame.index))
        return out

    def spy_apply(self, out):
        events.append(("applied", out.frame_index))
        return apply_backend(self, out)

    monkeypatch.setattr(Frontend, "track", spy_track)
    monkeypatch.setattr(BackendStage, "apply", spy_apply)
    ds = KittiOdometry(synth_sequence_factory(16, seed=0), "00")
    system = System(merge(SystemConfig(), {"backend": {"executor": "thread", "max_lag_frames": lag},
                                           "loop": {"enabled": False}}))
    try:
        for i in range(len(ds)):
            system.step(ds[i])
        keyframes = [system.map.keyframe_frame(k) for k in range(system.map.n_keyframes)]
        system.finish()
    finally:
        system.close()
    order = {e: n for n, e in enumerate(events)}
    pairs = [(a, b) for a, b in zip(keyframes, keyframes[1:]) if ("applied", a) in order]
    assert any(3 <= b - a < 6 for a, b in pairs), keyframes  # spacings where the two lags differ
    for a, b in pairs:
        after_tracking = order[("applied", a)] > order[("tracked", b)]
        assert after_tracking == (b - a < lag), (lag, a, b, keyframes)
    # A keyframe tracked before the previous one's result was applied is solved again on the refined map.
    late = sum(order[("applied", a)] > order[("tracked", b)] for a, b in pairs)
    assert system.loop_stats.relocalised == late, (system.loop_stats, late)
