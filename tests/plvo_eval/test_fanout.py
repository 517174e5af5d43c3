"""The Ray fan-out on a local Ray cluster (2 CPUs): one task per sequence and setting, results gathered into the
same tables as the in-process run, and Ray shut down afterwards."""

from __future__ import annotations

import pytest
from eval_scene import write_box_sequence

from plvo_eval.report import build_report, report_json
from plvo_eval.runner import SequenceSource, build_specs, execute, kiss_threads, with_threads

ray = pytest.importorskip("ray", reason="ray is not installed")


def test_ray_local_matches_in_process(tmp_path):
    root = tmp_path / "data"
    write_box_sequence(root, "a", n_frames=20, speed_mps=10.0, seed=0)
    write_box_sequence(root, "b", n_frames=20, speed_mps=7.0, seed=1)
    sources = [SequenceSource(str(root), "a"), SequenceSource(str(root), "b")]
    specs = with_threads(build_specs(sources, [], kiss=True), kiss_threads(2, "local"))
    local = report_json(build_report(execute(specs, tmp_path / "local", workers=1)))
    assert not ray.is_initialized()
    try:
        results = execute(specs, tmp_path / "ray", workers=2, ray="local")
    finally:
        if ray.is_initialized():  # execute shuts down the Ray it started; make sure even on failure
            ray.shutdown()
    assert not ray.is_initialized()
    assert [r.status for r in results] == ["ok", "ok"]
    assert [r.folder.parent.parent.parent.name for r in results] == ["ray", "ray"]
    remote = report_json(build_report(results))
    assert remote["sequences"] == ["a", "b"] and remote["settings"] == ["kiss"]
    for seq in ("a", "b", "all"):
        # the same single-threaded KISS-ICP on the same scans: equal figures
        assert remote["short_t_err_pct"]["kiss"][seq] == pytest.approx(local["short_t_err_pct"]["kiss"][seq], abs=1e-6)
    assert (tmp_path / "ray" / "runs" / "kiss" / "b" / "poses.txt").is_file()


def test_an_address_where_no_cluster_listens_is_one_line(tmp_path, capsys):
    """`--ray HOST:PORT` with nothing there used to wait ~2 minutes with Ray's retry lines (and half a minute more
    after SIGTERM); now a connection is tried for at most CONNECT_SECONDS first, and refused in one line."""
    import socket

    from faults_table import fault, one_error_line

    from plvo_app.cli import main

    row = fault("ray-no-cluster")
    root = tmp_path / "data"
    write_box_sequence(root, "a", n_frames=5, speed_mps=10.0, seed=0)
    with socket.socket() as s:  # a port nothing listens on: bound, never listening
        s.bind(("127.0.0.1", 0))
        address = f"127.0.0.1:{s.getsockname()[1]}"
        out = tmp_path / "out"
        assert main(["eval", "run", "--synth", str(root), "--ablations", "none", "--kiss", "--no-plots",
                     "--out", str(out), "--ray", address]) == row.exit
    line = one_error_line(capsys.readouterr().err)
    assert row.message in line and address in line and "connection refused" in line.lower(), line
    assert not (out / "runs").exists() and not ray.is_initialized()
