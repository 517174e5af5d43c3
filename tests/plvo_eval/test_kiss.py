"""KISS-ICP baseline on the 51 real frames of KITTI 04 reproduces the figure in shared/data/README.md:
0.74 / 0.63 / 0.55 % over 10 / 20 / 40 m (every frame a start) and 0.34 m final drift (voxel 1 m, no deskew); on
raw sweeps the evaluation runs it deskewed and not and reports the run closer to the truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from plvo.data.registry import open_dataset
from plvo_eval import tasks
from plvo_eval.kiss import KissOptions, KissOutput, lidar_to_cam0, run_kiss
from plvo_eval.kitti_metric import short_relative_error
from plvo_eval.tasks import (
    DESKEWED,
    NOT_DESKEWED,
    RunSpec,
    SequenceSource,
    anchor,
    better_way,
    execute_task,
    load_poses,
    write_task,
)

REFERENCE_PCT = {10.0: 0.74, 20.0: 0.63, 40.0: 0.55}
REFERENCE_DRIFT_M = 0.34


def test_kiss_on_real_frames_reproduces_reference(kitti_root):
    dataset = open_dataset(kitti_root, "04")
    out = run_kiss(dataset, KissOptions())
    assert out.poses.shape == (51, 4, 4)
    np.testing.assert_allclose(out.poses[0], np.eye(4), atol=1e-12)
    gt = dataset.gt_T_world_cam
    est = anchor(out.poses, gt[0])
    short = short_relative_error(gt, est)
    for e in short.per_length:
        # measured 0.738 / 0.627 / 0.554 %; KISS-ICP is deterministic up to thread scheduling
        assert e.t_err_pct == pytest.approx(REFERENCE_PCT[e.length_m], abs=0.03), e
    drift = float(np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]))
    assert drift == pytest.approx(REFERENCE_DRIFT_M, abs=0.03)


def test_lidar_to_cam0_conjugates():
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 1.5]
    lidar = np.stack([np.eye(4), T])
    moved = np.eye(4)
    moved[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]  # velo x forward -> cam z forward
    cam = lidar_to_cam0(lidar, moved)
    np.testing.assert_allclose(cam[1][:3, 3], [0.2, -1.5, 0.1])


# ---------------------------------------------------------------- both ways on raw sweeps


class _Straight:
    """A stand-in dataset: n frames 1 m apart straight ahead, its scans raw sweeps unless compensated."""

    sequence = "straight"

    def __init__(self, n: int, compensated: bool = False, truth: bool = True) -> None:
        self.n, self.scans_compensated = n, compensated
        self.gt_T_world_cam = _path(n, 1.0) if truth else None

    def __len__(self) -> int:
        return self.n


def _path(n: int, step: float) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = step * np.arange(n)
    return poses


def _fake_kiss(scale_deskewed: float, scale_not: float, calls: list[bool]):
    """run_kiss's stand-in: a path too long by the given scale, deskewed or not, each call recorded."""
    def run(dataset, options):
        calls.append(options.deskew)
        poses = _path(len(dataset), scale_deskewed if options.deskew else scale_not)
        return KissOutput(poses=poses, lidar_poses=poses, seconds=np.zeros(len(dataset)))
    return run


@pytest.mark.parametrize("n, deskewed, not_deskewed, reported, judged_by", [
    (40, 1.03, 1.01, NOT_DESKEWED, "short_t_err_pct"),  # 39 m: no devkit segment, the 10/20 m ones judge
    (40, 1.01, 1.03, DESKEWED, "short_t_err_pct"),
    (40, 1.02, 1.02, DESKEWED, "short_t_err_pct"),  # a tie keeps the data's own convention, deskewed
    (130, 1.04, 1.02, NOT_DESKEWED, "t_err_pct"),  # 129 m: the devkit's 100 m segments judge
])
def test_peers_on_raw_sweeps_run_both_ways_and_report_the_better(tmp_path, monkeypatch, n, deskewed, not_deskewed,
                                                                 reported, judged_by):
    calls: list[bool] = []
    monkeypatch.setattr(tasks, "run_kiss", _fake_kiss(deskewed, not_deskewed, calls))
    monkeypatch.setattr(SequenceSource, "open", lambda self: _Straight(n))
    spec = RunSpec(SequenceSource("unused", "straight"), "kiss", "kiss", None)
    result = write_task(execute_task(spec), tmp_path)
    assert result.ok and sorted(calls) == [False, True]
    deskew = result.details["ways"]
    assert deskew["reported"] == reported and deskew["judged_by"] == judged_by
    ways = deskew["ways"]
    # each way's figure is its scale error: a path s times too long reads |s - 1| times each segment's length over
    # its nominal one, which 1 m steps make up to 10 % longer (a segment ends past its length)
    for way, scale in ((DESKEWED, deskewed), (NOT_DESKEWED, not_deskewed)):
        assert 100 * (scale - 1) - 1e-9 <= ways[way]["metrics"][judged_by] <= 110 * (scale - 1)
    assert result.metrics == ways[reported]["metrics"]  # the table's figures are the reported run's
    gt, est = load_poses(result)
    np.testing.assert_allclose(est[-1, 2, 3], (n - 1) * (deskewed if reported == DESKEWED else not_deskewed))


