"""Per-stage statistics (plvo_eval.stage_stats, kiss_stats, stage_report) and `plvo eval stages`: each statistic
against the values it is made of or a known setting, and the report of a sequence set beside itself."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from eval_scene import write_box_sequence

from plvo.config import SystemConfig, merge
from plvo.data.kitti import KittiOdometry
from plvo.geometry import se3
from plvo.recording import FanOut
from plvo.results import MetricsResult, StageSteps, TrackingResult
from plvo.types import DepthPriors, FeatureSet
from plvo_app.cli import main
from plvo_eval.kiss import KissOptions, run_kiss
from plvo_eval.kiss_stats import kiss_summary, registration_fit, run_kiss_stats
from plvo_eval.stage_report import BAND, compare
from plvo_eval.stage_runs import run_kiss_side
from plvo_eval.stage_stats import (
    DISTRIBUTION,
    SHARE,
    SIGNED,
    StageStatsRecorder,
    backend_moves,
    describe,
)

TOWN_FRAMES = 12


class _Spy:
    """Keeps every result a run hands its recorders."""

    def __init__(self) -> None:
        self.results: list = []

    def on_run_start(self, info) -> None:
        pass

    def on_frame(self, frame) -> None:
        pass

    def on_stage(self, frame_index, result) -> None:
        self.results.append(result)

    def close(self) -> None:
        pass

    def of(self, kind) -> list:
        return [r for r in self.results if isinstance(r, kind)]


@pytest.fixture(scope="module")
def town(synth_seq) -> Path:
    """The suite's 20-frame town (generated once a session), of which the first TOWN_FRAMES frames run."""
    return synth_seq


@pytest.fixture(scope="module")
def town_run(town):
    """plvo inline on the town, with the statistics recorder and a spy beside it -> (summary, spy, config)."""
    from plvo.runtime.run import run_dataset

    config = merge(SystemConfig(), {"backend": {"concurrent": False}, "loop": {"enabled": False}})
    stats, spy = StageStatsRecorder(), _Spy()
    out = run_dataset(KittiOdometry(town, "00", frames=slice(0, TOWN_FRAMES)), config, FanOut([stats, spy]))
    summary = stats.summary()
    summary.update(backend_moves(out.stage_steps))
    return summary, spy, config


def test_matching_statistics_are_the_tracking_results_counts(town_run):
    summary, spy, config = town_run
    features = spy.of(FeatureSet)
    assert summary["orb_keypoints"]["n"] == len(features) == TOWN_FRAMES
    assert summary["line_segments"]["value"] == np.median([f.n_lines for f in features])
    tracked = [r for r in spy.of(TrackingResult) if r.status == "tracked"]
    assert len(tracked) == TOWN_FRAMES - 1  # every frame after the first, none lost on the town
    assert summary["lost"]["value"] == 0.0
    ratios = [len(r.point_inliers) / len(r.point_inlier) for r in tracked]
    assert summary["point_inlier_ratio"]["value"] == pytest.approx(np.median(ratios), abs=1e-12)
    assert summary["point_inlier_ratio"]["mean"] == pytest.approx(np.mean(ratios), abs=1e-12)
    assert summary["line_inliers"]["value"] == np.median([len(r.line_inliers) for r in tracked])
    assert summary["point_matches"]["value"] == np.median([r.n_point_matches for r in tracked])
    keyframes = sum(r.is_keyframe for r in tracked)
    assert summary["keyframe_share"]["value"] == pytest.approx(keyframes / len(tracked))
    # PnPL's residuals: one per inlier of its solve, each within the inlier threshold, sub-pixel on exact depth
    residuals = np.concatenate([r.pnpl_point_residuals for r in tracked])
    assert summary["pnpl_point_residual_px"]["n"] == len(residuals) > 20 * len(tracked)
    assert residuals.max() < config.tracking.outlier_reproj_px
    assert all(len(r.pnpl_point_residuals) <= len(r.point_inlier) for r in tracked)
    assert summary["pnpl_point_residual_px"]["value"] < 1.5


