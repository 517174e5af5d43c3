"""What the evaluation says about where the drift comes from: the per-stage heading and scale error of keyframe steps
(plvo_eval.stage_drift), each accepted loop judged by its edge (plvo_eval.revisits.loop_edge_errors), and Table I
with its development and held-out rows pooled apart (plvo_eval.splits)."""

from __future__ import annotations

import numpy as np
import pytest

from plvo.data.trajectory import write_kitti_poses
from plvo.geometry import se3
from plvo.results import StageSteps
from plvo_eval.kitti_metric import evaluate
from plvo_eval.report import build_report, report_json, report_markdown
from plvo_eval.revisits import loop_edge_errors
from plvo_eval.splits import DEVELOPMENT, HELD_OUT, twin_split
from plvo_eval.stage_drift import stage_drift
from plvo_eval.tasks import RunSpec, SequenceSource, TaskResult

UP_CAM = np.array([0.0, -1.0, 0.0])  # KITTI's cam0: y down


def _path(n: int, step_m: float, yaw_deg: float = 0.0, scale: float = 1.0) -> np.ndarray:
    """Camera poses (n,4,4) driving forward (z) in steps of step_m * scale, turning yaw_deg a step to the left."""
    step = se3.from_rt(se3.so3_exp(np.radians(yaw_deg) * UP_CAM), [0.0, 0.0, step_m * scale])
    out = [np.eye(4)]
    for _ in range(n - 1):
        out.append(out[-1] @ step)
    return np.stack(out)


def test_each_stage_is_charged_with_the_heading_and_scale_it_left():
    gt = _path(301, 1.0, yaw_deg=0.2)  # 300 m, turning
    est = _path(301, 1.0, yaw_deg=0.2 + 0.01, scale=1.002)  # the final trajectory: 1 deg a 100 m, 0.2 % long
    frames = np.arange(301)
    steps = []
    for a, b in zip(frames[:-3:3], frames[3::3]):  # a keyframe every 3 frames
        truth = se3.inv(gt[a]) @ gt[b]
        tracker = truth @ se3.from_rt(se3.so3_exp(np.radians(0.05) * UP_CAM), [0.0, 0.0, 0.03])  # 5 deg / 100 m
        steps.append(StageSteps((a, b), {"tracker": tracker, "ba": truth.copy()}))
    out = stage_drift(steps, frames, gt, est)
    tr, ba, final = out["tracker"], out["ba"], out["final"]
    assert tr["steps"] == ba["steps"] == final["steps"] == 100 and out["scale"]["steps"] == 0
    assert tr["yaw_deg_per_100m"] == pytest.approx(100 / 3 * 0.05, rel=0.02)  # ~33 steps a 100 m
    assert tr["yaw_bias_deg_per_100m"] == pytest.approx(tr["yaw_deg_per_100m"], rel=0.02)  # always the same way
    assert tr["scale_pct"] == pytest.approx(1.0, rel=0.02)  # 3 cm on 3 m
    assert ba["yaw_deg_per_100m"] == pytest.approx(0.0, abs=1e-9) and ba["scale_pct"] == pytest.approx(0, abs=1e-9)
    assert final["yaw_deg_per_100m"] == pytest.approx(1.0, rel=0.02) and final["scale_pct"] == pytest.approx(0.2,
                                                                                                          rel=0.02)
    other_way = [StageSteps((a, b), {"tracker": se3.inv(gt[a]) @ gt[b] @ se3.from_rt(
        se3.so3_exp(np.radians(-0.05) * UP_CAM), [0.0, 0.0, 0.0])}) for a, b in (e.frames for e in steps)]
    turned = stage_drift(other_way, frames, gt, est)["tracker"]
    assert turned["yaw_bias_deg_per_100m"] == pytest.approx(-tr["yaw_bias_deg_per_100m"], rel=0.05)  # the other way
    short = stage_drift(steps[:5], frames, gt, est)["tracker"]
    assert short["steps"] == 5 and short["yaw_deg_per_100m"] is None  # 15 m: no stretch to judge