def test_peers_run_once_on_compensated_scans_or_when_told(monkeypatch):
    calls: list[bool] = []
    monkeypatch.setattr(tasks, "run_kiss", _fake_kiss(1.01, 1.03, calls))
    spec = RunSpec(SequenceSource("unused", "straight"), "kiss", "kiss", None)
    out = tasks._method_kiss(_Straight(40, compensated=True), spec)
    assert calls == [True] and "ways" not in out.details
    for options in (KissOptions(both_ways=False), KissOptions(deskew=False)):
        calls.clear()
        out = tasks._method_kiss(_Straight(40), replace(spec, kiss=options))
        assert calls == [options.deskew] and "ways" not in out.details


def test_without_truth_the_deskewed_run_is_reported():
    runs = {way: tasks.MethodOutput(_path(40, scale), {}, {"loop_closures": k})
            for k, (way, scale) in enumerate(((DESKEWED, 1.03), (NOT_DESKEWED, 1.01)))}
    out = better_way(runs, None)
    assert out.details["ways"]["reported"] == DESKEWED and out.details["ways"]["judged_by"] is None
    assert out.details["loop_closures"] == 0  # the reported run's own figures stay at the top
    assert out.details["ways"]["ways"][NOT_DESKEWED]["details"] == {"loop_closures": 1}
    np.testing.assert_allclose(out.poses, runs[DESKEWED].poses)


def test_peers_on_a_lidar_with_kittis_elevation_error_run_with_its_correction_and_without(monkeypatch):
    """Real KITTI and the realistic twins carry KITTI's 0.205 deg elevation error: the peers run with kiss_icp's own
    KITTI correction and without, and the run closer to the truth is reported; raw sweeps add both of deskew."""
    calls: list[tuple[bool, bool]] = []

    def fake(dataset, options):
        calls.append((options.deskew, options.kitti_correction))
        poses = _path(len(dataset), 1.01 if options.kitti_correction else 1.03)
        return KissOutput(poses=poses, lidar_poses=poses, seconds=np.zeros(len(dataset)))

    class Kitti(_Straight):
        calib = type("Calib", (), {"lidar_elevation_offset_deg": 0.205})()

    monkeypatch.setattr(tasks, "run_kiss", fake)
    spec = RunSpec(SequenceSource("unused", "straight"), "kiss", "kiss", None)
    out = tasks._method_kiss(Kitti(40, compensated=True), spec)
    assert sorted(calls) == [(True, False), (True, True)]
    ways = out.details["ways"]
    assert ways["reported"] == tasks.AS_DELIVERED + tasks.CORRECTED and set(ways["ways"]) == {
        tasks.AS_DELIVERED, tasks.AS_DELIVERED + tasks.CORRECTED}
    np.testing.assert_allclose(out.poses[-1, 2, 3], 39 * 1.01)
    calls.clear()
    out = tasks._method_kiss(Kitti(40), spec)  # raw sweeps as well: four readings
    assert sorted(calls) == [(False, False), (False, True), (True, False), (True, True)]
    assert out.details["ways"]["reported"].endswith(tasks.CORRECTED)
    calls.clear()
    tasks._method_kiss(_Straight(40, compensated=True), spec)  # no elevation error: one run
    assert calls == [(True, False)]
