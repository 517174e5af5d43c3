"""Table I's pooled rows: a setting whose run of a sequence failed has its "all" figures marked as pooled over the
other sequences (report.json's "incomplete", a '*' and a footnote in report.md), never passed off as complete. The
second reading: each run's heading offset fitted, reported and taken out (report.json's "heading_aligned")."""

from __future__ import annotations

import json

import numpy as np
import pytest

from plvo.data.trajectory import write_kitti_poses
from plvo.geometry import se3
from plvo_eval.kitti_metric import evaluate
from plvo_eval.report import build_report, report_json, report_markdown
from plvo_eval.report_files import write_report
from plvo_eval.tasks import RunSpec, SequenceSource, TaskResult


def _line(n: int, spacing: float) -> np.ndarray:
    return np.stack([se3.from_rt(se3.so3_exp(np.array([0.0, 0.01 * np.sin(0.1 * k), 0.0])), [0.0, 0.0, spacing * k])
                     for k in range(n)])


def _task(tmp_path, setting: str, seq: str, scale: float | None, heading_deg: float = 0.0) -> TaskResult:
    """A finished task whose estimate is the ground truth scaled by `scale` and turned `heading_deg` to the left of
    it (the truth's heading offset against the estimate), or (None) a failed one."""
    spec = RunSpec(SequenceSource("root", seq), setting=setting, ablation=setting)
    folder = tmp_path / "runs" / setting / seq
    folder.mkdir(parents=True)
    if scale is None:
        return TaskResult(spec, "failed", "PlvoError: stage X exploded", 0, 0.0, 0.0, None, {}, folder)
    gt = _line(160 if seq == "a" else 120, 1.5)
    R = se3.from_rt(se3.so3_exp(np.array([0.0, -np.radians(heading_deg), 0.0])), np.zeros(3))
    est = R @ gt @ R.T
    est[:, :3, 3] *= scale
    write_kitti_poses(folder / "gt.txt", gt)
    write_kitti_poses(folder / "poses.txt", est)
    return TaskResult(spec, "ok", "", len(gt), 1.0, len(gt), None, {}, folder)


@pytest.fixture
def report(tmp_path):
    results = [_task(tmp_path, "full", "a", 1.01), _task(tmp_path, "full", "b", 1.03),
               _task(tmp_path, "points_only", "a", 1.02), _task(tmp_path, "points_only", "b", None)]
    return build_report(results)


def test_a_failed_sequence_marks_the_pooled_row(report):
    data = report_json(report)
    assert data["incomplete"] == {"full": [], "points_only": ["b"]}
    t = data["t_err_pct"]
    assert t["points_only"]["b"] is None and t["points_only"]["mean"] is None  # no mean over part of the rows
    # the pooled figure left is over "a" alone: what the marker says
    alone = evaluate({"a": report.poses["points_only"]["a"]}).kitti.t_err_pct
    assert t["points_only"]["all"] == pytest.approx(alone) and 1.5 < alone < 2.5
    assert t["full"]["mean"] is not None and 1.0 < t["full"]["all"] < 3.0  # over a (1 %) and b (3 %)
    md = report_markdown(report, data)
    table = md.split("**Translation error [%] (KITTI devkit, 100-800 m)**")[1].split("**")[0]
    all_row = next(line for line in table.splitlines() if line.startswith("| all |"))
    cells = [c.strip() for c in all_row.strip("|").split("|")]
    assert cells[1] == f"{t['full']['all']:.2f}" and cells[2] == f"{t['points_only']['all']:.2f}*"
    assert "Point-only: pooled without b" in table and "Ours (*): pooled" not in table
    by_length = md.split("by short length, all sequences pooled**")[1].split("**")[0]
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in by_length.splitlines()
            if line.startswith("| 10 |") or line.startswith("| 20 |") or line.startswith("| 40 |")]
    assert len(rows) == 3 and all(not r[1].endswith("*") and r[2].endswith("*") for r in rows), rows
    assert "Point-only: pooled without b" in by_length


def test_a_complete_report_has_no_marker(tmp_path):
    results = [_task(tmp_path, "full", "a", 1.01), _task(tmp_path, "full", "b", 1.03)]
    data = report_json(build_report(results))
    assert data["incomplete"] == {"full": []}
    md = report_markdown(build_report(results), data)
    assert "pooled without" not in md and "*|" not in md.replace(" ", "")


