"""plvo-viz end to end on the real frames 3:10 of KITTI 04 (one run shared by the module): the .rrd holds every
entity of the design's table the pipeline produces, at the frames it belongs to; poses.txt is written and close to
the ground truth; Ctrl-C keeps a readable recording; bad input is a one-line error; no dataset means the synthetic
town; the library imports no viewer."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from faults_table import VIZ, read_stderr_until

from plvo_app.rrd_reader import read_rrd
from plvo_app.viz_options import VizOptions

REPO = Path(__file__).resolve().parents[2]
FRAMES = list(range(3, 10))


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("KITTI_ROOT", None)
    env["PYTHONPATH"] = f"{REPO}{os.pathsep}{env.get('PYTHONPATH', '')}"
    return env


def viz(args: list[str], cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(VIZ + args, cwd=cwd, env=_env(), capture_output=True, text=True, timeout=timeout)


def _outputs(cwd: Path, stderr: str) -> tuple[Path, Path]:
    rrd = re.search(r"^recording: (\S+)$", stderr, re.M).group(1)
    out = re.search(r"^results: +(\S+?)/?$", stderr, re.M).group(1)
    return cwd / rrd, cwd / out


@pytest.fixture(scope="module")
def kitti_run(kitti_root, tmp_path_factory):
    cwd = tmp_path_factory.mktemp("viz")
    proc = viz(["--root", str(kitti_root), "--seq", "04", "--frames", "3:10", "--no-serve", "--record", "full"], cwd)
    assert proc.returncode == 0, proc.stderr
    rrd, out = _outputs(cwd, proc.stderr)
    return cwd, proc, rrd, out


@pytest.fixture(scope="module")
def recording(kitti_run):
    return read_rrd(kitti_run[2])


def _keyframes(data) -> list[int]:
    """The frames the log says became keyframes (the tracker decides; the test checks every entity against it)."""
    return sorted({f for f, _, text in data.log if re.match(rf"frame {f}: keyframe \d+ \(", text)})


def test_recording_holds_every_entity_the_pipeline_produces(recording):
    data, frames = recording, FRAMES
    kfs = _keyframes(data)
    assert kfs[0] == 3 and 2 <= len(kfs) <= 5, kfs  # the first frame, then one every 3-4 frames
    expect = {e: frames for e in ("camera", "camera/image", "camera/image/orb", "camera/image/lsd_merged",
                                  "camera/image/tracked_points", "camera/image/tracked_lines")}
    # per keyframe: the tracker's and the depth stage's debug layers, and (placed at their keyframe's frame although
    # the threaded back end delivers them later) the back end's map and graph
    expect.update({e: kfs for e in ("camera/image/lsd_raw", "camera/image/lidar", "camera/image/patches",
                                    "camera/image/line_patches", "lidar", "lidar/scan", "depth/points",
                                    "depth/lines", "depth/planes", "map/points", "map/lines")})
    expect.update({"graph": kfs[1:], "keyframes": sorted(set(kfs) | {frames[-1]}),
                   "trajectory/est": sorted(set(kfs[1:]) | {frames[-1]})})
    for entity, want in expect.items():
        assert data.frames(f"/world/{entity}") == want, entity
    assert "/world/loops" not in data.entities  # no loop in 7 frames (tests/plvo_app/test_rerun_recorder.py has one)
    for series, want in {"time/total": frames, "time/recording": frames, "tracking/point_inliers": frames,
                         "tracking/line_inliers": frames, "features/points": frames, "depth/point_priors": kfs,
                         "backend/scale_factor": kfs, "backend/zeta": kfs[1:], "map/points": kfs,
                         "loop/candidates": kfs}.items():
        assert data.frames(f"/metrics/{series}") == want, series
    assert {"/world", "/world/camera/image", "/world/trajectory/gt"} <= set(data.static)
    assert sum(1 for f, _, t in data.log if "keyframe" in t) == len(kfs)


def test_recording_contents_are_sane(recording, kitti_root):
    data = recording
    inliers = [row["Scalars:scalars"][0] for _, row in data.rows("/metrics/tracking/point_inliers")]
    assert min(inliers[1:]) >= 20, inliers  # every tracked frame keeps PnP inliers; they are drawn green
    f = FRAMES[2]
    colors = np.asarray(data.temporal["/world/camera/image/tracked_points"][f]["Points2D:colors"], np.uint32)
    assert ((colors >> 16) & 255 == 220).sum() == inliers[2]
    gt = np.asarray(data.static["/world/trajectory/gt"]["LineStrips3D:strips"][0])
    est = np.asarray(data.temporal["/world/trajectory/est"][FRAMES[-1]]["LineStrips3D:strips"][0])
    assert gt.shape == (7, 3) and np.allclose(gt[0], 0, atol=1e-6)  # moved into the estimate's world (frame 3)
    assert len(est) >= 7 and np.linalg.norm(est[-1] - gt[-1]) < 0.3
    props = data.properties
    assert props["plvo_run:status"] == "complete" and props["plvo_run:frames_done"] == 7
    assert "--frames 3:10" in props["plvo:command_line"] and "[orb]" in props["plvo:config"]
    assert props["plvo:git_revision"] and props["plvo:version"]


def test_poses_written_and_close_to_ground_truth(kitti_run, kitti_root):
    from plvo.data.registry import open_dataset
    from plvo.data.trajectory import read_kitti_poses

    _, proc, _, out = kitti_run
    lines = (out / "poses.txt").read_text().splitlines()
    assert len(lines) == len(FRAMES) and all(len(ln.split()) == 12 for ln in lines)
    est = read_kitti_poses(out / "poses.txt")
    gt = open_dataset(kitti_root, "04", slice(3, 10)).gt_T_world_cam
    gt = np.linalg.inv(gt[0]) @ gt  # KITTI's world is frame 0's cam0; the run's is frame 3's
    np.testing.assert_allclose(est[0], np.eye(4), atol=1e-9)
    path = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()
    err = np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1)
    assert path > 7 and err.max() < 0.02 * path, (err, path)
    timings = json.loads((out / "timings.json").read_text())
    assert timings["status"] == "complete" and timings["frames_done"] == 7
    assert timings["stages"]["total"]["runs"] == 7 and timings["frames_per_second"] > 0
    # the worker processes' start-up is waited for once, before the first frame (and the frames-a-second clock)
    assert timings["stages"]["workers_ready"]["runs"] == 1
    assert (out / "config.toml").read_text().startswith("[orb]")
    assert "frame/s" in proc.stderr or "s/frame" in proc.stderr  # the progress bar


def test_summary_scores_the_run_as_eval_metric_does(kitti_run, kitti_root):
    """The end of a run with truth: summary.json and the terminal's last lines hold the figures `plvo eval metric`
    gives for poses.txt against the sequence's own truth file cut to the frames run; truth.txt is that cut."""
    from plvo.data.trajectory import read_kitti_poses
    from plvo_eval.kitti_metric import evaluate_sequence

    cwd, proc, _, out = kitti_run
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "complete" and summary["frame_indices"] == FRAMES
    assert summary["truth_source"] == str(kitti_root / "poses" / "04.txt") and summary["truth"] == "truth.txt"
    whole = read_kitti_poses(kitti_root / "poses" / "04.txt")[FRAMES]  # 04's camera is cam0
    truth = read_kitti_poses(out / "truth.txt")
    np.testing.assert_allclose(truth, np.linalg.inv(whole[0]) @ whole, atol=1e-8)
    ev = evaluate_sequence(whole, read_kitti_poses(out / "poses.txt"))
    acc = summary["accuracy"]
    assert acc["ate_se3_m"] == pytest.approx(ev.ate_se3.rmse_m, abs=1e-4) and acc["ate_se3_m"] > 0
    assert acc["ate_sim3_m"] == pytest.approx(ev.ate_sim3.rmse_m, abs=1e-4)
    for e in ev.short.per_length:  # 7 frames (~9 m) hold no 10 m segment: no figure, null in the JSON
        got = acc["relative"][f"{e.length_m:g}m"]
        assert got["segments"] == e.n_segments and (
            got["t_err_pct"] is None if np.isnan(e.t_err_pct) else got["t_err_pct"] == pytest.approx(e.t_err_pct))
    assert acc["devkit"] is None  # 7 frames hold no 100 m segment, and it says so
    assert summary["frames_per_second"] > 0 and summary["tracked_share"] == 1.0
    last = proc.stderr.splitlines()[-7:]
    assert f"ATE {acc['ate_se3_m']:.3f} m after SE(3)" in "\n".join(last), last
    assert any(line.startswith("accuracy against the truth (") for line in last)
    assert "no figure (the path holds no 100 m segment)" in proc.stderr
    assert (cwd / "results" / "latest").resolve() == out.resolve()  # the newest run's folder
    assert last[-2] == "summary:   results/latest/summary.json" and last[-1].startswith("complete: 7 frames at ")


