"""KISS-SLAM beside KISS-ICP: its poses in cam0 convention and close to the ground truth on the twin of KITTI 07,
`plvo eval run --kiss-slam` writing its runs and its report column, the loop closures it accepts on a street block
driven round (and how they show in the report), and its chatter kept out of our output."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from eval_scene import _cast, _lidar_dirs, _pose, write_box_sequence

from plvo.data.registry import open_dataset, parse_frames
from plvo.data.trajectory import write_kitti_poses
from plvo_app.cli import main
from plvo_eval.kiss import KissOptions, lidar_to_cam0, run_kiss
from plvo_eval.kiss_slam import KissSlamOptions, _quiet, run_kiss_slam
from plvo_eval.report import build_report, report_json, report_markdown
from plvo_eval.runner import SequenceSource, build_specs, with_threads
from plvo_eval.tasks import AS_DELIVERED, CORRECTED, DESKEWED, NOT_DESKEWED, RunSpec, TaskResult, anchor
from plvo_synth.sensors import KITTI_CALIB_00_TEXT, T_CAM_VELO

TWIN_SEQUENCE = "07"  # the twin_root fixture's: frames 60:80 of KITTI 07


def _path_length(poses: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)))


def _final_error(est: np.ndarray, gt: np.ndarray) -> float:
    return float(np.linalg.norm(anchor(est, gt[0])[-1, :3, 3] - gt[-1, :3, 3]))


def _T_cam0_velo(dataset) -> np.ndarray:
    return np.asarray(dataset.calib.T_cam0_cam) @ np.asarray(dataset.calib.T_cam_velo)


# ---------------------------------------------------------------- the twin of 07 (20 frames, 16 m)


@pytest.fixture(scope="module")
def twin_runs(twin_root):
    dataset = open_dataset(twin_root, TWIN_SEQUENCE)
    return dataset, run_kiss_slam(dataset), run_kiss(dataset, KissOptions())


def test_twin_trajectory_is_close_to_the_ground_truth(twin_runs):
    dataset, slam, _kiss = twin_runs
    gt = dataset.gt_T_world_cam
    assert slam.poses.shape == (20, 4, 4) and slam.seconds.shape == (20,) and np.all(slam.seconds > 0)
    np.testing.assert_allclose(slam.poses[0], np.eye(4), atol=1e-12)
    assert slam.started_at < slam.finished_at and slam.finalize_s < slam.wall_s
    # 16 m is one local map (KISS-SLAM splits every 100 m) and nothing to close
    assert slam.n_local_maps == 1 and slam.n_closures == 0
    # measured: 15.82 m against 15.69 m (+0.8 %), 0.12 m off at the end; the bounds leave 2-4x of that, and poses
    # left in the lidar's frame (x forward, where cam0 has z) would end metres off
    assert _path_length(slam.poses) == pytest.approx(_path_length(gt), rel=0.03)
    assert _final_error(slam.poses, gt) < 0.3
    np.testing.assert_allclose(slam.poses, lidar_to_cam0(slam.lidar_poses, _T_cam0_velo(dataset)), atol=1e-9)


def test_twin_poses_agree_with_kiss_icp(twin_runs):
    """Within one local map and without a closure KISS-SLAM's trajectory is its KISS-ICP odometry, with KISS-SLAM's
    defaults equal to ours here (voxel 1 m, range 100 m, no deskew for want of timestamps): the same poses, through
    the same conversion to cam0 (measured equal to 1e-14 m)."""
    _dataset, slam, kiss = twin_runs
    np.testing.assert_allclose(slam.poses[:, :3, 3], kiss.poses[:, :3, 3], atol=1e-6)
    np.testing.assert_allclose(slam.poses[:, :3, :3], kiss.poses[:, :3, :3], atol=1e-9)


def test_eval_run_kiss_slam_on_the_twin(twin_root, tmp_path, capfd):
    out = tmp_path / "out"
    capfd.readouterr()
    code = main(["eval", "run", "--root", str(twin_root), "--seq", TWIN_SEQUENCE, "--kiss-slam", "--ablations",
                 "none", "--workers", "1", "--out", str(out), "--no-plots"])
    printed = capfd.readouterr()
    assert code == 0, printed.err
    # its prints and g2o's iterations (C++, straight to the file descriptors) are kept out of ours
    assert "KissSLAM|" not in printed.out + printed.err and "iteration=" not in printed.out + printed.err
    folder = out / "runs" / "kiss_slam" / TWIN_SEQUENCE
    assert len(np.loadtxt(folder / "poses.txt")) == 20 and (folder / "gt.txt").is_file()
    result = json.loads((folder / "result.json").read_text())
    assert result["status"] == "ok" and result["spec"]["method"] == "kiss_slam"
    details = dict(result["details"])
    ways = details.pop("ways")
    assert details == {"loop_closures": 0, "closures": [], "local_maps": 1}
    # the realistic twin's scans are compensated and carry KITTI's elevation error: KISS-SLAM ran with kiss_icp's
    # KITTI correction and without, and the table holds the run closer to the truth
    assert ways["judged_by"] == "short_t_err_pct" and set(ways["ways"]) == {AS_DELIVERED, AS_DELIVERED + CORRECTED}
    assert result["metrics"] == ways["ways"][ways["reported"]]["metrics"]
    figures = {way: v["metrics"]["short_t_err_pct"] for way, v in ways["ways"].items()}
    assert figures[ways["reported"]] == min(figures.values())
    assert result["timings"]["registration"]["runs"] == 20 and result["timings"]["finalize"]["runs"] == 1
    data = json.loads((out / "report.json").read_text())
    assert data["settings"] == ["kiss_slam"] and data["labels"] == {"kiss_slam": "KISS-SLAM"}
    assert data["loop_closures"] == {"kiss_slam": {TWIN_SEQUENCE: {"accepted": 0, "local_maps": 1, "closures": []}}}
    t_err = data["short_t_err_pct"]["kiss_slam"][TWIN_SEQUENCE]
    assert t_err == pytest.approx(result["metrics"]["short_t_err_pct"], rel=1e-9) and 0 < t_err < 3.0
    md = (out / "report.md").read_text()
    table = md.split("**Translation error [%] over 10/20/40 m, every frame a start**")[1].split("**")[0]
    assert "| Seq. | KISS-SLAM |" in table
    row = next(line for line in table.splitlines() if line.startswith(f"| {TWIN_SEQUENCE} |"))
    assert float(row.strip("| ").split("|")[1]) == pytest.approx(t_err, abs=0.005)
    closures = md.split("**Loop closures accepted**")[1]
    assert "| Seq. | KISS-SLAM |" in closures and f"| {TWIN_SEQUENCE} | 0 (1) |" in closures


# ---------------------------------------------------------------- a street block driven round: a loop to close

BLOCK_W, BLOCK_H, CORNER_R = 150.0, 100.0, 25.0  # street centre lines round one block, corner radius (m)
LOOP_FRAMES = 299  # 586 m: a lap of 457 m, then the first street again


def _block_pose(s: float) -> tuple[float, float, float]:
    """(x, y, yaw) at arc length s (m) counter-clockwise round the block, from (CORNER_R, 0) heading +x."""
    lap = 2 * (BLOCK_W + BLOCK_H) - 8 * CORNER_R + 2 * np.pi * CORNER_R
    s %= lap
    x, y, yaw = CORNER_R, 0.0, 0.0
    for side in (BLOCK_W, BLOCK_H, BLOCK_W, BLOCK_H):
        straight = side - 2 * CORNER_R
        if s < straight:
            return x + s * np.cos(yaw), y + s * np.sin(yaw), yaw
        s -= straight
        x, y = x + straight * np.cos(yaw), y + straight * np.sin(yaw)
        cx, cy = x - CORNER_R * np.sin(yaw), y + CORNER_R * np.cos(yaw)  # a left turn's centre
        phi = min(s / CORNER_R, np.pi / 2)
        if s < np.pi / 2 * CORNER_R:
            return cx + CORNER_R * np.sin(yaw + phi), cy - CORNER_R * np.cos(yaw + phi), yaw + phi
        s -= np.pi / 2 * CORNER_R
        yaw += np.pi / 2
        x, y = cx + CORNER_R * np.sin(yaw), cy - CORNER_R * np.cos(yaw)
    raise AssertionError("s beyond the lap")


def _block_boxes(rng: np.random.Generator) -> np.ndarray:
    """(B,2,3) lo, hi corners: the ground, and along both sides of the four streets building fronts with random
    widths, setbacks, heights and gaps, and clutter (what a density map's ORB features and ICP hold on to). Inside
    the block they stop where the corners' arcs begin, so that the car never drives through one."""
    boxes = [[[-100, -100, -1.0], [BLOCK_W + 100, BLOCK_H + 100, 0.0]]]
    corners = np.array([[0, 0], [BLOCK_W, 0], [BLOCK_W, BLOCK_H], [0, BLOCK_H]], dtype=np.float64)
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        length = float(np.linalg.norm(b - a))
        d = (b - a) / length
        left = np.array([-d[1], d[0]])  # into the block
        for side, s, end in ((-1, -40.0, length + 40.0), (1, CORNER_R, length - CORNER_R)):
            while s < end:
                width = rng.uniform(3, 9)
                if rng.random() > 0.15:  # else a gap
                    offset, depth = rng.uniform(7, 11), rng.uniform(5, 9)
                    p, q = a + d * s + left * side * offset, a + d * (s + width) + left * side * (offset + depth)
                    boxes.append([[*np.minimum(p, q), 0], [*np.maximum(p, q), rng.uniform(4, 15)]])
                    for _ in range(2):
                        along, size = s + rng.uniform(0, width), rng.uniform(0.6, 2.5, 2)
                        p = a + d * along + left * side * rng.uniform(3.5, 6.0)
                        q = p + d * size[0] + left * side * size[1]
                        boxes.append([[*np.minimum(p, q), 0], [*np.maximum(p, q), rng.uniform(0.8, 3.5)]])
                s += width
    return np.asarray(boxes, dtype=np.float64)


def write_block_loop(root: Path, name: str = "00", n_frames: int = LOOP_FRAMES, seed: int = 0) -> Path:
    """Write a KITTI-layout sequence driving round a street block and on along its first street (as
    eval_scene.write_box_sequence: a 32-beam lidar ray-cast analytically, blank images, KITTI 00's calibration).
    The car starts at 10 m/s and reaches 20 m/s at 5 m/s^2: KISS-ICP's first registration has no motion to go by,
    and 2 m at once from standstill lost it."""
    rng = np.random.default_rng(seed)
    boxes, dirs = _block_boxes(rng), _lidar_dirs(240)
    centres, half = boxes.mean(axis=1), (boxes[:, 1] - boxes[:, 0]) / 2
    seq = root / "sequences" / name
    for sub in ("image_0", "velodyne"):
        (seq / sub).mkdir(parents=True, exist_ok=True)
    (root / "poses").mkdir(parents=True, exist_ok=True)
    (seq / "calib.txt").write_text(KITTI_CALIB_00_TEXT)
    (seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(n_frames)))
    image = np.zeros((32, 96), np.uint8)
    T_velo_cam = np.linalg.inv(T_CAM_VELO)
    speeds = np.minimum(20.0, 10.0 + 0.5 * np.arange(n_frames))
    arc = np.concatenate([[0.0], np.cumsum(0.1 * speeds[:-1])])
    T_world_cam = []
    for i in range(n_frames):
        T = _pose(*_block_pose(arc[i]))
        reach = np.all(np.abs(centres[:, :2] - T[:2, 3]) < 62.0 + half[:, :2], axis=1)  # the 60 m range, plus
        ranges = _cast(T[:3, 3], dirs @ T[:3, :3].T, boxes[reach])
        ok = ranges < 60.0
        points = dirs[ok] * (ranges[ok] + rng.normal(0, 0.01, ok.sum()))[:, None]
        np.hstack([points, np.full((len(points), 1), 0.5)]).astype(np.float32).tofile(seq / "velodyne" / f"{i:06d}.bin")
        cv2.imwrite(str(seq / "image_0" / f"{i:06d}.png"), image)
        T_world_cam.append(T @ T_velo_cam)
    T_world_cam = np.asarray(T_world_cam)
    write_kitti_poses(root / "poses" / f"{name}.txt", np.linalg.inv(T_world_cam[0]) @ T_world_cam)
    return root


