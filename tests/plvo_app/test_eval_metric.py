"""`plvo eval metric`: table and JSON output, one-line errors with exit status 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from faults_table import fault

from plvo.data.trajectory import read_kitti_poses, write_kitti_poses
from plvo.geometry import se3
from plvo_app.cli import main
from plvo_eval.kitti_metric import evaluate_sequence


def _line(n: int, spacing: float = 0.5) -> np.ndarray:
    return np.stack([se3.from_rt(np.eye(3), [0.0, 0.0, spacing * k]) for k in range(n)])


@pytest.fixture
def scaled_pair(tmp_path) -> tuple[Path, Path]:
    gt = _line(1000)  # 499.5 m straight
    est = gt.copy()
    est[:, :3, 3] *= 1.02
    write_kitti_poses(tmp_path / "gt.txt", gt)
    write_kitti_poses(tmp_path / "est.txt", est)
    return tmp_path / "gt.txt", tmp_path / "est.txt"


def test_json_output(scaled_pair, capsys):
    gt, est = scaled_pair
    assert main(["eval", "metric", "--gt", str(gt), "--est", str(est), "--json", "--short", "5,15"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {"t_err_pct", "r_err_deg_per_m", "ate_m", "segments", "short"} <= set(out)
    # scale 1.02 on a straight path: 2 %, times the segment's overshoot of its nominal length (here one 0.5 m step,
    # as the devkit ends a segment at the first frame strictly beyond the length)
    assert out["t_err_pct"] == pytest.approx(2.0, rel=5e-3)
    for length in (100, 200, 300, 400):
        assert out["segments"][str(length)]["t_err_pct"] == pytest.approx(2.0 * (length + 0.5) / length, rel=1e-9)
    assert out["r_err_deg_per_m"] == pytest.approx(0.0, abs=1e-9)
    assert list(out["segments"]) == ["100", "200", "300", "400", "500", "600", "700", "800"]
    assert out["segments"]["100"]["n_segments"] == 80 and out["segments"]["500"]["n_segments"] == 0
    assert out["segments"]["500"]["t_err_pct"] is None  # no 500 m segment in 499.5 m
    assert list(out["short"]) == ["5", "15"]
    assert out["short"]["15"]["t_err_pct"] == pytest.approx(2.0 * 15.5 / 15, rel=1e-9)
    assert out["ate_sim3_m"] < 1e-6 and out["ate_m"] > 1.0 and out["n_frames"] == 1000


def test_a_truth_that_does_not_move_gets_no_sim3_score(tmp_path, capsys):
    """A standing truth and an estimate that drove off: the Sim(3) fit used to shrink the estimate to a point and
    report 0.0000 m (a perfect score); now it is none, said so, null in the JSON, and the SE(3) ATE tells the
    drift."""
    row = fault("metric-still-truth")
    still = np.stack([np.eye(4)] * 20)
    write_kitti_poses(tmp_path / "gt.txt", still)
    write_kitti_poses(tmp_path / "est.txt", _line(20))
    args = ["eval", "metric", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt")]
    assert main(args) == row.exit
    ate = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("ATE"))
    assert row.message in ate and "after Sim(3) alignment (scale" not in ate, ate
    assert main([*args, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ate_sim3_m"] is None and out["sim3_scale"] is None
    assert out["ate_m"] == pytest.approx(np.sqrt(np.mean((0.5 * np.arange(20) - 4.75) ** 2)), rel=1e-9)


def test_table_output(scaled_pair, capsys):
    gt, est = scaled_pair
    assert main(["eval", "metric", "--gt", str(gt), "--est", str(est)]) == 0
    out = capsys.readouterr().out
    assert "KITTI devkit metric" in out and "ATE RMSE" in out and "short relative error" in out
    row_100 = next(line for line in out.splitlines() if line.strip().startswith("100 m"))
    assert float(row_100.split()[3]) == pytest.approx(2.01, abs=1e-3)


def test_json_matches_library_on_real_ground_truth(kitti_root, tmp_path, capsys):
    gt_path = kitti_root / "poses" / "04.txt"
    gt = read_kitti_poses(gt_path)
    rng = np.random.default_rng(4)
    est = np.stack([T @ se3.exp(rng.normal(0, 0.01, 6)) for T in gt])
    write_kitti_poses(tmp_path / "est.txt", est)
    assert main(["eval", "metric", "--gt", str(gt_path), "--est", str(tmp_path / "est.txt"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    ev = evaluate_sequence(gt, read_kitti_poses(tmp_path / "est.txt"))
    assert out["t_err_pct"] == pytest.approx(ev.kitti.t_err_pct, rel=1e-12)
    assert out["ate_m"] == pytest.approx(ev.ate_se3.rmse_m, rel=1e-12)
    assert out["short"]["10"]["t_err_pct"] == pytest.approx(ev.short.per_length[0].t_err_pct, rel=1e-12)


@pytest.fixture
def turned_pair(tmp_path) -> tuple[Path, Path]:
    """A 300 m straight truth, and an estimate of it 1 % too long, heading 0.5 deg to the left of the truth."""
    gt = _line(600)
    R = se3.from_rt(se3.so3_exp(np.array([0.0, np.radians(-0.5), 0.0])), np.zeros(3))
    est = R @ gt @ R.T
    est[:, :3, 3] *= 1.01
    write_kitti_poses(tmp_path / "gt.txt", gt)
    write_kitti_poses(tmp_path / "est.txt", est)
    return tmp_path / "gt.txt", tmp_path / "est.txt"


def test_json_gives_both_readings(turned_pair, capsys):
    gt, est = turned_pair
    assert main(["eval", "metric", "--gt", str(gt), "--est", str(est), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    aligned = out["heading_aligned"]
    assert aligned["heading_offset_deg"] == pytest.approx(0.5, abs=1e-9)
    # as the devkit reads it: the 1 % scale and the 0.5 deg turn (0.87 %) together, |1.01 R e - e| / |e| (1.33 %),
    # times each segment's overshoot of its nominal length by one 0.5 m step
    both = 100 * np.sqrt(1.01**2 - 2 * 1.01 * np.cos(np.radians(0.5)) + 1)
    assert out["segments"]["100"]["t_err_pct"] == pytest.approx(both * 100.5 / 100, rel=1e-6)
    assert out["short"]["10"]["t_err_pct"] == pytest.approx(both * 10.5 / 10, rel=1e-6)
    # the turn taken out: the scale error alone
    assert aligned["segments"]["100"]["t_err_pct"] == pytest.approx(1.0 * 100.5 / 100, rel=1e-6)
    assert aligned["short"]["10"]["t_err_pct"] == pytest.approx(1.0 * 10.5 / 10, rel=1e-6)
    assert aligned["segments"]["100"]["n_segments"] == out["segments"]["100"]["n_segments"] == 40
    assert "ate_m" in out and "ate_m" not in aligned  # ATE aligns the whole path anyway: one reading


def test_table_gives_both_readings_and_names_the_angle(turned_pair, capsys):
    gt, est = turned_pair
    assert main(["eval", "metric", "--gt", str(gt), "--est", str(est)]) == 0
    out = capsys.readouterr().out
    assert "heading offset taken out: 0.500 deg about the camera's vertical axis" in out
    head, aligned = out.split("heading offset taken out:", 1)
    assert "KITTI devkit metric, heading offset taken out:" in aligned
    assert "short relative error, heading offset taken out:" in aligned

    def row(text: str, length: str) -> float:
        return float(next(line for line in text.splitlines() if line.strip().startswith(length)).split()[3])

    assert row(head, "100 m") == pytest.approx(1.330 * 1.005, abs=2e-3)
    assert row(aligned, "100 m") == pytest.approx(1.005, abs=1e-3)
    assert row(aligned, "10 m") == pytest.approx(1.05, abs=1e-3)


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def test_missing_file(scaled_pair, tmp_path, capsys):
    gt, _ = scaled_pair
    assert main(["eval", "metric", "--gt", str(gt), "--est", str(tmp_path / "none.txt")]) == 2
    assert "none.txt: no such pose file" in _error_line(capsys)


def test_wrong_number_of_columns(scaled_pair, tmp_path, capsys):
    gt, est = scaled_pair
    lines = est.read_text().splitlines()
    lines[4] = " ".join(lines[4].split()[:8])
    (tmp_path / "bad.txt").write_text("\n".join(lines) + "\n")
    assert main(["eval", "metric", "--gt", str(gt), "--est", str(tmp_path / "bad.txt")]) == 2
    assert "bad.txt:5: expected 12 numbers" in _error_line(capsys)


def test_different_lengths(scaled_pair, tmp_path, capsys):
    gt, _ = scaled_pair
    write_kitti_poses(tmp_path / "short.txt", _line(900))
    assert main(["eval", "metric", "--gt", str(gt), "--est", str(tmp_path / "short.txt"), "--json"]) == 2
    err = _error_line(capsys)
    assert "short.txt: 900 poses" in err and "has 1000" in err
    assert capsys.readouterr().out == ""


def test_bad_short_lengths(scaled_pair, capsys):
    gt, est = scaled_pair
    assert main(["eval", "metric", "--gt", str(gt), "--est", str(est), "--short", "10,x"]) == 2
    assert "'x' is not a number" in _error_line(capsys)


def test_installed_command_exits_2_with_one_line(tmp_path):
    """The real `plvo` process: no traceback, one line on stderr, exit status 2."""
    exe = Path(sys.executable).parent / "plvo"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "plvo_app.cli"]
    proc = subprocess.run(
        [*cmd, "eval", "metric", "--gt", str(tmp_path / "a.txt"), "--est", str(tmp_path / "b.txt")],
        capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [f"error: {tmp_path / 'a.txt'}: no such pose file"]