def test_second_run_never_overwrites(kitti_run, monkeypatch):
    """Two runs started in the same second get distinct recordings and results folders (in-process: the naming)."""

    from plvo_app import cmd_viz

    cwd, _, rrd, out = kitti_run
    monkeypatch.chdir(cwd)
    stamp = re.search(r"04_(\d{8}-\d{6})", rrd.name).group(1)
    monkeypatch.setattr(cmd_viz.time, "strftime", lambda fmt: stamp)
    args = VizOptions()  # no --rrd, no --out
    second, made = cmd_viz._outputs(args, "04")
    assert second.rrd.name == f"04_{stamp}-2.rrd" and second.out.name == f"04_{stamp}-2"
    assert (cwd / rrd.relative_to(cwd)).is_file() and (out / "poses.txt").is_file()
    # the results folder is claimed when named (made here, empty), so a third run started before the second
    # wrote anything gets a name of its own, and a run that stops early removes what it claimed
    assert made == [second.out] and second.out.is_dir() and not any(second.out.iterdir())
    third, _ = cmd_viz._outputs(args, "04")
    assert third.out.name == f"04_{stamp}-3" and third.rrd.name == f"04_{stamp}-3.rrd"
    cmd_viz.remove_made(made)
    assert not second.out.exists() and out.is_dir()


