"""Bad input refused at load with one line naming the field, file and line: config ranges, calibration, pose
matrices; results files 0644; a killed `plvo synth` leaves no staging folder for good."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from faults_table import fault, one_error_line

from plvo.config import ABLATIONS, SystemConfig, config_from_dict, load_config, with_ablation
from plvo.config_fields import ORDERED, bounded, check_ranges, numeric_fields
from plvo.errors import CalibrationError, ConfigError, TrajectoryError

REPO = Path(__file__).resolve().parents[3]


def _outside(key: str, value, bound: float, is_open: bool, below: bool):
    """A value just outside `bound` (the bound itself when open), of the field's type."""
    step = -1 if below else 1
    if isinstance(value, tuple):  # as long as the default (a rotation vector is three angles)
        return (_outside(key, value[0], bound, is_open, below),) * len(value)
    if isinstance(value, int):
        return int(bound) if is_open else int(bound) + step
    return float(bound) if is_open else float(bound) + step * 1e-6 * max(1.0, abs(bound))


def _nested(key: str, value) -> dict:
    section, name = key.split(".")
    return {section: {name: list(value) if isinstance(value, tuple) else value}}


def test_every_numeric_field_has_a_range_and_the_defaults_are_in_it():
    fields = numeric_fields(SystemConfig())
    assert len(fields) > 150 and all(f.valid is not None for f in fields.values()), \
        [k for k, f in fields.items() if f.valid is None]
    check_ranges(SystemConfig())
    for name in ABLATIONS:
        with_ablation(SystemConfig(), name)  # every ablation accepted


def test_each_fields_boundaries_are_refused_by_dotted_name():
    fields = numeric_fields(SystemConfig())
    checked = 0
    for key, decl in fields.items():
        value = decl.value
        assert decl.valid is not None, key
        rng = bounded(decl.valid, decl.unit, decl.is_int)
        assert math.isfinite(rng.lo) and math.isfinite(rng.hi), (key, rng)  # every field bounded both ways
        bounds = [(rng.lo, rng.lo_open, True), (rng.hi, rng.hi_open, False)]
        for bound, is_open, below in bounds:
            bad = _outside(key, value, bound, is_open, below)
            with pytest.raises(ConfigError, match=rf"config key '{key}' = .* is out of range"):
                config_from_dict(_nested(key, bad))
            checked += 1
        if isinstance(value, float):
            with pytest.raises(ConfigError, match=rf"'{key}' = nan is out of range"):
                config_from_dict(_nested(key, float("nan")))
        # the closed bound itself is accepted (unless an ordering with another field forbids it)
        for bound, is_open, _ in bounds:
            inside = type(value[0] if isinstance(value, tuple) else value)(bound)
            if not is_open and not any(key in pair for pair in ORDERED):
                config_from_dict(_nested(key, (inside,) * len(value) if isinstance(value, tuple) else inside))
    assert checked >= len(fields)


def test_choices_and_the_vocabulary_folder_are_checked_when_read(tmp_path):
    """Choice strings that only the code using them checked (registration.method and fallback, unused at the
    defaults' local map; zeta_formula), and a vocabulary folder first read by the loop closer's process: each
    is now refused when the config is read, naming the key."""
    row = fault("config-choice")
    assert row.exit == ConfigError.exit_status
    for section, key, value in (("registration", "method", "nd"), ("registration", "fallback", "off"),
                                ("registration", "zeta_formula", "inverted")):
        with pytest.raises(ConfigError, match=rf"'{section}.{key}' = '{value}' {row.message}"):
            config_from_dict({section: {key: value}})
    with pytest.raises(ConfigError, match=r"'loop.vocab_dir' = .*: no orb.npz or lbd.npz there"):
        config_from_dict({"loop": {"vocab_dir": str(tmp_path)}})
    with pytest.raises(ConfigError, match=r"'orb.n_features' = 1000000000 is out of range \(must be \[1, 1e\+08\]\)"):
        config_from_dict({"orb": {"n_features": 10**9}})
    with pytest.raises(ConfigError, match=r"'backend.worker_timeout_s' = 1e\+30 is out of range"):
        config_from_dict({"backend": {"worker_timeout_s": 1e30}})


