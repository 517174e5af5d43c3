"""`plvo eval metric --plot DIR`: one PNG per kind with every run drawn, the estimates SE(3)-aligned as the ATE
aligns them; existing plots refused before any work."""

from __future__ import annotations

import json

import numpy as np
import pytest
from metric_files import EST, GT, TIMES, noisy_estimate, results_folder

from plvo.data.trajectory import write_poses
from plvo.geometry import se3
from plvo_app.cli import main
from plvo_eval.kitti_metric import absolute_trajectory_error
from plvo_eval.metric_plots import FIGSIZE, PLOTS, PlottedRun, roll_pitch_yaw, up_axis

DPI = 110  # plvo_eval.plots.save_figure's


def _image(path):
    import matplotlib.image as mpimg

    return mpimg.imread(path)


def test_plots_of_several_runs(tmp_path, capsys):
    a = results_folder(tmp_path / "a", range(0, 80))
    b = results_folder(tmp_path / "b", range(50, 150), est=noisy_estimate(GT, seed=2, scale=0.97))
    write_poses(tmp_path / "gt.txt", GT, TIMES, "kitti")
    plots = tmp_path / "plots" / "new"  # made as needed
    capsys.readouterr()
    assert main(["eval", "metric", "--gt", str(tmp_path / "gt.txt"), "--est", str(a), "--est", str(b),
                 "--plot", str(plots)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[-4:] == [f"plot: {plots / name}.png" for name in PLOTS]
    assert sorted(p.name for p in plots.iterdir()) == sorted(f"{name}.png" for name in PLOTS)  # no leftovers
    for name in PLOTS:
        img = _image(plots / f"{name}.png")
        w, h = FIGSIZE[name]
        assert img.shape[1] == pytest.approx(w * DPI, rel=0.1) and img.shape[0] == pytest.approx(h * DPI, rel=0.1)
        rgb = img[..., :3]
        assert (rgb.min(axis=2) < 0.9).mean() > 0.01, name  # not blank
        # both runs drawn: matplotlib's first two colours, C0 (blue) and C1 (orange)
        blue = (np.abs(rgb - [0.122, 0.467, 0.706]).max(axis=2) < 0.05).sum()
        orange = (np.abs(rgb - [1.0, 0.498, 0.055]).max(axis=2) < 0.05).sum()
        assert blue > 50 and orange > 50, (name, blue, orange)
        black = (rgb.max(axis=2) < 0.05).sum()  # the truth
        assert black > 200, name


def test_json_stays_one_document_beside_the_plots(tmp_path, capsys):
    write_poses(tmp_path / "gt.txt", GT[:60], TIMES[:60], "tum")
    write_poses(tmp_path / "est.txt", EST[:60], TIMES[:60], "tum")
    capsys.readouterr()
    assert main(["eval", "metric", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt"),
                 "--plot", str(tmp_path / "p"), "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["n_frames"] == 60
    assert captured.err.splitlines() == [f"plot: {tmp_path / 'p' / name}.png" for name in PLOTS]


def test_an_existing_plot_is_refused_before_any_work(tmp_path, capsys):
    plots = tmp_path / "plots"
    plots.mkdir()
    (plots / "xyz.png").write_bytes(b"mine")
    # the estimate does not even exist: the refusal comes first
    status = main(["eval", "metric", "--gt", str(tmp_path / "none.txt"), "--est", str(tmp_path / "none.txt"),
                   "--plot", str(plots)])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and err == [f"error: {plots / 'xyz.png'}: already exists; plvo eval metric --plot never "
                                   "replaces a file (choose another --plot folder)"]
    assert (plots / "xyz.png").read_bytes() == b"mine" and [p.name for p in plots.iterdir()] == ["xyz.png"]
    (tmp_path / "file").write_text("x")
    status = main(["eval", "metric", "--gt", str(tmp_path / "none.txt"), "--est", str(tmp_path / "none.txt"),
                   "--plot", str(tmp_path / "file")])
    assert status == 2 and "is a file, not a folder for the plots" in capsys.readouterr().err


def test_the_plotted_estimate_is_aligned_as_the_ate_aligns_it():
    T = se3.from_rt(se3.so3_exp(np.array([0.1, 1.2, -0.2])), np.array([5.0, -1.0, 30.0]))
    est = T @ GT  # the truth in another world frame
    ate = absolute_trajectory_error(GT, est)
    run = PlottedRun("r", GT, est, np.arange(len(GT)), None, ate)
    np.testing.assert_allclose(run.aligned, GT, atol=1e-9)


def test_up_axis_and_yaw_unwrapped():
    assert up_axis(GT[:, :3, 3]) == 1  # KITTI cam0: y down
    straight = np.zeros((10, 3))
    straight[:, 2] = np.arange(10)
    assert up_axis(straight) == 1  # flat across x and y: y taken
    z_up = GT[:, :3, 3][:, [2, 0, 1]]  # ahead along x, left along y, z up
    assert up_axis(z_up) == 2
    yaw = np.radians(np.linspace(0.0, 350.0, 36))  # a full turn: no jump at 180 deg
    poses = np.stack([se3.from_rt(se3.so3_exp(np.array([0.0, a, 0.0])) @ se3.so3_exp(np.array([0.05, 0.0, 0.0])),
                                  np.zeros(3)) for a in yaw])
    rpy = roll_pitch_yaw(poses, 1)
    np.testing.assert_allclose(rpy[:, 2], np.degrees(yaw), atol=1e-9)
    np.testing.assert_allclose(rpy[:, 1], np.degrees(0.05), atol=1e-9)  # pitch about x
    np.testing.assert_allclose(rpy[:, 0], 0.0, atol=1e-9)


def test_orientations_are_drawn_from_the_origin_not_the_position_fit():
    """Along a straight drive the ATE's position fit leaves the roll about the road free (real 04 came out rolled
    39 deg): the orientation plot starts each estimate at the truth's first pose instead."""
    from plvo_eval.kitti_metric import absolute_trajectory_error
    from plvo_eval.metric_plots import PlottedRun

    n = 30
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 2, 3] = np.arange(n) * 1.0  # straight along z
    est = gt.copy()
    est[:, 0, 3] += 0.01 * np.sin(np.arange(n))  # a little lateral noise
    run = PlottedRun("r", gt, est, np.arange(n), None, absolute_trajectory_error(gt, est))
    np.testing.assert_allclose(run.from_origin[:, :3, :3], gt[:, :3, :3], atol=1e-12)