def test_track_lengths_count_the_frames_each_landmark_is_tied_to(town_run):
    summary, spy, _ = town_run
    frames, keyframes = Counter(), Counter()
    for r in spy.of(TrackingResult):
        ids = set(r.association.point_landmark[r.association.point_landmark >= 0].tolist())
        frames.update(ids)
        if r.is_keyframe:
            keyframes.update(ids)
    tracked = [i for i, n in frames.items() if n > 1]
    assert summary["point_tracked_share"]["value"] == pytest.approx(len(tracked) / len(frames))
    assert summary["point_track_frames"]["value"] == np.median([frames[i] for i in tracked])
    assert summary["point_track_keyframes"]["mean"] == pytest.approx(np.mean([keyframes[i] for i in tracked]))
    assert summary["point_track_frames"]["value"] >= 2


def test_depth_prior_statistics_are_the_keyframes_priors(town_run):
    summary, spy, _ = town_run
    priors = spy.of(DepthPriors)
    assert summary["point_prior_coverage"]["n"] == len(priors) >= 3
    # a prior is a finite depth: the share of each keyframe's keypoints with one, averaged over keyframes
    assert summary["point_prior_coverage"]["value"] == pytest.approx(
        np.mean([np.isfinite(p.point_depth).mean() for p in priors]), abs=1e-12)
    shares = sum(summary[k]["value"] for k in summary if k.startswith("point_prior_missing_"))
    assert shares + summary["point_prior_coverage"]["value"] == pytest.approx(1.0, abs=1e-12)
    fits = np.concatenate([p.point_residual[p.point_valid] for p in priors])
    assert summary["point_prior_residual_m"]["value"] == pytest.approx(np.median(fits), abs=1e-15)
    assert summary["point_prior_residual_m"]["value"] < 0.05  # the town's surfaces are exact planes


def test_lidar_and_bundle_adjustment_statistics_are_the_back_ends(town_run):
    summary, spy, _ = town_run
    backend = [m.values for m in spy.of(MetricsResult) if "scale_factor" in m.values]
    registered = [v for v in backend if "e_bar" in v]
    assert len(registered) >= 2
    assert summary["registration_e_bar_m"]["value"] == pytest.approx(np.median([v["e_bar"] for v in registered]))
    assert summary["registration_zeta"]["mean"] == pytest.approx(np.mean([v["zeta"] for v in registered]))
    assert summary["scale_correction_pct"]["value"] == pytest.approx(
        np.median([100 * (v["scale_factor"] - 1) for v in registered]))
    ba = [v for v in backend if "ba_initial_cost" in v]
    assert summary["ba_cost_ratio"]["value"] == pytest.approx(
        np.median([v["ba_final_cost"] / v["ba_initial_cost"] for v in ba]))
    assert summary["ba_cost_ratio"]["value"] <= 1.0  # an adjustment lowers its cost
    assert summary["ba_move_m"]["n"] == len(ba)


def test_backend_moves_measure_each_stage_against_the_one_before():
    step = se3.from_rt(np.eye(3), [0.0, 0.0, 1.0])
    scaled = se3.from_rt(np.eye(3), [0.0, 0.0, 1.02])
    turned = scaled @ se3.exp(np.r_[0.0, 0.0, 0.0, 0.0, np.radians(0.5), 0.0])
    moves = backend_moves([StageSteps((0, 3), {"tracker": step, "scale": scaled, "ba": turned}),
                           StageSteps((3, 6), {"tracker": step, "ba": scaled})])
    assert moves["scale_move_m"]["n"] == 1 and moves["scale_move_m"]["value"] == pytest.approx(0.02)
    # the first keyframe's adjustment turned the scale correction's step by 0.5 deg in place, the second's moved
    # the tracker's (no scale correction) by 2 cm without turning it
    assert moves["ba_move_deg"]["n"] == 2 and moves["ba_move_deg"]["mean"] == pytest.approx(0.25)
    assert moves["ba_move_m"]["mean"] == pytest.approx(0.01)