def test_report_json_carries_its_provenance(report, tmp_path):
    from plvo_eval import provenance

    started = provenance.start(["plvo", "eval", "run", "--out", "x"])
    paths = write_report(report, tmp_path / "out", plots=False, started=started)
    data = json.loads(paths["json"].read_text())
    prov = data["provenance"]
    assert prov["command_line"] == "plvo eval run --out x" and prov["started_utc"] == started["started_utc"]
    assert len(prov["load_start"]) == 3 and len(prov["load_end"]) == 3 and prov["finished_utc"]
    assert data["incomplete"]["points_only"] == ["b"]
    assert "Revision " in paths["markdown"].read_text() and "`plvo eval run --out x`" in paths["markdown"].read_text()


def _md_rows(md: str, title: str) -> dict[str, list[str]]:
    """The rows of report.md's table titled `title`: first cell -> the others."""
    table = md.split(f"**{title}**")[1].split("**")[0]
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in table.splitlines() if line.startswith("| ")]
    return {r[0]: r[1:] for r in rows[1:]}


def test_heading_offsets_are_fitted_reported_and_taken_out(tmp_path):
    offsets = {("full", "a"): 0.4, ("full", "b"): -0.7, ("kiss", "a"): 1.1, ("kiss", "b"): 0.2}
    results = [_task(tmp_path, s, q, 1.002, heading_deg=d) for (s, q), d in offsets.items()]
    report = build_report(results)
    data = report_json(report)
    aligned = data["heading_aligned"]
    for (s, q), d in offsets.items():  # estimates exact but for the turn and the 0.2 % scale: the angle comes back
        assert aligned["heading_offset_deg"][s][q] == pytest.approx(d, abs=1e-6)
        # the offset is most of the raw error; taken out, the 0.2 % scale error is left
        assert data["short_t_err_pct"][s][q] > 0.9 * np.radians(abs(d)) * 100
        assert aligned["short_t_err_pct"][s][q] == pytest.approx(0.2, rel=0.15)
        assert aligned["t_err_pct"][s][q] == pytest.approx(0.2, rel=0.05)
    for s in ("full", "kiss"):  # pooled as the raw segments are: all segments of both runs, each aligned
        ev = evaluate({q: report.poses[s][q] for q in ("a", "b")})
        assert aligned["short_t_err_pct"][s]["all"] == pytest.approx(ev.short_aligned.t_err_pct, rel=1e-12)
        assert aligned["t_err_pct"][s]["all"] == pytest.approx(ev.kitti_aligned.t_err_pct, rel=1e-12)
        assert set(aligned["short_by_length_t_err_pct"][s]) == {"10", "20", "40"}
    assert data["t_err_pct"]["kiss"]["a"] > 1.5  # the devkit reading stays as it was
    md = report_markdown(report, data)
    angles = _md_rows(md, "Heading offset fitted [deg] (> 0: the truth runs right of the estimate)")
    assert angles == {"a": ["0.400", "1.100"], "b": ["-0.700", "0.200"]}
    short = _md_rows(md, "Translation error [%] over 10/20/40 m, every frame a start, heading offset taken out")
    assert short["a"] == [f"{aligned['short_t_err_pct'][s]['a']:.2f}" for s in ("full", "kiss")]
    devkit = _md_rows(md, "Translation error [%] (KITTI devkit, 100-800 m), heading offset taken out")
    assert devkit["all"] == [f"{aligned['t_err_pct'][s]['all']:.2f}" for s in ("full", "kiss")]
    assert "by short length, all sequences pooled, heading offset taken out**" in md


def test_a_failed_run_has_no_angle_and_marks_the_aligned_pooled_row(report):
    data = report_json(report)
    aligned = data["heading_aligned"]
    assert aligned["heading_offset_deg"]["points_only"]["b"] is None
    assert aligned["heading_offset_deg"]["full"]["a"] == pytest.approx(0.0, abs=1e-9)  # none put in
    md = report_markdown(report, data)
    rows = _md_rows(md, "Translation error [%] over 10/20/40 m, every frame a start, heading offset taken out")
    assert rows["b"][1] == "-" and rows["all"][1].endswith("*") and not rows["all"][0].endswith("*")


def test_aligned_figures_pool_the_development_and_held_out_twins_apart(tmp_path):
    offsets = {"twin04": 0.3, "twin07": -0.9}  # one development twin, one held out
    report = build_report([_task(tmp_path, "full", q, 1.01, heading_deg=d) for q, d in offsets.items()])
    aligned = report_json(report)["heading_aligned"]
    for q, split in (("twin04", "development"), ("twin07", "held-out")):
        assert aligned["heading_offset_deg"]["full"][q] == pytest.approx(offsets[q], abs=1e-6)
        alone = evaluate({q: report.poses["full"][q]})
        assert aligned["short_t_err_pct"]["full"][f"all ({split})"] == pytest.approx(alone.short_aligned.t_err_pct)
        assert aligned["short_t_err_pct"]["full"][f"all ({split})"] == pytest.approx(1.0, rel=0.15)