@pytest.fixture(scope="module")
def block_runs(tmp_path_factory):
    root = write_block_loop(tmp_path_factory.mktemp("block"))
    dataset = open_dataset(root, "00")
    # one thread each: on all cores of a busy machine KISS-SLAM ends 1.318-1.343 m off over 15 runs (its threads sum
    # in another order each time) and one run of the suite found no closure; on one thread 1.3241 m every run
    slam = run_kiss_slam(dataset, KissSlamOptions(max_threads=1))
    return dataset, slam, run_kiss(dataset, KissOptions(max_threads=1))


def test_a_loop_round_the_block_is_closed_and_shows_in_the_trajectory(block_runs):
    """Round the block and 130 m on: six local maps, the last two driven where the first two were, more than three
    maps apart as map_closures requires. Measured (five runs, all cores and one thread): the closures of map 4 to map 0
    (overlap 0.70) and of 5 to 1 (0.60) accepted each time, their frames 0.9 m from the reference's (median);
    KISS-SLAM 1.32-1.34 m off at the end against KISS-ICP's 2.34 m."""
    dataset, slam, kiss = block_runs
    gt = dataset.gt_T_world_cam
    assert slam.n_local_maps >= 5 and slam.n_closures >= 1, slam
    for c in slam.closures:
        assert c.query_map - c.reference_map > 3
        query = gt[c.query_frames[0]:c.query_frames[1] + 1, :3, 3]
        reference = gt[c.reference_frames[0]:c.reference_frames[1] + 1, :3, 3]
        nearest = np.linalg.norm(query[:, None] - reference[None], axis=2).min(axis=1)
        assert np.median(nearest) < 5.0, (c, np.median(nearest))  # a true revisit: the same street
    # KISS-ICP tracks the lap (the comparison means something) and the closure pulls the end back to the start
    assert _path_length(kiss.poses) == pytest.approx(_path_length(gt), rel=0.01)
    assert 1.0 < _final_error(kiss.poses, gt) < 4.0
    assert _final_error(slam.poses, gt) < 0.8 * _final_error(kiss.poses, gt)


