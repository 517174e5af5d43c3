"""Table I's pooled rows: a setting whose run of a sequence failed has its "all" figures marked as pooled over the
other sequences (report.json's "incomplete", a '*' and a footnote in report.md), never passed off as complete."""

from __future__ import annotations

import json

import numpy as np
import pytest

from plvo.data.trajectory import write_kitti_poses
from plvo.eval.kitti_metric import evaluate
from plvo.eval.report import build_report, report_json, report_markdown
from plvo.eval.report_files import write_report
from plvo.eval.tasks import RunSpec, SequenceSource, TaskResult
from plvo.geometry import se3


def _line(n: int, spacing: float) -> np.ndarray:
    return np.stack([se3.from_rt(se3.so3_exp(np.array([0.0, 0.01 * np.sin(0.1 * k), 0.0])), [0.0, 0.0, spacing * k])
                     for k in range(n)])


def _task(tmp_path, setting: str, seq: str, scale: float | None) -> TaskResult:
    """A finished task whose estimate is the ground truth scaled by `scale`, or (None) a failed one."""
    spec = RunSpec(SequenceSource("root", seq), setting=setting, ablation=setting)
    folder = tmp_path / "runs" / setting / seq
    folder.mkdir(parents=True)
    if scale is None:
        return TaskResult(spec, "failed", "PlvoError: stage X exploded", 0, 0.0, 0.0, None, {}, folder)
    gt = _line(160 if seq == "a" else 120, 1.5)
    est = gt.copy()
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
    from plvo import provenance

    started = provenance.start(["plvo", "eval", "run", "--out", "x"])
    paths = write_report(report, tmp_path / "out", plots=False, started=started)
    data = json.loads(paths["json"].read_text())
    prov = data["provenance"]
    assert prov["command_line"] == "plvo eval run --out x" and prov["started_utc"] == started["started_utc"]
    assert len(prov["load_start"]) == 3 and len(prov["load_end"]) == 3 and prov["finished_utc"]
    assert data["incomplete"]["points_only"] == ["b"]
    assert "Revision " in paths["markdown"].read_text() and "`plvo eval run --out x`" in paths["markdown"].read_text()