def test_ordered_fields_are_refused_when_crossed():
    with pytest.raises(ConfigError, match=r"'orb.fast_threshold_min' = 30 must not exceed 'orb.fast_threshold'"):
        config_from_dict({"orb": {"fast_threshold_min": 30}})
    with pytest.raises(ConfigError, match=r"'registration.min_range_m'"):
        config_from_dict({"registration": {"min_range_m": 70.0}})


def test_config_out_of_range_is_one_line(tmp_path, capsys):
    row = fault("config-range")
    from plvo_app.cli import main

    bad = tmp_path / "bad.toml"
    bad.write_text("[orb]\nn_features = 0\n")
    with pytest.raises(ConfigError, match="orb.n_features"):
        load_config(bad)
    status = main(["run", "--config", str(bad), "--root", str(tmp_path / "none"), "--no-serve"])
    line = one_error_line(capsys.readouterr().err)
    assert status == row.exit and row.message in line and "orb.n_features" in line and str(bad) in line


# ---- calibration ------------------------------------------------------------------------------------------------

def _odometry_with_tr(root: Path, tr: str) -> Path:
    from kitti_layout import make_odometry

    seq_dir = make_odometry(root)
    lines = [ln for ln in (seq_dir / "calib.txt").read_text().splitlines() if not ln.startswith("Tr:")]
    (seq_dir / "calib.txt").write_text("\n".join([*lines, f"Tr: {tr}"]) + "\n")
    return seq_dir


def test_calibration_non_finite_is_named(tmp_path, capsys):
    row = fault("calib-nan")
    from plvo.data.kitti import KittiOdometry
    from plvo_app.cli import main

    _odometry_with_tr(tmp_path, " ".join(["nan"] + ["0"] * 11))
    with pytest.raises(CalibrationError, match=r"calib\.txt:5: 'Tr' holds NaN or infinite values"):
        KittiOdometry(tmp_path, "07")
    status = main(["run", "--root", str(tmp_path), "--seq", "07", "--no-serve"])
    line = one_error_line(capsys.readouterr().err)
    assert status == row.exit and row.message in line and "'Tr'" in line
    assert not (Path.cwd() / "recordings" / "07").exists()


@pytest.mark.parametrize("what", ["zero focal length", "singular Tr", "scaled Tr"])
def test_degenerate_calibration_is_named_where_it_is_read(tmp_path, capsys, what):
    """A calibration that parses but cannot be a camera and a rigid mounting used to pass the reading and end the
    run frames later as an unexpected error (or name the folder, not the file)."""
    row = fault("calib-degenerate")
    from plvo.data.kitti import KittiOdometry
    from plvo_app.cli import main

    seq_dir = _odometry_with_tr(tmp_path, {"zero focal length": "0 -1 0 0 0 0 -1 0 1 0 0 0",
                                           "singular Tr": " ".join(["0"] * 12),
                                           "scaled Tr": "0 -2 0 0 0 0 -2 0 2 0 0 0"}[what])
    if what == "zero focal length":
        text = (seq_dir / "calib.txt").read_text().splitlines()
        text = [" ".join(["P0:", "0", *ln.split()[2:]]) if ln.startswith("P0:") else ln for ln in text]
        (seq_dir / "calib.txt").write_text("\n".join(text) + "\n")
    with pytest.raises(CalibrationError, match=row.message) as info:
        KittiOdometry(tmp_path, "07")
    assert str(seq_dir / "calib.txt") in str(info.value)
    assert ("focal length fx 0" if what == "zero focal length" else "'Tr', the lidar's mounting") in str(info.value)
    status = main(["run", "--root", str(tmp_path), "--seq", "07", "--no-serve"])
    line = one_error_line(capsys.readouterr().err)
    assert status == row.exit and row.message in line and "calib.txt" in line


def test_calibration_unparseable_is_not_missing(tmp_path):
    row = fault("calib-unparseable")
    from plvo.data.kitti import KittiOdometry

    _odometry_with_tr(tmp_path, "1 0 0 0 0 1 0 0 0 0 1 zero")
    with pytest.raises(CalibrationError) as info:
        KittiOdometry(tmp_path, "07")
    assert row.message in str(info.value) and "'zero' is not a number" in str(info.value)
    assert "no 'Tr'" not in str(info.value) and row.exit == info.value.exit_status