# ---------------------------------------------------------------- wiring, report, output


def test_a_single_frame_is_the_origin(tmp_path):
    """kiss_slam's own finishing step fixes a pose-graph variable that a one-frame run lacks, and g2o then ends
    the process with a segmentation fault; the frame's pose is the origin."""
    write_box_sequence(tmp_path, "a", n_frames=3)
    out = run_kiss_slam(open_dataset(tmp_path, "a", frames=parse_frames("1:2")))
    assert out.poses.shape == (1, 4, 4) and out.n_local_maps == 1 and out.n_closures == 0
    np.testing.assert_allclose(out.poses[0], np.eye(4), atol=1e-12)


def test_threads_and_specs():
    sources = [SequenceSource("root", "a")]
    specs = with_threads(build_specs(sources, ["full"], kiss=True, kiss_slam=True), 3)
    assert [(s.method, s.setting) for s in specs] == [("plvo", "full"), ("kiss", "kiss"), ("kiss_slam", "kiss_slam")]
    assert specs[0].kiss.max_threads == 0 and specs[0].kiss_slam.max_threads == 0
    assert specs[1].kiss.max_threads == 3 and specs[2].kiss_slam.max_threads == 3
    assert RunSpec.from_json(json.loads(json.dumps(specs[2].to_json()))) == specs[2]


