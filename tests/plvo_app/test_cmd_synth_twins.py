"""`plvo synth --follow/--twins` and `plvo eval run --twins`: a twin is generated once (kept when current, staged
until complete), Table I gets a row per twin, and bad input is one line with exit status 2."""

from __future__ import annotations

import json

import numpy as np
import pytest

from plvo.errors import SynthError
from plvo_app.cli import main
from plvo_synth.twin.batch import parse_twins, twin_jobs


def test_parse_twins():
    assert parse_twins("00-03,08") == ["00", "01", "02", "03", "08"]
    assert parse_twins("5") == ["05"]
    with pytest.raises(SynthError, match="runs backwards"):
        parse_twins("10-00")
    with pytest.raises(SynthError, match="'x1'"):
        parse_twins("00,x1")


def test_synth_follow_errors_are_one_line(tmp_path, kitti_root, capsys):
    poses = kitti_root / "poses" / "05.txt"
    assert main(["synth", "--out", str(tmp_path), "--seq", "05", "--follow", str(poses), "--frames", "0:99999"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "05.txt has 2761 poses" in err
    assert main(["synth", "--out", str(tmp_path), "--seq", "05", "--follow", str(tmp_path / "none.txt")]) == 2
    assert "none.txt: no such pose file" in capsys.readouterr().err
    assert main(["synth", "--out", str(tmp_path), "--twins", "05", "--kitti-poses", str(tmp_path)]) == 2
    assert "05.txt: no such pose file" in capsys.readouterr().err
    assert main(["synth", "--out", str(tmp_path), "--seq", "05", "--follow", str(poses), "--lidar", "hdl128"]) == 2
    assert not (tmp_path / "sequences").exists()  # nothing written
    mine = tmp_path / "sequences" / "05"
    (mine / "image_0").mkdir(parents=True)  # a sequence of the user's, not a twin: never replaced silently
    assert main(["synth", "--out", str(tmp_path), "--twins", "05", "--kitti-poses", str(kitti_root / "poses"),
                 "--frames", "0:2"]) == 2
    assert "exists and is not a twin (pass --overwrite" in capsys.readouterr().err
    assert mine.is_dir() and not list((mine / "image_0").iterdir())


def test_eval_run_twins_generates_once_and_tables(tmp_path, kitti_root, capsys):
    twins, out = tmp_path / "twins", tmp_path / "eval"
    argv = ["eval", "run", "--twins", "05", "--kitti-poses", str(kitti_root / "poses"), "--twin-root", str(twins),
            "--frames", "40:52", "--traffic", "3", "--ablations", "points_only", "--workers", "1", "--out", str(out),
            "--no-plots"]
    assert main(argv) == 0
    seq = twins / "sequences" / "05"
    assert len(list((seq / "image_0").glob("*.png"))) == 12 and len(list((seq / "velodyne").glob("*.bin"))) == 12
    assert not list(twins.glob(".twin-*"))  # no staging folder left behind
    report = json.loads((out / "report.json").read_text())
    text = (out / "report.md").read_text()
    assert "twin05" in text and "KISS-ICP" in text and "KISS-SLAM" in text and "Point-only" in text
    assert set(report["settings"]) == {"points_only", "kiss", "kiss_slam"}
    stamp = (seq / "image_0" / "000000.png").stat().st_mtime_ns
    capsys.readouterr()
    assert main(argv + ["--resume"]) == 0
    assert "twin 05: kept (current)" in capsys.readouterr().err
    assert (seq / "image_0" / "000000.png").stat().st_mtime_ns == stamp
    gt = np.loadtxt(twins / "poses" / "05.txt").reshape(-1, 3, 4)
    full = np.loadtxt(kitti_root / "poses" / "05.txt").reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (12, 1, 1))
    T[:, :3] = full[40:52]
    rebased = np.linalg.inv(T[0]) @ T
    np.testing.assert_allclose(gt, rebased[:, :3], atol=1e-8)


def test_batch_over_processes_is_complete_or_absent(tmp_path, kitti_root):
    from plvo_synth.twin.batch import ensure_twins, is_current
    from plvo_synth.twin.generate import TwinSettings

    jobs = twin_jobs(["05", "07"], kitti_root / "poses", TwinSettings("", "60:63", traffic=2))
    seen, finished = [], []
    done = ensure_twins(jobs, tmp_path, workers=2, progress=lambda d, n: seen.append((d, n)), on_done=finished.append)
    assert [d.sequence for d in done] == ["05", "07"] and not any(d.error or d.cached for d in done)
    assert seen[-1] == (6, 6) and {d.sequence for d in finished} == {"05", "07"}
    assert all(is_current(tmp_path, j) for j in jobs)
    assert all(len(list((tmp_path / "sequences" / j.sequence / "velodyne").glob("*.bin"))) == 3 for j in jobs)
    again = ensure_twins(jobs, tmp_path, workers=2)
    assert all(d.cached for d in again)
    assert not list(tmp_path.glob(".twin-*"))


def test_batch_over_ray(tmp_path, kitti_root):
    pytest.importorskip("ray", reason="ray is not installed (the 'compare' extra)")
    from plvo_synth.twin.batch import ensure_twins, is_current
    from plvo_synth.twin.generate import TwinSettings

    other = twin_jobs(["05"], kitti_root / "poses", TwinSettings("", "63:65", traffic=2))
    done = ensure_twins(other, tmp_path, workers=1, ray="local")
    assert not done[0].error and not done[0].cached and is_current(tmp_path, other[0])
    assert len(list((tmp_path / "sequences" / "05" / "image_0").glob("*.png"))) == 2
    assert not list(tmp_path.glob(".twin-*"))


def test_the_stage_of_a_killed_run_is_cleared(tmp_path, kitti_root):
    from plvo_synth.twin.generate import TwinSettings, generate_twin

    settings = TwinSettings(str(kitti_root / "poses" / "05.txt"), "60:62", traffic=0)
    generate_twin(tmp_path, "05", settings)
    before = (tmp_path / "poses" / "05.txt").read_text()
    dead = tmp_path / ".twin-05-999999999-abc"  # what a killed run leaves: a stage whose process is gone
    (dead / "sequences" / "05" / "image_0").mkdir(parents=True)
    assert (tmp_path / "sequences" / "05" / "calib.txt").is_file()
    generate_twin(tmp_path, "05", TwinSettings(settings.follow, "62:64", traffic=0), overwrite=True)
    assert not dead.exists() and not list(tmp_path.glob(".twin-*"))
    assert (tmp_path / "poses" / "05.txt").read_text() != before
    assert len(list((tmp_path / "sequences" / "05" / "velodyne").glob("*.bin"))) == 2


def test_a_stopped_twin_resumes_where_it_stopped(tmp_path, kitti_root):
    """A run stopped part-way leaves its stage; the next run with the same settings renders only the frames it
    lacks, and the twin is the same, file for file, as one written in one go. A stage of other settings is
    removed by the next run, and one that another process holds is refused."""
    import filecmp

    from plvo_synth.generate import _stage_lock
    from plvo_synth.twin.generate import TwinSettings, generate_twin

    settings = TwinSettings(str(kitti_root / "poses" / "07.txt"), "60:66", traffic=6)
    whole = tmp_path / "whole"
    generate_twin(whole, "07", settings)

    class Stop(Exception):
        pass

    def stop_after_3(done, n):
        if done >= 3:
            raise Stop

    cut = tmp_path / "cut"
    with pytest.raises(Stop):
        generate_twin(cut, "07", settings, progress=stop_after_3)
    (stage,) = cut.glob(".twin-07-partial-*")
    assert not (cut / "sequences" / "07").exists()  # complete or absent
    kept = len(list((stage / ".frames").glob("*.json")))
    assert 3 <= kept < 6
    reports = []
    with _stage_lock(stage) as held:  # another process writing it
        assert held
        with pytest.raises(SynthError, match="another process is writing sequence 07"):
            generate_twin(cut, "07", settings)
    generate_twin(cut, "07", settings, progress=lambda d, n: reports.append(d))
    assert reports[0] == kept and reports[-1] == 6 and len(reports) == 1 + 6 - kept
    assert not list(cut.glob(".twin-*"))
    a, b = whole / "sequences" / "07", cut / "sequences" / "07"
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file()) and len(files) > 6 * 5
    assert all(filecmp.cmp(a / f, b / f, shallow=False) for f in files)
    with pytest.raises(Stop):
        generate_twin(cut, "07", TwinSettings(settings.follow, "66:72", traffic=6), progress=stop_after_3,
                      overwrite=True)
    assert len(list(cut.glob(".twin-07-partial-*"))) == 1
    generate_twin(cut, "07", TwinSettings(settings.follow, "70:72", traffic=6), overwrite=True)
    assert not list(cut.glob(".twin-*"))  # the 66:72 stage went with the run of other settings


