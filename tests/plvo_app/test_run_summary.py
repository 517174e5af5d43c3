"""The run's summary (plvo_app.run_summary): figures from truth and poses, the terminal's lines, the latest link.
The whole path through plvo-viz is tested in tests/plvo_app/test_cmd_viz.py (summary.json of a KITTI run)."""

import numpy as np
import pytest

from plvo_app.run_summary import accuracy, build_summary, point_latest, summary_lines
from plvo_eval.kitti_metric import evaluate_sequence


def _drive(n: int, step_m: float, yaw_per_frame: float = 0.0) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    yaw = 0.0
    for i in range(1, n):
        yaw += yaw_per_frame
        c, s = np.cos(yaw), np.sin(yaw)
        poses[i, :3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]  # about the camera's vertical (y) axis
        poses[i, :3, 3] = poses[i - 1, :3, 3] + poses[i, :3, :3] @ [0.0, 0.0, step_m]
    return poses


def test_a_long_run_gets_the_devkit_figure_and_the_lines_say_it():
    truth = _drive(200, 1.0)  # 199 m: the devkit's 100 m segments exist
    est = _drive(200, 1.01, yaw_per_frame=1e-4)  # 1 % long and slowly turning
    acc = accuracy(truth, est)
    ev = evaluate_sequence(truth, est)
    assert acc["devkit"]["t_err_pct"] == pytest.approx(ev.kitti.t_err_pct, abs=1e-4) and acc["devkit"]["segments"]
    assert acc["ate_se3_m"] == pytest.approx(ev.ate_se3.rmse_m, abs=1e-4) and acc["ate_se3_m"] > 0.05
    assert acc["sim3_scale"] == pytest.approx(1 / 1.01, abs=2e-3)
    summary = build_summary(run="r", sequence="s", status="complete", reason="", frame_indices=range(200),
                            frames_done=200, frames_tracked=200, fps=12.5, poses_file=None, pose_format="kitti",
                            truth_source="poses/00.txt", truth_file=None, figures=acc)
    lines = summary_lines(summary)
    assert lines[0] == "accuracy against the truth (poses/00.txt), 200 frames, 199.0 m:"
    assert any(line.startswith("  KITTI devkit (100..800 m): ") and " %" in line for line in lines)
    assert "10 m: " in lines[2] and "40 m: " in lines[2]


def test_a_run_without_truth_has_no_accuracy_lines():
    summary = build_summary(run="r", sequence="bag", status="complete", reason="", frame_indices=[5, 6],
                            frames_done=2, frames_tracked=1, fps=3.0, poses_file=None, pose_format="tum",
                            truth_source=None, truth_file=None, figures=None)
    assert summary_lines(summary) == [] and summary["accuracy"] is None and summary["tracked_share"] == 0.5
    assert summary["frame_indices"] == [5, 6]


def test_latest_link_never_replaces_a_users_file(tmp_path):
    older, newer = tmp_path / "04_a", tmp_path / "04_b"
    older.mkdir(), newer.mkdir()
    assert point_latest(older) == tmp_path / "latest" and point_latest(newer) == tmp_path / "latest"
    assert (tmp_path / "latest").resolve() == newer.resolve() and older.is_dir()
    (tmp_path / "latest").unlink()
    (tmp_path / "latest").write_text("the user's")
    assert point_latest(newer) is None and (tmp_path / "latest").read_text() == "the user's"