def test_default_recording_name_taken_meanwhile(tmp_path):
    """A default recording name taken between naming and writing (another run started in the same second): the
    recorder takes the next free name, and the other file is untouched; a name the user gave is never taken over."""
    import rerun as rr

    from plvo.errors import RecordingError
    from plvo_app.rrd_sink import RrdFileSink

    taken = tmp_path / "04_20261202-201804.rrd"
    taken.write_bytes(b"another run's")
    sink = RrdFileSink(rr.RecordingStream("plvo"), taken, next_free=True)
    sink.close()
    assert sink.path == tmp_path / "04_20261202-201804-2.rrd" and sink.path.stat().st_size > 0
    assert taken.read_bytes() == b"another run's"
    with pytest.raises(RecordingError, match="File exists"):
        RrdFileSink(rr.RecordingStream("plvo"), taken)


def test_ctrl_c_keeps_a_readable_recording(kitti_root, tmp_path):
    cmd = ["--root", str(kitti_root), "--seq", "04", "--no-serve", "--rrd", "cut.rrd", "--out", "out", "-v"]
    p = subprocess.Popen(VIZ + cmd, cwd=tmp_path, env=_env(), stderr=subprocess.PIPE, text=True)
    seen = read_stderr_until(p, "frame 3: keyframe")  # a few frames are in
    p.send_signal(signal.SIGINT)
    err = seen + p.stderr.read()
    assert p.wait(timeout=120) == 130, err
    data = read_rrd(tmp_path / "cut.rrd")
    done = data.properties["plvo_run:frames_done"]
    assert data.properties["plvo_run:status"] == "interrupted" and 3 <= done < 51
    assert data.frames("/world/camera") == list(range(done))  # the poses, sent as columns, flushed on close
    assert data.frames("/world/camera/image")[0] == 0  # the default level's detail on the first keyframe
    assert data.frames("/metrics/time/total") == list(range(done))  # the buffered scalars were flushed on close
    timings = json.loads((tmp_path / "out" / "timings.json").read_text())
    assert timings["status"] == "interrupted" and timings["frames_done"] == done
    assert not (tmp_path / "out" / "poses.txt").exists()
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())  # says how it ended, scores nothing
    assert summary["status"] == "interrupted" and summary["accuracy"] is None and summary["frames_done"] == done
    assert not (tmp_path / "out" / "truth.txt").exists() and not (tmp_path / "results").exists()
    assert not list(tmp_path.rglob("*.part"))  # no half-written file left behind
    assert "interrupted after" in err and "ATE" not in err


@pytest.mark.parametrize("args, message", [
    (["--root", "/nonexistent/kitti", "--seq", "04"], "/nonexistent/kitti"),
    (["--seq", "04", "--frames", "5:2"], "frames '5:2'"),
    (["--seq", "04", "--frames", "x:3"], "frames 'x:3'"),
    (["--seq", "04", "--config", "missing.toml"], "missing.toml"),
    (["--seq", "04", "--ablation", "nonsense"], "unknown ablation"),
])
def test_bad_input_one_line_error(kitti_root, tmp_path, monkeypatch, capsys, args, message):
    from plvo_app.cli import main_viz

    monkeypatch.delenv("KITTI_ROOT", raising=False)
    monkeypatch.chdir(tmp_path)
    if "--root" not in args:
        args = ["--root", str(kitti_root), *args]
    assert main_viz([*args, "--no-serve"]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if not ln.startswith("INFO")]
    assert len(lines) == 1 and lines[0].startswith("error:") and message in lines[0], lines
    assert not (tmp_path / "recordings").exists() and not (tmp_path / "results").exists()