def test_both_ways_keep_the_reported_runs_closures_on_top(monkeypatch):
    """On raw sweeps KISS-SLAM runs deskewed and not; the report reads the loop closures of the run it reports."""
    import plvo_eval.tasks as tasks
    from plvo_eval.kiss_slam import KissSlamOutput, LoopClosure

    class Straight:
        sequence, scans_compensated = "straight", False
        gt_T_world_cam = np.tile(np.eye(4), (40, 1, 1))
        gt_T_world_cam[:, 2, 3] = np.arange(40.0)

        def __len__(self) -> int:
            return 40

    def fake(dataset, options):  # deskewed: 3 % too long with one closure; not: 1 % too long, none
        poses = Straight.gt_T_world_cam.copy()
        poses[:, 2, 3] *= 1.03 if options.deskew else 1.01
        closures = (LoopClosure(0, 4, (0, 9), (30, 39)),) if options.deskew else ()
        return KissSlamOutput(poses, poses, np.zeros(40), 0.0, closures, 5 if options.deskew else 1)

    monkeypatch.setattr(tasks, "run_kiss_slam", fake)
    out = tasks._method_kiss_slam(Straight(), RunSpec(SequenceSource("unused", "straight"), "kiss_slam",
                                                      "kiss_slam", None))
    assert out.details["ways"]["reported"] == NOT_DESKEWED
    assert (out.details["loop_closures"], out.details["local_maps"], out.details["closures"]) == (0, 1, [])
    assert out.details["ways"]["ways"][DESKEWED]["details"]["loop_closures"] == 1