def test_a_loop_is_judged_by_its_edge_whichever_way_it_was_seen():
    gt = np.stack([np.eye(4), se3.from_rt(se3.so3_exp(np.radians(180.0) * UP_CAM), [2.0, 0.0, 6.0]),
                   se3.from_rt(np.eye(3), [300.0, 0.0, 0.0])])
    kf_row = {10: 0, 90: 1, 95: 2}
    right = se3.inv(gt[0]) @ gt[1]
    slightly_off = right @ se3.from_rt(se3.so3_exp(np.radians([0.0, 0.3, 0.0])), [0.05, 0.0, 0.1])
    wrong = se3.inv(gt[0]) @ gt[2] @ se3.from_rt(np.eye(3), [0.0, 0.0, 3.0])
    out = loop_edge_errors(gt, kf_row, [(10, 90, right), (10, 90, slightly_off), (10, 95, np.eye(4)),
                                        (10, 95, wrong), (10, 7, right)])
    assert [e["true"] for e in out] == [True, True, False, False]  # keyframe 7 has no frame: left out
    assert out[0]["heading_apart_deg"] == pytest.approx(180.0) and out[0]["edge_error_m"] == pytest.approx(0.0)
    assert out[2]["edge_error_m"] == pytest.approx(300.0) and out[3]["edge_error_m"] == pytest.approx(3.0)


def _task(tmp_path, setting: str, seq: str, scale: float) -> TaskResult:
    spec = RunSpec(SequenceSource("root", seq.removeprefix("twin"), label=seq), setting=setting, ablation=setting)
    folder = tmp_path / "runs" / setting / seq
    folder.mkdir(parents=True)
    gt = _path(150, 1.5, yaw_deg=0.1)
    est = gt.copy()
    est[:, :3, 3] *= scale
    write_kitti_poses(folder / "gt.txt", gt)
    write_kitti_poses(folder / "poses.txt", est)
    drift = {"tracker": {"steps": 10, "yaw_deg_per_100m": 0.5, "scale_pct": 0.3},
             "final": {"steps": 10, "yaw_deg_per_100m": 0.02, "scale_pct": 0.01}}
    loops = [{"true": True, "edge_error_m": 0.04, "edge_error_deg": 0.1}]
    return TaskResult(spec, "ok", "", len(gt), 1.0, len(gt), None, {}, folder,
                      {"stage_drift": drift, "loops": loops} if setting == "full" else {})


def test_table_i_pools_the_development_and_held_out_twins_apart(tmp_path):
    assert twin_split("twin04") == DEVELOPMENT and twin_split("twin08") == DEVELOPMENT
    assert twin_split("twin07") == HELD_OUT
    assert twin_split("twin11") is None and twin_split("04") is None
    scales = {"twin07": 1.03, "twin04": 1.01, "twin09": 1.02, "twin00": 1.05}
    results = [_task(tmp_path, s, q, k if s == "full" else 1.0 + 2 * (k - 1.0)) for q, k in scales.items()
               for s in ("full", "kiss")]
    report = build_report(results)
    assert report.sequences == ("twin04", "twin09", "twin07", "twin00")  # development rows first
    data = report_json(report)
    assert data["splits"] == {DEVELOPMENT: ["twin04", "twin09"], HELD_OUT: ["twin07", "twin00"]}
    t = data["t_err_pct"]["full"]
    dev = evaluate({q: report.poses["full"][q] for q in ("twin04", "twin09")}).kitti.t_err_pct
    held = evaluate({q: report.poses["full"][q] for q in ("twin07", "twin00")}).kitti.t_err_pct
    assert t["all (development)"] == pytest.approx(dev) and t["all (held-out)"] == pytest.approx(held)
    assert dev < t["all"] < held
    assert data["stage_drift"]["full"]["twin04"]["tracker"]["yaw_deg_per_100m"] == 0.5
    assert data["plvo_loops"]["full"]["twin00"]["true"] == 1 and "kiss" not in data["plvo_loops"]
    md = report_markdown(report, data)
    assert "| all (development) |" in md and "| all (held-out) |" in md
    assert "Where the heading and the scale go: Ours (*)" in md
    assert "| twin04 | 0.500 / 0.30 | - | - | 0.020 / 0.01 |" in md
    assert "held out: twin07, twin00" in md
    single = build_report([r for r in results if r.spec.source.name in ("twin04", "twin09")])
    assert not single.split_evaluations and "splits" not in report_json(single)  # one split only: pooled once
