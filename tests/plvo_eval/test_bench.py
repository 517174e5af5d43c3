"""`plvo bench`: stable JSON keys with positive figures, atomic output, one-line errors (exit 2).

These check the bench's bookkeeping on a few frames, never the speed itself (the design: speed is measured by
`plvo bench`, not by timed tests).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from plvo.errors import ConfigError
from plvo_app import cmd_bench
from plvo_app.cli import main
from plvo_eval.bench import BUDGET_MS, parse_stages, stage_stats

STAT_KEYS = {"source", "n", "median_ms", "p90_ms", "mean_ms", "max_ms", "budget_ms", "within_budget"}


def test_stage_stats_figures_and_budget():
    s = stage_stats([k * 1e-3 for k in range(1, 11)], budget_ms=5.0)  # 1..10 ms
    assert set(s) == STAT_KEYS and s["n"] == 10 and s["source"] == "isolated"
    assert s["median_ms"] == pytest.approx(5.5) and s["mean_ms"] == pytest.approx(5.5)
    assert s["p90_ms"] == pytest.approx(9.1) and s["max_ms"] == pytest.approx(10.0)
    assert s["within_budget"] is False  # the median 5.5 ms is over 5 ms
    assert stage_stats([0.004], budget_ms=5.0)["within_budget"] is True
    empty = stage_stats([], budget_ms=5.0, source="system")
    assert empty["n"] == 0 and empty["median_ms"] is None and empty["within_budget"] is None


def test_parse_stages():
    assert parse_stages("all") == parse_stages("features,matching,depth,registration,backend,loop,system")
    assert parse_stages(" depth , features") == {"depth", "features"}
    with pytest.raises(ConfigError, match="unknown stage.*pnp"):
        parse_stages("features,pnp")


def _spy_atomic(monkeypatch) -> list:
    calls = []
    real = cmd_bench.write_text_atomic

    def spy(path, text):
        calls.append(path)
        real(path, text)

    monkeypatch.setattr(cmd_bench, "write_text_atomic", spy)
    return calls


def test_isolated_stages_on_real_frames(kitti_root, tmp_path, monkeypatch, capsys):
    out = tmp_path / "res" / "bench.json"
    calls = _spy_atomic(monkeypatch)
    assert main(["bench", "--root", str(kitti_root), "--seq", "04", "--frames", "0:4", "--out", str(out),
                 "--stages", "features,matching,depth,registration"]) == 0
    assert calls == [out]
    assert [p.name for p in out.parent.iterdir()] == ["bench.json"]  # no temporary file left beside it
    r = json.loads(out.read_text())
    assert {"schema", "created_utc", "command_line", "git_revision", "versions", "machine", "input", "stages",
            "memory", "config", "duration_s", "provenance"} <= set(r)
    prov = r["provenance"]
    assert prov["command_line"] == r["command_line"] and prov["machine"]["cpu_count"] >= 1
    assert len(prov["load_start"]) == 3 and len(prov["load_end"]) == 3 and prov["finished_utc"] >= prov["started_utc"]
    assert {"revision", "dirty", "plvo_version", "machine"} <= set(prov)
    assert r["input"]["n_frames"] == 4 and r["input"]["image_size"] == [1226, 370]
    assert r["input"]["scan_points_median"] > 100_000 and r["input"]["registration"]["init"] == "ground truth"
    expect_n = {"features": 4, "features_1241x376": 4, "features_orb": 4, "features_lsd": 4, "features_repair": 4,
                "features_lbd": 4, "matching": 3, "depth": 2, "registration": 1}  # depth at frames 0, 3
    assert set(r["stages"]) == set(expect_n)
    for name, n in expect_n.items():
        s = r["stages"][name]
        assert set(s) == STAT_KEYS and s["n"] == n and s["source"] == "isolated", name
        assert 0 < s["median_ms"] <= s["p90_ms"] <= s["max_ms"], name
        assert s["budget_ms"] == BUDGET_MS.get(name), name
        assert isinstance(s["within_budget"], bool) == (name in BUDGET_MS), name
    assert "system" not in r  # no whole run was asked for
    assert r["memory"]["ru_maxrss_mb"] > 100 and r["memory"]["isolated_stages"]["peak_mb"] > 100
    m = r["machine"]
    assert m["cpu_count"] >= 1 and len(m["load_avg_start"]) == 3 and len(m["load_avg_end"]) == 3
    assert "OPENBLAS_NUM_THREADS" in m["threads"] and r["versions"]["numpy"] and r["versions"]["gtsam"]
    assert "features" in capsys.readouterr().out  # the human table


def test_whole_system_with_and_without_recording(synth_seq, tmp_path):
    out = tmp_path / "sys.json"
    assert main(["bench", "--synth", str(synth_seq), "--frames", "0:6", "--out", str(out),
                 "--stages", "system"]) == 0
    r = json.loads(out.read_text())
    assert r["input"]["dataset"] == "kitti_odometry" and r["input"]["n_frames"] == 6
    sysr = r["system"]
    assert sysr["backend_concurrent"] is True
    off, on = sysr["recording_off"]["runs"][0], sysr["recording_on"]["runs"][0]
    for run in (off, on):
        assert run["frames"] == 6 and run["n_keyframes"] >= 2 and run["cpu_s"] > 0
        assert run["fps"] == pytest.approx(6 / run["wall_s"], rel=1e-2)
    assert sysr["recording_off"]["fps"] == off["fps"] and sysr["recording_off"]["fps_budget"] == 10.0
    assert on["rrd_bytes"] > 10_000 and sysr["recording_on"]["rrd_bytes_per_frame"] == round(on["rrd_bytes"] / 6)
    assert on["recording_ms_per_frame"] > off["recording_ms_per_frame"]  # Rerun encodes; the null recorder not
    assert on["recording_pct_of_step"] > off["recording_pct_of_step"] >= 0
    assert sysr["recording_overhead_pct"] == pytest.approx(100 * (off["fps"] / on["fps"] - 1), abs=0.5)
    assert isinstance(sysr["recording_overhead_within_budget"], bool)
    for name in ("pnpl", "matching_pnpl", "bundle_adjustment", "scale_correction_ba", "backend", "loop"):
        s = r["stages"][name]
        assert s["source"] == "system" and s["n"] >= 1 and s["median_ms"] > 0, name
    assert r["stages"]["matching_pnpl"]["n"] == 5 and r["stages"]["matching_pnpl"]["budget_ms"] == 15.0
    assert "features" not in r["stages"]  # isolated stages were not asked for
    assert {"tracking", "total", "features"} <= set(sysr["stages_recording_off"])
    assert r["memory"]["system_recording_on"]["peak_mb"] > 100
    # What a user gets from plvo-viz (from disk, recording on), with KISS-ICP on the same scans beside it
    dep = r["deployed"]
    assert dep["fresh_processes"] is True  # each run in a new process, as a user runs plvo-viz
    assert dep["runs"][0]["frames"] == 6 and dep["runs"][0]["recording"] and dep["runs"][0]["rrd_bytes"] > 10_000
    assert dep["fps"] == pytest.approx(6 / dep["runs"][0]["wall_s"], rel=1e-2)
    # set-up is outside the clock and reported apart: it holds the wait for the workers' start-up
    assert dep["setup_s"] == dep["runs"][0]["setup_s"] > dep["runs"][0]["workers_ready_s"] > 0
    pair = dep["pairs"][0]
    assert pair["plvo_fps"] == dep["fps"] and pair["plvo_setup_s"] == dep["setup_s"]
    kiss = dep["kiss_icp_runs"][0]
    assert kiss is not None, "kiss-icp is in the compare extra that make test installs"
    assert kiss["frames"] == 6 and kiss["fps"] == pytest.approx(6 / kiss["wall_s"], rel=1e-2)
    assert kiss["setup_s"] > 0 and pair["kiss_icp_setup_s"] == kiss["setup_s"] == dep["kiss_icp_setup_s"]
    assert dep["kiss_icp_fps"] == kiss["fps"] == pair["kiss_icp_fps"]
    assert dep["at_least_kiss_icp"] == (dep["fps"] >= dep["kiss_icp_fps"])
    assert pair["ratio"] == pytest.approx(dep["fps"] / kiss["fps"], rel=1e-2)
    assert dep["ratio_to_kiss_icp"] == pair["ratio"] and dep["ratio_to_kiss_icp_runs"] == [pair["ratio"]]
    assert dep["ratio_to_kiss_icp_interval"] is None  # one run: no interval
    # the CPU of every process: the worker processes (back end, loop closer) did the keyframes' work
    run = dep["runs"][0]
    assert run["workers_cpu_ms_per_frame"] > 0
    assert run["all_processes_cpu_ms_per_frame"] == pytest.approx(
        run["cpu_ms_per_frame"] + run["workers_cpu_ms_per_frame"], abs=0.02)
    # bytes a frame of each recording level, from one run recorded at all three
    levels = r["recording_levels"]
    assert set(levels) == {"summary", "default", "full"}
    assert levels["summary"]["bytes"] <= levels["default"]["bytes"] <= levels["full"]["bytes"]
    assert all(v["frames"] == 6 and v["bytes_per_frame"] > 0 for v in levels.values())


def test_missing_root_is_one_line_error(tmp_path, capsys):
    out = tmp_path / "never.json"
    assert main(["bench", "--root", str(tmp_path / "nowhere"), "--stages", "features", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "nowhere" in err and "\n" not in err
    assert not out.exists()


def test_bad_stage_name_is_one_line_error(tmp_path, capsys):
    assert main(["bench", "--root", str(tmp_path), "--stages", "features,warp"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "warp" in err and "\n" not in err


def test_loop_correction_figures_count_only_corrections():
    """The loop worker times every keyframe; the correction stages are zero unless a loop was accepted, and their
    figures are over the corrections alone (none at all on a sequence without a revisit)."""
    from plvo_eval.bench import SystemRun, system_stages

    timings = {"loop_query": [0.001, 0.002, 0.003], "loop_correct": [0.0, 0.004, 0.0],
               "loop_global_ba": [0.0, 0.5, 0.0], "loop_apply": [0.0, 0.0, 0.0]}
    run = SystemRun(False, 3, 1.0, 1.0, 3, 0, (0.0,), (0.0,), {}, [], timings)
    out = system_stages([run])
    assert out["loop_query"]["n"] == 3 and out["loop_query"]["median_ms"] == pytest.approx(2.0)
    assert out["loop_correct"]["n"] == 1 and out["loop_correct"]["median_ms"] == pytest.approx(4.0)
    assert out["loop_global_ba"]["median_ms"] == pytest.approx(500.0)
    assert out["loop_apply"]["n"] == 0 and out["loop_apply"]["median_ms"] is None


def test_deployed_runs_come_before_the_frames_are_preloaded(synth_seq, monkeypatch):
    """The deployed figure is plvo-viz's: measured while the bench's process holds no preloaded frames (with the 51
    frames of 04 in memory every process of the run took ~10 % more CPU), i.e. before load_frames."""
    from plvo.config import SystemConfig
    from plvo.data.registry import open_dataset
    from plvo_eval import bench

    order = []
    real_load = bench.load_frames
    monkeypatch.setattr(bench, "deployed_figures", lambda *a, **k: order.append("deployed") or {"fps": 1.0})
    monkeypatch.setattr(bench, "load_frames", lambda ds: order.append("load") or real_load(ds))
    fake_run = type("Run", (), {"rss": {"peak_mb": 1.0}})()
    monkeypatch.setattr(bench, "system_runs", lambda *a, **k: ([fake_run], []))
    monkeypatch.setattr(bench, "system_figures", lambda off, on: {})
    monkeypatch.setattr(bench, "system_stages", lambda runs: {})
    dataset = open_dataset(synth_seq, None, slice(0, 3))
    report = bench.run_bench(dataset, SystemConfig(), frozenset({"system"}), 1, lambda run: (None, None))
    assert order == ["deployed", "load"] and report["deployed"] == {"fps": 1.0}


def _pid_and_module_count() -> tuple[int, int]:
    import os
    import sys

    return os.getpid(), len(sys.modules)


def _fails() -> None:
    raise ValueError("no scans")


def test_a_fresh_process_runs_the_call_and_reports_its_failure_in_one_line():
    import os

    from plvo_eval.bench import in_fresh_process

    pid, _ = in_fresh_process(_pid_and_module_count)
    assert pid != os.getpid()
    with pytest.raises(RuntimeError, match=r"^bench: _fails in a fresh process failed: ValueError: no scans"):
        in_fresh_process(_fails)


class _SlowScans:
    """A KITTI dataset whose scans take 50 ms each to read and whose images cannot be read at all."""

    def __init__(self, dataset):
        self.inner = dataset
        self.sequence, self.calib, self.frame_indices = dataset.sequence, dataset.calib, dataset.frame_indices

    def __len__(self) -> int:
        return len(self.inner)

    def __getitem__(self, i):
        raise AssertionError("KISS-ICP decoded a camera image")

    def load_scan(self, i):
        import time

        time.sleep(0.05)
        return self.inner.load_scan(i)


def test_kiss_icp_reads_the_scans_alone_inside_its_clock_and_its_setup_apart(synth_seq):
    """As plvo's: the clock runs from the first scan read (from disk, images never decoded) to the last pose;
    what came before it (here 0.3 s, standing for opening the dataset) is setup_s."""
    import time

    from plvo.data.registry import open_dataset
    from plvo_eval.bench import kiss_run

    dataset = _SlowScans(open_dataset(synth_seq, None, slice(0, 4)))
    started = time.perf_counter()
    time.sleep(0.3)
    k = kiss_run(dataset, setup_started=started)
    total = time.perf_counter() - started
    assert k is not None and k.frames == 4
    assert k.wall_s >= 4 * 0.05  # the reads are timed
    assert k.setup_s >= 0.3 and k.setup_s + k.wall_s <= total  # the set-up is not, and is counted apart
    assert k.fps == pytest.approx(4 / k.wall_s)


def test_the_kitti_scan_reader_is_the_frames_scan(synth_seq):
    import numpy as np

    from plvo.data.registry import open_dataset
    from plvo_eval.kiss import scan_reader

    dataset = open_dataset(synth_seq, None, slice(2, 5))
    read = scan_reader(dataset)
    np.testing.assert_array_equal(read(1), dataset[1].scan)
    np.testing.assert_array_equal(read(-1), dataset[2].scan)


def test_the_bench_records_with_the_input_files_as_plvo_viz_does(kitti_root, tmp_path, monkeypatch):
    """plvo-viz's recorder digests every frame's image and scan file (plvo_app.run_identity); the bench's recorded
    runs stand for plvo-viz, so their RunInfo names the same files and the recorder digests them too."""
    from plvo.data.registry import open_dataset
    from plvo_app.run_identity import input_files

    seen = {}

    def capture(dataset, cfg, stages, repeat, factory, info, reopen):
        seen["info"] = info
        raise KeyboardInterrupt  # stop before any run: only what the runs would be given is checked

    monkeypatch.setattr(cmd_bench, "run_bench", capture)
    out = tmp_path / "b.json"
    code = main(["bench", "--root", str(kitti_root), "--seq", "04", "--frames", "0:3", "--out", str(out)])
    assert code != 0 and not out.exists()  # interrupted: no result that looks complete
    files = seen["info"].extra["input_files"]
    assert files == input_files(open_dataset(kitti_root, "04", range(3))) and len(files) == 3
    assert all(f.endswith(".png") and s.endswith(".bin") for f, s in files.values())


def test_the_ratio_s_interval_says_what_a_bench_resolves():
    """The geometric mean of the run-by-run ratios with a bootstrap interval: none from fewer than 3 runs, a point
    where every run agrees, and narrower the more runs there are of the same spread."""
    import numpy as np

    from plvo_eval.bench import ratio_interval

    assert ratio_interval([0.9, 1.1]) is None
    same = ratio_interval([0.9] * 7)
    assert same == {"geomean": 0.9, "low": 0.9, "high": 0.9, "level": 0.9}
    spread = list(0.9 * np.exp(np.linspace(-0.15, 0.15, 21)))
    few, many = ratio_interval(spread), ratio_interval(spread * 4)
    assert few["geomean"] == many["geomean"] == 0.9
    assert few["low"] < many["low"] < 0.9 < many["high"] < few["high"]
    assert ratio_interval(spread) == few  # the same runs, the same figures


def test_the_bench_table_gives_the_ratio_s_interval():
    """The summary printed after a bench carries the interval, here for a committed bench's 21 runs (their ratios
    are in the file; the interval was added to the report after it was written)."""
    from plvo_eval.bench import ratio_interval

    report = json.loads((Path(__file__).parents[2] / "docs/results/bench/04_252c0a2_21.json").read_text())
    dep = report["deployed"]
    dep["ratio_to_kiss_icp_interval"] = ratio_interval(dep["ratio_to_kiss_icp_runs"])
    text = cmd_bench.format_table(report)
    assert "ratio, run by run, median 0.88 (medians of 21 runs)" in text
    assert "ratio's geometric mean 0.887, 90 % bootstrap interval 0.856-0.919" in text