def _result(tmp_path, setting: str, method: str, details: dict | None) -> TaskResult:
    spec = RunSpec(SequenceSource("root", "a"), method=method, setting=setting, ablation=None)
    folder = tmp_path / setting
    folder.mkdir()
    gt = np.stack([np.eye(4)] * 30)
    gt[:, 2, 3] = np.arange(30.0)
    write_kitti_poses(folder / "gt.txt", gt)
    write_kitti_poses(folder / "poses.txt", gt)
    return TaskResult(spec, "ok", "", 30, 1.0, 30.0, None, {}, folder, details or {})


def test_report_counts_the_loop_closures(tmp_path):
    closure = {"reference_map": 0, "query_map": 4, "reference_frames": [0, 56], "query_frames": [231, 281]}
    results = [_result(tmp_path, "kiss_slam", "kiss_slam", {"loop_closures": 1, "closures": [closure],
                                                            "local_maps": 6}),
               _result(tmp_path, "kiss", "kiss", None), _result(tmp_path, "full", "plvo", None)]
    report = build_report(results)
    assert report.settings == ("full", "kiss", "kiss_slam")  # plvo first, then KISS-ICP, then KISS-SLAM
    data = report_json(report)
    assert data["loop_closures"] == {"kiss_slam": {"a": {"accepted": 1, "local_maps": 6, "closures": [closure]}}}
    md = report_markdown(report, data)
    tables = [s for s in md.split("**")[2::2] if "\n| " in s]  # what follows each bold title, where a table
    assert len(tables) >= 7
    for table in tables[:7]:  # every error table has the three columns
        assert "| Ours (*) | KISS-ICP | KISS-SLAM |" in table, table
    assert "| a | 1 (6) |" in md and "local map 4 (frames 231-281) to 0 (frames 0-56)" in md
    # without KISS-SLAM the report keeps its keys and sections
    plain = report_json(build_report(results[1:2]))
    assert "loop_closures" not in plain and "Loop closures" not in report_markdown(build_report(results[1:2]))


def test_plot_legends_name_kiss_slam(tmp_path, monkeypatch):
    from plvo_eval import plots

    legends = {}

    def keep(fig, path):
        legends[path.name] = [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()]
        plots._pyplot().close(fig)
        return path

    monkeypatch.setattr(plots, "save_figure", keep)
    plots.write_plots(build_report([_result(tmp_path, "kiss", "kiss", None),
                                    _result(tmp_path, "kiss_slam", "kiss_slam", {"loop_closures": 0})]), tmp_path)
    assert set(legends) == {"trajectory_a.png", "error_by_length.png", "error_by_speed.png"}
    assert all("KISS-SLAM" in labels and "KISS-ICP" in labels for labels in legends.values()), legends


def test_quiet_keeps_its_chatter_out_and_lets_errors_through(capfd, caplog):
    capfd.readouterr()
    with caplog.at_level(logging.DEBUG, logger="plvo_eval.kiss_slam"), pytest.raises(ValueError, match="boom"), \
            _quiet():
        print("KissSLAM| Closure Detected")
        os.write(2, b"iteration= 0\t chi2= 0.0\n")  # as g2o writes, beneath Python
        raise ValueError("boom")
    printed = capfd.readouterr()
    assert printed.out == "" and printed.err == ""
    assert "KISS-SLAM: KissSLAM| Closure Detected" in caplog.text and "KISS-SLAM: iteration= 0" in caplog.text
    print("ours")
    os.write(2, b"ours too\n")
    printed = capfd.readouterr()
    assert printed.out == "ours\n" and printed.err == "ours too\n"  # the descriptors are back