def test_existing_rrd_is_refused(kitti_root, tmp_path, monkeypatch, capsys):
    from plvo_app.cli import main_viz

    monkeypatch.chdir(tmp_path)
    (tmp_path / "taken.rrd").write_bytes(b"")
    assert main_viz(["--root", str(kitti_root), "--seq", "04", "--frames", "0:2", "--no-serve",
                     "--rrd", "taken.rrd"]) == 2
    assert "already exists" in capsys.readouterr().err


def test_no_dataset_runs_the_synthetic_town(synth_seq, tmp_path, monkeypatch, capsys):
    """Dispatch only: the cache is pre-filled with the 20-frame test sequence under the default's key, so that
    nothing is generated; an empty cache is shown generating with a progress bar (the generator stubbed)."""
    import argparse

    from plvo_app import cmd_viz
    from plvo_synth import DEFAULT_SEQUENCE, DEFAULT_SETTINGS, cache

    monkeypatch.delenv("KITTI_ROOT", raising=False)
    monkeypatch.setenv("PLVO_CACHE", str(tmp_path / "cache"))
    parser = argparse.ArgumentParser()
    cmd_viz.add_arguments(parser)
    calls = []

    def fake_generate(progress=None, stop=None):
        calls.append(stop)
        for i in range(1, 4):
            progress(i, stop)
        return synth_seq

    monkeypatch.setattr("plvo_synth.default_sequence_root", fake_generate)
    dataset, label, _ = cmd_viz._open(VizOptions.from_args(parser.parse_args(["--frames", "0:5"])))
    err = capsys.readouterr().err
    assert calls == [5] and label == f"town{DEFAULT_SEQUENCE}" and len(dataset) == 5  # the frames asked, no more
    assert "no --root and no $KITTI_ROOT: running the synthetic town" in err and "generating frames 0..4" in err
    assert f"its ground truth: {tmp_path / 'cache'}" in err
    assert str(tmp_path / "cache") in err and "synthetic town:" in err  # where, and the progress bar

    monkeypatch.undo()
    monkeypatch.delenv("KITTI_ROOT", raising=False)
    monkeypatch.setenv("PLVO_CACHE", str(tmp_path / "cache"))
    key = cache.settings_hash(DEFAULT_SETTINGS, DEFAULT_SEQUENCE)
    (tmp_path / "cache" / "synth").mkdir(parents=True)
    (tmp_path / "cache" / "synth" / key).symlink_to(synth_seq, target_is_directory=True)
    dataset, label, _ = cmd_viz._open(VizOptions.from_args(parser.parse_args(["--frames", "0:20"])))
    err = capsys.readouterr().err
    assert len(dataset) == 20 and dataset.gt_T_world_cam is not None and "cached in" in err


def test_library_imports_no_viewer():
    code = ("import sys, plvo.runtime.system, plvo.recording, plvo.results; "
            "s = plvo.runtime.system.System(__import__('plvo.config').config.SystemConfig()); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('rerun', 'viser')))")
    out = subprocess.run([sys.executable, "-c", code], env=_env(), capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_the_last_line_says_an_extrinsic_found_and_what_was_done_with_it():
    """Started again with it: the correction and the frame; named only (restart_on_extrinsic off): what to state."""
    from plvo_app.cmd_viz import rig_line

    restarted = rig_line({"restarts": [{"reason": "camera-lidar extrinsic", "time_offset_s": 0.0, "at_frame": 16,
                                           "extrinsic_correction_deg": [-0.1205, -0.3429, 0.0788]}]})
    assert restarted == ("\ncamera-lidar extrinsic: turned by [-0.12, -0.34, +0.08] deg (found at frame 16); the run "
                         "started again from its first frame with it corrected")
    named = rig_line({"extrinsic": {"found": {"correction_deg": [-1.12, 0.66, -0.43],
                                                 "sigma_deg": [0.14, 0.31, 0.28]}}})
    assert "turned by [-1.12, +0.66, -0.43] deg (+- [0.14, 0.31, 0.28])" in named
    assert named.endswith("run again with crosscheck.extrinsic_correction_deg = [-1.12, +0.66, -0.43] composed with "
                          "the one stated")
    both = rig_line({"restarts": [{"reason": "camera-lidar time offset and camera-lidar extrinsic",
                                      "time_offset_s": 0.098, "at_frame": 26,
                                      "extrinsic_correction_deg": [1.0, 0.0, 0.0]}]})
    assert both.count("\n") == 2 and "0.098 s after the images" in both and "[+1.00, +0.00, +0.00]" in both
    assert rig_line({"extrinsic": {"found": None}, "time_offset": {"found": None}}) == ""