def test_registration_fit_reads_the_offset_from_a_plane():
    g = np.arange(-5.0, 5.0, 0.25)
    wall = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    map_points = np.c_[wall, np.zeros(len(wall))]
    source = np.c_[wall[::7] + 0.1, np.full(len(wall[::7]), 0.05)]  # 5 cm off the plane, between its samples
    nearest, share, plane = registration_fit(source, np.eye(4), map_points, 0.3)
    assert plane == pytest.approx(0.05, abs=1e-9)
    assert nearest == pytest.approx(np.sqrt(0.1**2 + 0.1**2 + 0.05**2), abs=1e-9) and share == 1.0
    _, share, _ = registration_fit(source, se3.from_rt(np.eye(3), [0.0, 0.0, 0.5]), map_points, 0.3)
    assert share == 0.0  # lifted half a metre: no point within the correspondence distance


@pytest.fixture(scope="module")
def box_pair(tmp_path_factory) -> tuple[Path, Path]:
    """A clean 12-frame box street and the same with 8 cm of range noise on every return."""
    clean = write_box_sequence(tmp_path_factory.mktemp("clean"), "00", n_frames=12)
    noisy = write_box_sequence(tmp_path_factory.mktemp("noisy"), "00", n_frames=12)
    rng = np.random.default_rng(1)
    for path in sorted((noisy / "sequences" / "00" / "velodyne").glob("*.bin")):
        scan = np.fromfile(path, np.float32).reshape(-1, 4)
        r = np.linalg.norm(scan[:, :3], axis=1, keepdims=True)
        scan[:, :3] *= (r + rng.normal(0.0, 0.08, r.shape)) / r
        scan.tofile(path)
    return clean, noisy


def test_kiss_statistics_run_kiss_as_it_runs_and_see_range_noise(box_pair):
    clean, noisy = box_pair
    ds = KittiOdometry(clean, "00")
    out, per_frame = run_kiss_stats(ds, KissOptions(max_threads=1))
    np.testing.assert_allclose(out.poses, run_kiss(ds, KissOptions(max_threads=1)).poses, atol=1e-9)
    summary = kiss_summary(per_frame, ds.frame_indices, ds.gt_T_world_cam, out.poses)
    assert summary["kiss_residual_m"]["n"] == len(ds) - 1  # the first scan has no map to fit
    assert summary["kiss_inlier_share"]["value"] > 0.9
    assert summary["drift_final_scale_pct"]["n"] == len(ds) - 1
    _, noisy_frames = run_kiss_stats(KittiOdometry(noisy, "00"), KissOptions(max_threads=1))
    noisy_summary = kiss_summary(noisy_frames)
    # the box faces are exact planes with 1 cm of range noise (measured: 2.3 cm, the fits straddling their edges);
    # 8 cm more shows in the distance to them (measured: 3.8 cm)
    assert summary["kiss_plane_residual_m"]["value"] < 0.03
    assert noisy_summary["kiss_plane_residual_m"]["value"] > summary["kiss_plane_residual_m"]["value"] + 0.01


def test_kiss_on_raw_sweeps_runs_both_ways_and_reports_the_closer(box_pair):
    ds = KittiOdometry(box_pair[0], "00")
    ds.scans_compensated = False  # read as a twin's sweeps: each return deskewed by its azimuth's time
    way, ways, _ = run_kiss_side(ds, KissOptions(max_threads=1))
    # and with kiss_icp's KITTI correction and without (the pair has no scene.json: read as KITTI's own scans)
    assert set(ways) == {"deskewed", "not_deskewed", "deskewed+elevation_corrected",
                         "not_deskewed+elevation_corrected"}
    errors = {w: ways[w]["accuracy"]["short_t_err_pct"] for w in ways}
    assert errors[way] == min(errors.values())  # 12 frames: judged by the short segments (no devkit segment)
    assert ways["deskewed"]["stats"]["kiss_correction_m"]["value"] != ways["not_deskewed"]["stats"][
        "kiss_correction_m"]["value"]