# ---- pose files -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("matrix", ["zeros", "scaled", "reflection"])
def test_eval_metric_rejects_non_rotations(tmp_path, capsys, matrix):
    row = fault("pose-not-rotation")
    from plvo.data.trajectory import read_kitti_poses, write_kitti_poses
    from plvo_app.cli import main

    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, 2, 3] = np.arange(5.0)
    write_kitti_poses(tmp_path / "gt.txt", poses)
    bad = poses.copy()
    bad[3, :3, :3] = {"zeros": np.zeros((3, 3)), "scaled": 2 * np.eye(3), "reflection": np.diag([1.0, 1, -1])}[matrix]
    (tmp_path / "est.txt").write_text("# header\n" + "\n".join(
        " ".join(f"{v:.9e}" for v in T[:3].reshape(-1)) for T in bad) + "\n")
    with pytest.raises(TrajectoryError, match=r"est\.txt:5: the 3x3 block is not a rotation"):
        read_kitti_poses(tmp_path / "est.txt")  # line 5: the comment is line 1
    status = main(["eval", "metric", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt")])
    line = one_error_line(capsys.readouterr().err)
    assert status == row.exit and row.message in line and "est.txt:5" in line


def test_rotations_within_tolerance_are_accepted(tmp_path, kitti_root):
    from plvo.data.trajectory import read_kitti_poses

    gt = read_kitti_poses(kitti_root / "poses" / "04.txt")  # KITTI's 7-digit ground truth passes
    assert len(gt) == 271


# ---- files on disk ----------------------------------------------------------------------------------------------

def test_atomic_writes_follow_the_umask(tmp_path):
    row = fault("results-mode")
    from plvo.atomic import write_text_atomic
    from plvo.config import save_config
    from plvo.data.trajectory import write_kitti_poses

    old = os.umask(0o022)
    try:
        write_text_atomic(tmp_path / "timings.json", "{}\n")
        save_config(SystemConfig(), tmp_path / "config.toml")
        write_kitti_poses(tmp_path / "poses.txt", np.eye(4)[None])
    finally:
        os.umask(old)
    for name in ("timings.json", "config.toml", "poses.txt"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o644, name
    assert not list(tmp_path.glob(".*.part")) and row.exit == 0


def test_stale_synth_stage_removed_by_next_run(tmp_path):
    """A `plvo synth` killed with SIGKILL leaves its staging folder; the next run into the same root removes it."""
    row = fault("synth-killed")
    env = dict(os.environ, PYTHONPATH=f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    cmd = [sys.executable, "-c", "import sys; from plvo_app.cli import main; sys.exit(main())",
           "synth", "--out", str(tmp_path), "--frames", "40", "--no-progress"]
    p = subprocess.Popen(cmd, env=env, stderr=subprocess.DEVNULL)
    t0 = time.time()
    while not list(tmp_path.glob(".synth-00-*/sequences/00/image_0/*.png")) and time.time() - t0 < 120:
        time.sleep(0.2)
    p.kill()
    assert p.wait(timeout=30) == row.exit
    stale = list(tmp_path.glob(".synth-00-*"))
    assert len(stale) == 1 and str(p.pid) in stale[0].name
    from plvo_synth.generate import remove_stale_stages

    assert remove_stale_stages(tmp_path, ".synth-00-") == stale and not stale[0].exists()


def test_synth_sigterm_leaves_no_stage(tmp_path):
    row = fault("synth-term")
    env = dict(os.environ, PYTHONPATH=f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    cmd = [sys.executable, "-c", "import sys; from plvo_app.cli import main; sys.exit(main())",
           "synth", "--out", str(tmp_path), "--frames", "40", "--no-progress"]
    p = subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True)
    t0 = time.time()
    while not list(tmp_path.glob(".synth-00-*/sequences/00/image_0/*.png")) and time.time() - t0 < 120:
        time.sleep(0.2)
    p.terminate()
    err = p.stderr.read()
    assert p.wait(timeout=60) == row.exit, err
    assert err.strip().splitlines()[-1] == row.message and "Traceback" not in err
    assert not list(tmp_path.glob(".synth-*")) and not (tmp_path / "sequences" / "00").exists()


def test_eval_and_bench_out_of_the_wrong_kind(tmp_path, capsys):
    from plvo_app.cli import main

    eval_row, bench_row = fault("eval-out-file"), fault("bench-out-dir")
    (tmp_path / "afile").write_text("mine\n")
    status = main(["eval", "run", "--root", str(tmp_path), "--seq", "04", "--kiss", "--out", str(tmp_path / "afile")])
    line = one_error_line(capsys.readouterr().err)
    assert status == eval_row.exit and eval_row.message in line and (tmp_path / "afile").read_text() == "mine\n"
    status = main(["bench", "--root", str(tmp_path), "--seq", "04", "--out", str(tmp_path)])
    line = one_error_line(capsys.readouterr().err)
    assert status == bench_row.exit and bench_row.message in line


def test_no_command_replaces_an_output_that_exists(synth_seq, tmp_path, capsys):
    """One rule for every command that writes (docs/faults.md, "Outputs"): an existing file is refused, named, before
    any work, and left as it was. plvo bench, plvo eval run (without --resume), plvo eval stages and plvo vocab used
    to replace theirs; plvo-viz took a recording named like a results file in its own results folder (poses.txt
    then written over it)."""
    from plvo_app.cli import main, main_viz

    row = fault("output-exists")
    mine = "mine\n"

    def refused(status: int, path: Path) -> None:
        line = one_error_line(capsys.readouterr().err)
        assert status == row.exit and row.message in line and str(path) in line, line
        assert path.read_text() == mine

    bench = tmp_path / "bench.json"
    bench.write_text(mine)
    refused(main(["bench", "--root", str(synth_seq), "--seq", "00", "--stages", "features", "--out", str(bench)]),
            bench)
    report = tmp_path / "eval" / "report.json"
    report.parent.mkdir()
    report.write_text(mine)
    refused(main(["eval", "run", "--root", str(synth_seq), "--seq", "00", "--kiss", "--out", str(report.parent)]),
            report)
    stages = tmp_path / "stages" / "report.md"
    stages.parent.mkdir()
    stages.write_text(mine)
    refused(main(["eval", "stages", "--real", str(synth_seq), "00", "--twin", str(synth_seq), "00",
                  "--out", str(stages.parent)]), stages)
    vocab = tmp_path / "vocab" / "lbd.npz"
    vocab.parent.mkdir()
    vocab.write_text(mine)
    refused(main(["vocab", "--out", str(vocab.parent), "--synth", "3", "--no-progress"]), vocab)
    out = tmp_path / "out"
    status = main_viz(["--root", str(synth_seq), "--seq", "00", "--frames", "0:3", "--out", str(out), "--rrd",
                       str(out / "poses.txt"), "--no-serve"])
    line = one_error_line(capsys.readouterr().err)
    assert status == row.exit and "over the recording" in line and not (out / "poses.txt").exists(), line


def test_unexpected_error_in_any_command_is_one_line(tmp_path, capsys, monkeypatch):
    row = fault("unexpected-other")
    from plvo_app.cli import main
    from plvo_eval import kitti_metric

    def bug(*args, **kwargs):
        raise ZeroDivisionError("injected eval bug")

    monkeypatch.setattr(kitti_metric, "evaluate_sequence", bug)
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)  # re-read $TMPDIR
    poses = np.tile(np.eye(4), (3, 1, 1))
    from plvo.data.trajectory import write_kitti_poses

    write_kitti_poses(tmp_path / "p.txt", poses)
    status = main(["eval", "metric", "--gt", str(tmp_path / "p.txt"), "--est", str(tmp_path / "p.txt")])
    line = one_error_line(capsys.readouterr().err)
    assert status == row.exit and row.message in line
    assert line.startswith("error: unexpected ZeroDivisionError: injected eval bug")
    log = Path(line.rsplit("see the log ", 1)[1].rstrip(")"))
    assert log.parent == tmp_path and "ZeroDivisionError: injected eval bug" in log.read_text()
