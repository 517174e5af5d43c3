"""`plvo eval metric` inputs: KITTI and TUM on either side, association by time, results folders (cut to their
frames, or their own truth.txt), --frames, several runs in one table, and the one-line refusals."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from faults_table import fault
from metric_files import EST, GT, TIMES, N, noisy_estimate, results_folder

from plvo.data.trajectory import write_poses
from plvo.errors import TrajectoryError
from plvo_app.cli import main
from plvo_app.eval_metric import SHORT_DEFAULT, parse_lengths
from plvo_eval.associate import associate, pose_format, times_beside
from plvo_eval.kitti_metric import SHORT_LENGTHS, evaluate_sequence


@pytest.fixture
def kitti_root(tmp_path) -> Path:
    """The KITTI odometry layout: ROOT/poses/00.txt and ROOT/sequences/00/times.txt."""
    root = tmp_path / "kitti"
    write_poses(root / "poses" / "00.txt", GT, TIMES, "kitti")
    (root / "sequences" / "00").mkdir(parents=True)
    (root / "sequences" / "00" / "times.txt").write_text("".join(f"{t:.6e}\n" for t in TIMES))
    return root


def _json(capsys, *args) -> dict | list:
    capsys.readouterr()
    assert main(["eval", "metric", *map(str, args), "--json"]) == 0, capsys.readouterr().err
    return json.loads(capsys.readouterr().out)


def _refused(capsys, *args) -> str:
    capsys.readouterr()
    status = main(["eval", "metric", *map(str, args)])
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert status == 2 and len(lines) == 1 and lines[0].startswith("error: "), captured.err
    assert captured.out == ""
    return lines[0]


FIGURES = ("n_frames", "path_length_m", "ate_m", "ate_sim3_m", "sim3_scale", "t_err_pct", "r_err_deg_per_m",
           "short_t_err_pct", "short_r_err_deg_per_m")


def _close(a, b, rel: float) -> bool:
    return a is b is None or (a is not None and b is not None and a == pytest.approx(b, rel=rel, abs=rel))


def _same_figures(a: dict, b: dict, rel: float = 1e-9) -> None:
    """The figures of two outputs alike (rel 0: exactly), whatever files they name."""
    for key in FIGURES:
        assert _close(a[key], b[key], rel), (key, a[key], b[key])
    for table in ("segments", "short"):
        assert list(a[table]) == list(b[table])
        for length in a[table]:
            for key, value in a[table][length].items():
                assert _close(value, b[table][length][key], rel), (table, length, key)
    assert _close(a["heading_aligned"]["heading_offset_deg"], b["heading_aligned"]["heading_offset_deg"], rel)


# ---- formats ------------------------------------------------------------------------------------------------------

def test_format_is_told_by_the_column_count(tmp_path):
    write_poses(tmp_path / "k.txt", GT[:3], TIMES[:3], "kitti")
    write_poses(tmp_path / "t.txt", GT[:3], TIMES[:3], "tum")
    (tmp_path / "h.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + (tmp_path / "t.txt").read_text())
    (tmp_path / "x.txt").write_text("1 2 3 4 5 6 7\n")
    assert [pose_format(tmp_path / f) for f in ("k.txt", "t.txt", "h.txt")] == ["kitti", "tum", "tum"]
    with pytest.raises(TrajectoryError, match=r"x\.txt:1: 7 numbers: neither a KITTI pose \(12 numbers\) nor a TUM"):
        pose_format(tmp_path / "x.txt")
    with pytest.raises(TrajectoryError, match="is a folder, not a pose file"):
        pose_format(tmp_path)
    # --help spells the default out without importing the metric
    assert parse_lengths(SHORT_DEFAULT) == SHORT_LENGTHS


def test_tum_estimate_against_kitti_truth_gives_the_kitti_figures(kitti_root, tmp_path, capsys):
    gt = kitti_root / "poses" / "00.txt"
    write_poses(tmp_path / "est.txt", EST, TIMES, "kitti")
    write_poses(tmp_path / "est_tum.txt", EST, TIMES, "tum")
    ref = _json(capsys, "--gt", gt, "--est", tmp_path / "est.txt")
    assert ref["pairing"] == "" and ref["n_frames"] == N
    # the times.txt of the odometry layout found beside poses/00.txt: paired by time
    by_time = _json(capsys, "--gt", gt, "--est", tmp_path / "est_tum.txt")
    assert by_time["pairing"] == (f"paired by time (truth times from {kitti_root / 'sequences' / '00' / 'times.txt'}):"
                                  f" {N} of {N} estimate poses matched a truth pose within 0.02 s")
    _same_figures(by_time, ref)
    # a lone KITTI truth: line by line, the counts being equal
    write_poses(tmp_path / "alone" / "gt.txt", GT, TIMES, "kitti")
    by_order = _json(capsys, "--gt", tmp_path / "alone" / "gt.txt", "--est", tmp_path / "est_tum.txt")
    assert "line by line" in by_order["pairing"]
    _same_figures(by_order, ref)
    # its times given
    (tmp_path / "stamps.txt").write_text("".join(f"{t:.9f}\n" for t in TIMES))
    given = _json(capsys, "--gt", tmp_path / "alone" / "gt.txt", "--gt-times", tmp_path / "stamps.txt",
                  "--est", tmp_path / "est_tum.txt")
    assert given["pairing"].startswith("paired by time (truth times from")
    _same_figures(given, ref)
    # and the other way round: a KITTI estimate against a TUM truth
    write_poses(tmp_path / "gt_tum.txt", GT, TIMES, "tum")
    _same_figures(_json(capsys, "--gt", tmp_path / "gt_tum.txt", "--est", tmp_path / "est.txt"), ref)


# ---- association --------------------------------------------------------------------------------------------------

def test_association_matches_the_right_pairs_with_jitter_and_drops():
    rng = np.random.default_rng(7)
    gt_t = 0.1 * np.arange(100)
    gt_kept = np.setdiff1d(np.arange(100), [20, 21, 70])  # the truth misses three poses
    est_of = np.setdiff1d(np.arange(100), [5, 6, 40])  # the estimate misses three others
    est_t = gt_t[est_of] + rng.uniform(-0.009, 0.009, len(est_of))
    est_t = np.concatenate([est_t, [3.05, 20.0, 20.1]])  # mid-way between two truth poses; after the truth's end
    order = np.argsort(est_t)
    est_t, est_of = est_t[order], np.concatenate([est_of, [-1, -1, -1]])[order]
    rng.shuffle(gt_kept)  # a truth out of order is matched all the same
    i_est, i_gt = associate(est_t, gt_t[gt_kept], 0.02)
    expected = np.flatnonzero(np.isin(est_of, gt_kept))
    np.testing.assert_array_equal(i_est, expected)
    np.testing.assert_array_equal(gt_kept[i_gt], est_of[i_est])
    assert len(i_est) == 100 - 6
    # one truth pose for two estimate poses: the closer keeps it
    i_est, i_gt = associate(np.array([0.995, 1.004, 1.1]), np.array([1.0, 1.1]), 0.02)
    assert list(i_est) == [1, 2] and list(i_gt) == [0, 1]


def test_tum_against_tum_is_associated_by_time(tmp_path, capsys):
    rng = np.random.default_rng(3)
    keep = np.setdiff1d(np.arange(N), [10, 11, 12, 99])
    write_poses(tmp_path / "gt.txt", GT, TIMES, "tum")
    write_poses(tmp_path / "est.txt", EST[keep], TIMES[keep] + rng.uniform(-0.01, 0.01, len(keep)), "tum")
    capsys.readouterr()
    assert main(["eval", "metric", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt")]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first == f"{tmp_path / 'est.txt'}: paired by time: {len(keep)} of {len(keep)} estimate poses matched a " \
                    "truth pose within 0.02 s"
    out = _json(capsys, "--gt", tmp_path / "gt.txt", "--est", tmp_path / "est.txt")
    ev = evaluate_sequence(GT[keep], EST[keep])
    assert out["n_frames"] == len(keep)
    assert out["ate_m"] == pytest.approx(ev.ate_se3.rmse_m, rel=1e-9)
    assert out["short_t_err_pct"] == pytest.approx(ev.short.t_err_pct, rel=1e-9)
    # a tolerance below the jitter drops the pairs that are further apart
    tight = _json(capsys, "--gt", tmp_path / "gt.txt", "--est", tmp_path / "est.txt", "--max-dt", "0.005")
    assert 0.3 * len(keep) < tight["n_frames"] < 0.7 * len(keep)


def test_too_few_pairs_in_time_is_one_line(tmp_path, capsys):
    row = fault("metric-unpaired")
    write_poses(tmp_path / "gt.txt", GT, TIMES, "tum")
    write_poses(tmp_path / "est.txt", EST, TIMES - 1000.0, "tum")  # another clock
    line = _refused(capsys, "--gt", tmp_path / "gt.txt", "--est", tmp_path / "est.txt")
    assert f"{tmp_path / 'est.txt'}: 0 of {N} poses have a truth pose in {tmp_path / 'gt.txt'} within 0.02 s" in line
    assert row.message in line and row.exit == 2
    assert "same clock" in line and "--max-dt" in line


# ---- results folders and cuts -------------------------------------------------------------------------------------

@pytest.mark.parametrize("frames", [range(0, 51), range(30, 100)])
def test_a_partial_run_against_the_whole_truth_is_the_run_against_its_part(kitti_root, tmp_path, capsys, frames):
    run = results_folder(tmp_path / "results" / "run", frames)
    idx = list(frames)
    write_poses(tmp_path / "head.txt", GT[idx], TIMES[idx], "kitti")  # what `head -51` (or sed 31,100p) makes
    ref = _json(capsys, "--gt", tmp_path / "head.txt", "--est", run / "poses.txt")
    whole = _json(capsys, "--gt", kitti_root / "poses" / "00.txt", "--est", run)
    assert whole["name"] == "run" and whole["est"] == str(run) and whole["n_frames"] == len(idx)
    assert whole["pairing"] == (f"truth cut to frames {idx[0]}:{idx[-1] + 1} of {kitti_root / 'poses' / '00.txt'} "
                                f"({run / 'summary.json'})")
    _same_figures(whole, ref, rel=0.0)
    own = _json(capsys, "--est", run)  # no --gt: the folder's truth.txt
    assert own["gt"] == str(run / "truth.txt")
    _same_figures(own, ref, rel=0.0)
    cut = _json(capsys, "--gt", kitti_root / "poses" / "00.txt", "--est", run / "poses.txt",
                "--frames", f"{idx[0]}:{idx[-1] + 1}")
    _same_figures(cut, ref, rel=0.0)


def test_a_tum_run_folder_is_paired_by_time_with_a_kitti_truth(kitti_root, tmp_path, capsys):
    run = results_folder(tmp_path / "run", range(40, 120), fmt="tum")
    write_poses(tmp_path / "part.txt", GT[40:120], TIMES[40:120], "kitti")
    ref = _json(capsys, "--gt", tmp_path / "part.txt", "--est", run / "poses.txt")
    out = _json(capsys, "--gt", kitti_root / "poses" / "00.txt", "--est", run)
    assert out["pairing"].startswith("paired by time") and "80 of 80" in out["pairing"]
    _same_figures(out, ref)
    _same_figures(_json(capsys, "--est", run), ref)  # its TUM truth.txt


def test_missing_pieces_are_one_line(kitti_root, tmp_path, capsys):
    row = fault("metric-no-truth")
    gt = kitti_root / "poses" / "00.txt"
    no_truth = results_folder(tmp_path / "no_truth", range(0, 30), truth=False)
    line = _refused(capsys, "--est", no_truth)
    assert line == f"error: {no_truth}: {row.message}" and row.exit == 2
    assert main(["eval", "metric", "--est", str(no_truth), "--gt", str(gt)]) == 0  # --gt is the way out
    failed = tmp_path / "failed"
    failed.mkdir()
    (failed / "summary.json").write_text(json.dumps({"run": "failed", "status": "failed", "frame_indices": []}))
    line = _refused(capsys, "--est", failed, "--gt", gt)
    assert f"{failed}: no poses.txt (the run's status is 'failed'" in line
    line = _refused(capsys, "--est", tmp_path, "--gt", gt)
    assert f"{tmp_path}: no poses.txt (not a plvo results folder" in line
    wrong = results_folder(tmp_path / "wrong", range(0, 30))
    (wrong / "summary.json").write_text(json.dumps({"run": "wrong", "frame_indices": list(range(29))}))
    line = _refused(capsys, "--est", wrong, "--gt", gt)
    assert f"{wrong / 'summary.json'}: 'frame_indices' lists 29 frames, but {wrong / 'poses.txt'} has 30" in line
    (wrong / "summary.json").write_text("{not json")
    assert f"{wrong / 'summary.json'}: not JSON" in _refused(capsys, "--est", wrong, "--gt", gt)
    beyond = results_folder(tmp_path / "beyond", range(0, 30))
    write_poses(tmp_path / "short_gt.txt", GT[:20], TIMES[:20], "kitti")
    line = _refused(capsys, "--est", beyond, "--gt", tmp_path / "short_gt.txt")
    assert f"{tmp_path / 'short_gt.txt'}: 20 poses (frames 0..19), but {beyond / 'poses.txt'} holds frame 29" in line


def test_what_to_give_is_named(kitti_root, tmp_path, capsys):
    write_poses(tmp_path / "gt.txt", GT, TIMES, "kitti")
    write_poses(tmp_path / "est_tum.txt", EST[:60], TIMES[:60], "tum")
    write_poses(tmp_path / "est.txt", EST[:60], TIMES[:60], "kitti")
    write_poses(tmp_path / "gt_tum.txt", GT, TIMES, "tum")
    line = _refused(capsys, "--est", tmp_path / "est.txt")
    assert f"--est {tmp_path / 'est.txt'}: a pose file needs --gt" in line
    line = _refused(capsys, "--gt", tmp_path / "gt.txt", "--est", tmp_path / "est_tum.txt")
    assert line.startswith(f"error: {tmp_path / 'gt.txt'}: KITTI poses have no times") and "--gt-times" in line
    line = _refused(capsys, "--gt", tmp_path / "gt_tum.txt", "--est", tmp_path / "est.txt")
    assert line.startswith(f"error: {tmp_path / 'est.txt'}: KITTI poses have no times") and "--frames A:B" in line
    line = _refused(capsys, "--gt", tmp_path / "gt.txt", "--est", tmp_path / "est.txt")
    assert "est.txt: 60 poses, but the ground truth" in line and "--frames A:B" in line
    # each way out works
    for gt in ("gt.txt", "gt_tum.txt"):
        assert main(["eval", "metric", "--gt", str(tmp_path / gt), "--est", str(tmp_path / "est.txt"),
                     "--frames", "0:60"]) == 0
    (tmp_path / "t.txt").write_text("".join(f"{t}\n" for t in TIMES))
    assert main(["eval", "metric", "--gt", str(tmp_path / "gt.txt"), "--gt-times", str(tmp_path / "t.txt"),
                 "--est", str(tmp_path / "est_tum.txt")]) == 0
    line = _refused(capsys, "--gt", tmp_path / "gt.txt", "--est", tmp_path / "est.txt", "--frames", "100:200")
    assert f"--frames 100:200: {tmp_path / 'gt.txt'} has {N} poses" in line
    (tmp_path / "few.txt").write_text("".join(f"{t}\n" for t in TIMES[:10]))
    line = _refused(capsys, "--gt", tmp_path / "gt.txt", "--gt-times", tmp_path / "few.txt", "--est",
                    tmp_path / "est_tum.txt")
    assert f"{tmp_path / 'few.txt'}: 10 times for {N} poses" in line
    # a times.txt of the layout that does not fit its poses is named, not passed over
    (kitti_root / "sequences" / "00" / "times.txt").write_text("0.0\n0.1\n")
    line = _refused(capsys, "--gt", kitti_root / "poses" / "00.txt", "--est", tmp_path / "est_tum.txt")
    assert "times.txt: 2 times for 150 poses (found beside" in line and "--gt-times" in line
    run = results_folder(tmp_path / "run", range(0, 30))
    line = _refused(capsys, "--gt", tmp_path / "gt.txt", "--est", run, "--frames", "0:30")
    assert "--frames 0:30: every --est is a results folder" in line
    (tmp_path / "seven.txt").write_text("1 2 3 4 5 6 7\n")
    line = _refused(capsys, "--gt", tmp_path / "gt.txt", "--est", tmp_path / "seven.txt")
    assert "seven.txt:1: 7 numbers: neither a KITTI pose (12 numbers) nor a TUM line" in line


def test_times_beside_a_kitti_truth(kitti_root, tmp_path):
    assert times_beside(kitti_root / "poses" / "00.txt") == kitti_root / "sequences" / "00" / "times.txt"
    assert times_beside(kitti_root / "poses" / "01.txt") is None
    (tmp_path / "poses.txt").write_text("")
    (tmp_path / "times.txt").write_text("0\n")  # a plvo folder dataset: poses.txt and times.txt side by side
    assert times_beside(tmp_path / "poses.txt") == tmp_path / "times.txt"


# ---- several runs -------------------------------------------------------------------------------------------------

def test_several_runs_a_row_each(kitti_root, tmp_path, capsys):
    gt = kitti_root / "poses" / "00.txt"
    a = results_folder(tmp_path / "results" / "a", range(0, 51))
    b = results_folder(tmp_path / "results" / "b", range(20, 150), est=noisy_estimate(GT, seed=2, scale=0.98))
    write_poses(tmp_path / "other.txt", EST, TIMES, "tum")
    runs = ["--est", a, "--est", b, "--est", tmp_path / "other.txt"]
    singles = [_json(capsys, "--gt", gt, "--est", e) for e in (a, b, tmp_path / "other.txt")]
    listed = _json(capsys, "--gt", gt, *runs)
    assert isinstance(listed, list) and [r["name"] for r in listed] == ["a", "b", "other"]
    for one, row in zip(singles, listed):
        assert one == row
    capsys.readouterr()
    assert main(["eval", "metric", "--gt", str(gt), *map(str, runs)]) == 0
    lines = capsys.readouterr().out.splitlines()
    head = lines[0].split()
    assert head[:4] == ["run", "frames", "ATE", "SE3"] and "devkit" in head and "heading" in head
    for line, one in zip(lines[1:4], singles):
        cells = line.split()
        assert cells[0] == one["name"] and int(cells[1]) == one["n_frames"]
        assert float(cells[2]) == pytest.approx(one["ate_m"], abs=5e-5)
        assert float(cells[4]) == pytest.approx(one["short"]["10"]["t_err_pct"], abs=5e-4)
    assert lines[4].startswith("3 runs")
    assert sum(line.startswith(f"  {name}: ") for line in lines for name in ("a", "b", "other")) == 3
    # the devkit columns: only b and other are longer than 100 m
    assert lines[1].split()[-3] == "-" and lines[2].split()[-3] != "-"
    # every folder with its own truth.txt, no --gt
    own = _json(capsys, "--est", a, "--est", b)
    assert [r["gt"] for r in own] == [str(a / "truth.txt"), str(b / "truth.txt")]


def test_runs_of_one_name_are_told_apart_by_path(tmp_path, capsys):
    for sub in ("x", "y"):
        write_poses(tmp_path / sub / "poses.txt", EST[:40], TIMES[:40], "kitti")
    write_poses(tmp_path / "gt.txt", GT[:40], TIMES[:40], "kitti")
    out = _json(capsys, "--gt", tmp_path / "gt.txt", "--est", tmp_path / "x" / "poses.txt",
                "--est", tmp_path / "y" / "poses.txt")
    assert [r["name"] for r in out] == [str(tmp_path / "x" / "poses.txt"), str(tmp_path / "y" / "poses.txt")]


def test_a_single_kitti_pair_prints_the_table_as_before(tmp_path, capsys):
    write_poses(tmp_path / "gt.txt", GT, TIMES, "kitti")
    write_poses(tmp_path / "est.txt", EST, TIMES, "kitti")
    capsys.readouterr()
    assert main(["eval", "metric", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt")]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"ground truth {tmp_path / 'gt.txt'}, estimate {tmp_path / 'est.txt'}: {N} frames")


def test_help_imports_no_numpy_plotting_or_scipy():
    """`plvo eval metric --help` builds the metric's parser: that pulls no numpy, matplotlib or scipy in, nor does
    importing the eval command."""
    code = ("import sys, argparse; from plvo_app import cmd_eval, eval_metric; "
            "eval_metric.add_metric_arguments(argparse.ArgumentParser()); "
            "print(sorted(m for m in ('numpy', 'matplotlib', 'scipy', 'plvo_eval.associate') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "[]"