def _entry(value, kind=DISTRIBUTION, n=10):
    return {**describe([], "s", "u", kind), "value": value, "n": n}


def test_compare_flags_outside_the_band_and_never_a_signed_figure():
    lo, hi = BAND
    real = {"a": _entry(1.0), "b": _entry(1.0), "c": _entry(-1.0, SIGNED), "d": _entry(0.0), "e": _entry(0.0),
            "f": _entry(0.5, SHARE), "g": _entry(0.004, SHARE), "h": _entry(1.0)}
    twin = {"a": _entry(lo), "b": _entry(lo - 1e-3), "c": _entry(3.0, SIGNED), "d": _entry(0.0), "e": _entry(0.2),
            "f": _entry(0.3, SHARE), "g": _entry(0.0, SHARE), "i": _entry(2.0)}
    rows = {r["name"]: r for r in compare(real, twin)}
    assert not rows["a"]["flagged"] and rows["b"]["flagged"]
    assert rows["c"]["ratio"] is None and not rows["c"]["flagged"]
    assert rows["d"]["ratio"] == 1.0 and not rows["d"]["flagged"]  # 0 on both sides: equal
    assert rows["e"]["ratio"] is None and rows["e"]["flagged"]  # 0 on the real side only
    assert rows["f"]["ratio"] == pytest.approx(0.6) and rows["f"]["flagged"]
    assert not rows["g"]["flagged"]  # a share 0.4 percentage point away: noise, whatever its ratio
    assert rows["h"]["flagged"] and rows["i"]["flagged"]  # one side only
    assert [r["name"] for r in compare(real, twin)] == [*"abcdefgh", "i"]


def test_stages_command_reports_a_sequence_beside_itself(town, tmp_path, capsys):
    """The command at the defaults (deployed mode) on one town twice: every figure equal, nothing flagged."""
    out = tmp_path / "report"
    frames = f"0:{TOWN_FRAMES}"
    status = main(["eval", "stages", "--real", str(town), "00", "--twin", str(town), "00", "--frames", frames,
                   "--out", str(out)])
    assert status == 0
    data = json.loads((out / "report.json").read_text())
    assert data["real"]["n_frames"] == data["twin"]["n_frames"] == TOWN_FRAMES
    for system in ("plvo", "kiss"):
        rows = data[system]
        assert len(rows) > 10
        assert not [r["name"] for r in rows if r["flagged"]]
        for r in rows:  # (the drifts over stretches are None on both: 11 m of path is no stretch of 50 m)
            a, b = r["real"]["value"], r["twin"]["value"]
            assert (a is None and b is None) or a == pytest.approx(b, rel=1e-6, abs=1e-12), r["name"]
    names = {r["name"] for r in data["plvo"]}
    assert {"point_inlier_ratio", "pnpl_point_residual_px", "point_prior_coverage", "registration_e_bar_m",
            "ba_move_m", "drift_scale_yaw_deg_per_100m", "point_track_frames"} <= names
    assert {r["system"] for r in data["accuracy"]} == {"plvo", "kiss"}
    # 11 m of path: 10 m segments only (a length without segments on either side has no row)
    assert [(r["system"], r["length_m"]) for r in data["accuracy"]] == [("plvo", "10")] * 2 + [("kiss", "10")] * 2
    assert all(r["ratio"] == pytest.approx(1.0, rel=1e-6) and not r["flagged"] for r in data["accuracy"])
    markdown = (out / "report.md").read_text()
    assert "| matching | point_inlier_ratio |" in markdown and "## KISS-ICP" in markdown
    assert "every statistic within 0.8-1.25" in markdown


def test_stages_command_refuses_a_missing_sequence_in_one_line(town, tmp_path, capsys):
    out = tmp_path / "report"
    status = main(["eval", "stages", "--real", str(town), "00", "--twin", str(tmp_path / "none"), "00",
                   "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and str(tmp_path / "none") in err[0]
    assert not out.exists()