def test_synth_ideal_writes_the_twins_as_before(tmp_path, kitti_root):
    """--ideal: KITTI 00-02's calibration for every twin, raw sweeps, no realism in scene.json; without it the twin
    has its own sequence's calibration and compensated scans."""
    poses = kitti_root / "poses" / "05.txt"
    for flag, out in (("--ideal", tmp_path / "ideal"), (None, tmp_path / "real")):
        argv = ["synth", "--out", str(out), "--seq", "05", "--follow", str(poses), "--frames", "40:42", "--traffic",
                "0", "--no-progress"]
        assert main(argv + ([flag] if flag else [])) == 0
    ideal = json.loads((tmp_path / "ideal" / "sequences" / "05" / "gt" / "scene.json").read_text())
    real = json.loads((tmp_path / "real" / "sequences" / "05" / "gt" / "scene.json").read_text())
    assert "realism" not in ideal and "realism" not in ideal["settings"] and ideal["lidar"]["sweep_s"] == 0.1
    assert real["realism"]["calibration"]["name"] == "04-10" and real["lidar"]["motion_compensated"]
    calib = (tmp_path / "ideal" / "sequences" / "05" / "calib.txt").read_text()
    assert calib.startswith("P0: 7.188560000000e+02")  # 00-02's
    image = tmp_path / "real" / "sequences" / "05" / "image_0" / "000000.png"
    from PIL import Image

    assert Image.open(image).size == (1226, 370)
    assert main(["synth", "--out", str(tmp_path / "town"), "--seq", "00", "--frames", "2", "--ideal"]) == 2
