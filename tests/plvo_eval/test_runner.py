"""`plvo eval run` end to end on two tiny synthetic sequences: table shape, numbers equal to `plvo eval metric` on
the same files, local process fan-out, ablation columns, failed runs recorded, resume."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from eval_scene import write_box_sequence

from plvo.data.dataset import Dataset
from plvo.errors import PlvoError
from plvo_app.cli import main
from plvo_eval import tasks
from plvo_eval.report import build_report, report_json
from plvo_eval.runner import RunSpec, SequenceSource, build_specs, execute


@pytest.fixture(scope="module")
def boxes_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("boxes")
    write_box_sequence(root, "a", n_frames=30, speed_mps=10.0, seed=0)
    write_box_sequence(root, "b", n_frames=30, speed_mps=7.0, seed=1)
    return root


def _metric_json(gt, est, capsys) -> dict:
    capsys.readouterr()
    assert main(["eval", "metric", "--gt", str(gt), "--est", str(est), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_eval_run_kiss_two_sequences_matches_metric(boxes_root, tmp_path, capsys):
    out = tmp_path / "out"
    # two workers: the local process pool path
    code = main(["eval", "run", "--synth", str(boxes_root), "--ablations", "none", "--kiss",
                 "--out", str(out), "--workers", "2"])
    assert code == 0
    data = json.loads((out / "report.json").read_text())
    assert data["settings"] == ["kiss"] and data["sequences"] == ["a", "b"]
    for key in ("t_err_pct", "r_err_deg_per_m", "short_t_err_pct", "short_r_err_deg_per_m"):
        assert set(data[key]["kiss"]) == {"a", "b", "all", "mean"}
    # 29 m and 20 m: no 100 m devkit segment, so the devkit cells are empty and the short ones filled
    assert data["t_err_pct"]["kiss"]["a"] is None
    for seq in ("a", "b"):
        folder = out / "runs" / "kiss" / seq
        ref = _metric_json(folder / "gt.txt", folder / "poses.txt", capsys)
        assert data["short_t_err_pct"]["kiss"][seq] == pytest.approx(ref["short_t_err_pct"], rel=1e-9)
        assert data["short_r_err_deg_per_m"]["kiss"][seq] == pytest.approx(ref["short_r_err_deg_per_m"], rel=1e-9)
        assert data["ate_m"]["kiss"][seq] == pytest.approx(ref["ate_m"], rel=1e-9)
        result = json.loads((folder / "result.json").read_text())
        assert result["status"] == "ok" and result["n_frames"] == 30
        assert result["metrics"]["short_t_err_pct"] == pytest.approx(ref["short_t_err_pct"], rel=1e-9)
        # KISS-ICP tracks this cluttered street: a few % at most over 10-20 m
        assert ref["short_t_err_pct"] < 3.0
    mean = np.mean([data["short_t_err_pct"]["kiss"][s] for s in ("a", "b")])
    assert data["short_t_err_pct"]["kiss"]["mean"] == pytest.approx(mean)
    lo, hi = sorted(data["short_t_err_pct"]["kiss"][s] for s in ("a", "b"))
    assert lo <= data["short_t_err_pct"]["kiss"]["all"] <= hi  # pooled segments: between the two
    for png in ("trajectory_a.png", "trajectory_b.png", "error_by_length.png", "error_by_speed.png"):
        assert (out / "plots" / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "| a |" in (out / "report.md").read_text()
    assert not list(out.glob("runs/*/.*"))  # no temporary folder left behind


def _drifting(scale: float):
    def method(dataset: Dataset, spec: RunSpec) -> tasks.MethodOutput:
        gt = dataset.gt_T_world_cam
        est = gt.copy()
        est[:, :3, 3] *= scale
        return tasks.MethodOutput(est, {"tracking": [0.01] * len(gt)})

    return method


def test_ablation_columns_failures_and_resume(boxes_root, tmp_path, monkeypatch):
    """In-process fan-out with a stand-in for plvo (ground truth scaled by 1.02): every ablation is a column,
    KISS-ICP the last; a failing setting is recorded, not raised; --resume keeps finished folders unless their
    configuration changed."""
    monkeypatch.setitem(tasks.METHODS, "plvo", _drifting(1.02))
    sources = [SequenceSource(str(boxes_root), "a"), SequenceSource(str(boxes_root), "b", frames="0:20")]
    specs = build_specs(sources, ["full", "no_depth_priors", "no_scale_correction", "points_only"], kiss=True)
    assert len(specs) == 10
    results = execute(specs, tmp_path, workers=1)
    data = report_json(build_report(results))
    assert data["settings"] == ["full", "no_depth_priors", "no_scale_correction", "points_only", "kiss"]
    for setting in data["settings"][:4]:
        for seq in ("a", "b"):
            # a 2 % scale error reads as 2 % times the segment's overshoot of its nominal length (<= one step)
            assert 2.0 <= data["short_t_err_pct"][setting][seq] < 2.0 * 1.15
        assert data["tasks"][setting]["b"]["status"] == "ok"
    assert len(np.loadtxt(tmp_path / "runs" / "full" / "b" / "poses.txt")) == 20

    def broken(dataset, spec):
        raise PlvoError("stage X exploded")

    monkeypatch.setitem(tasks.METHODS, "plvo", broken)
    mtimes = {p: p.stat().st_mtime_ns for p in tmp_path.glob("runs/kiss/*/result.json")}
    again = execute(specs[:4] + specs[5:], tmp_path, workers=1, resume=True)  # finished ones kept
    assert all(r.ok for r in again)
    assert {p: p.stat().st_mtime_ns for p in tmp_path.glob("runs/kiss/*/result.json")} == mtimes
    # a run whose configuration is not what its ablation means now (an older version's) is not resumed
    used = tmp_path / "runs" / "no_scale_correction" / "a" / "config.toml"
    used.write_text(used.read_text().replace("registration = false", "registration = true", 1))
    stale = execute([specs[2]], tmp_path, workers=1, resume=True)
    assert stale[0].status == "failed" and "stage X exploded" in stale[0].error
    failed = execute([specs[0]], tmp_path, workers=1)  # not resumed: rerun, fails, replaces the folder
    assert failed[0].status == "failed" and "stage X exploded" in failed[0].error
    assert not (tmp_path / "runs" / "full" / "a" / "poses.txt").exists()
    report = report_json(build_report(failed + again[4:]))
    assert report["short_t_err_pct"]["full"]["a"] is None
    assert report["tasks"]["full"]["a"]["status"] == "failed"


def test_cli_errors(tmp_path, capsys):
    assert main(["eval", "run", "--out", str(tmp_path)]) == 2
    assert "no sequence to run" in capsys.readouterr().err
    assert main(["eval", "run", "--synth", str(tmp_path), "--ablations", "bogus", "--out", str(tmp_path)]) == 2
    assert "neither a root" in capsys.readouterr().err


@pytest.fixture(scope="module")
def town_root(tmp_path_factory):
    from plvo_synth import generate_sequence

    root = tmp_path_factory.mktemp("town")
    generate_sequence(root, "01", n_frames=24, seed=3, speed_mps=10.0)
    generate_sequence(root, "02", n_frames=24, seed=4, speed_mps=8.0)
    return root


def test_eval_run_plvo_on_two_synthetic_town_sequences_matches_metric(town_root, tmp_path, capsys):
    """The real pipeline under two ablations over two tiny synthetic town sequences: Table I's shape (a row a
    sequence plus the pooled and mean rows, a column a setting), every cell equal to `plvo eval metric` on the
    task's own files, and errors a working tracker gives (<= 2 % over 10 m on 23 and 18 m of street)."""
    out = tmp_path / "out"
    code = main(["eval", "run", "--synth", str(town_root), "--ablations", "full,points_only", "--out", str(out),
                 "--workers", "1", "--no-plots", "--set", "backend.concurrent=false"])
    assert code == 0
    data = json.loads((out / "report.json").read_text())
    assert data["settings"] == ["full", "points_only"] and data["sequences"] == ["01", "02"]
    md = (out / "report.md").read_text()
    for setting in ("full", "points_only"):
        assert set(data["short_t_err_pct"][setting]) == {"01", "02", "all", "mean"}
        for seq in ("01", "02"):
            folder = out / "runs" / setting / seq
            ref = _metric_json(folder / "gt.txt", folder / "poses.txt", capsys)
            for key in ("short_t_err_pct", "short_r_err_deg_per_m", "ate_m"):
                assert data[key][setting][seq] == pytest.approx(ref[key], rel=1e-9), (setting, seq, key)
            assert len(np.loadtxt(folder / "poses.txt")) == 24
            assert ref["short_t_err_pct"] < 2.0, (setting, seq, ref["short_t_err_pct"])
            assert f"{ref['short_t_err_pct']:.2f}" in md



_POOL_SCRIPT = """
import os, sys, time
from plvo_eval.runner import worker_pool
if __name__ == "__main__":
    pool = worker_pool(1)
    print(pool.submit(os.getpid).result(), flush=True)
    pool.submit(time.sleep, 120)
    time.sleep(120)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the workers' parent-death signal is Linux's prctl")
def test_killed_eval_run_takes_its_workers_along(tmp_path):
    """A `plvo eval run` killed mid-sweep must not leave its pool workers running their sequences to the end (they
    did: two cores busy for minutes after the sweep was gone). The sweep's own pool, a worker in a long task."""
    script = tmp_path / "sweep.py"
    script.write_text(_POOL_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        worker = int(proc.stdout.readline())
        time.sleep(1.0)  # the worker is inside its long task
        assert Path(f"/proc/{worker}").exists()
        proc.kill()
        proc.wait()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and Path(f"/proc/{worker}").exists():
            time.sleep(0.1)
        assert not Path(f"/proc/{worker}").exists(), "the pool worker outlived the killed sweep"
    finally:
        proc.kill()
