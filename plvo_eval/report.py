"""The paper's Table I from task results: errors per sequence and setting, averaged, as Markdown and JSON
(plvo_eval.report_files writes them with plvo_eval.plots' figures).

Rows are sequences, columns settings (the plvo ablations, then KISS-ICP and KISS-SLAM). Figures are recomputed from
each task folder's gt.txt and poses.txt with plvo_eval.kitti_metric, so they equal `plvo eval metric` on the same
files.
The "all" row is the devkit's pooled figure (every segment of every sequence averaged together, as the KITTI
server computes it); "mean" is the plain mean of the per-sequence figures. A setting whose run of some sequence
failed (or has no ground truth) has its pooled figure over the others only: it is marked, never passed off as over
all of them (report.json's "incomplete": setting -> those sequences; in report.md "0.62*" and a footnote), and its
mean is left out. Sequences shorter than 100 m have no
devkit segment: their cells read "-", and the short-segment table (10/20/40 m, every frame a start) covers them.
Every relative error is given twice: as the devkit defines it, and with each run's constant heading offset against
the truth taken out (plvo_eval.kitti_metric.fit_heading_offset: a real clip's truth can be turned against the sensors
by a degree or more, a floor under every system's error); report.json's "heading_aligned" holds the second reading's
tables and the fitted angles, report.md a table of the angles and the aligned tables after the others.
A setting whose runs count their loop closures (KISS-SLAM) also gets them per sequence: report.json's
"loop_closures" and a table in report.md; plvo's runs say how true each loop they accepted is (its edge against the
ground truth, plvo_eval.revisits) and what each stage of the pipeline left of the heading and the scale
(plvo_eval.stage_drift): report.json's "plvo_loops" and "stage_drift", each a table in report.md.
When the rows hold KITTI twins of both the development set and the held-out one (plvo_eval.splits), the rows are
grouped by set and each set is pooled apart as well ("all (development)", "all (held-out)").
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from plvo_eval.kitti_metric import (
    DEVKIT_LENGTHS,
    SHORT_LENGTHS,
    Evaluation,
    RelativeError,
    SequenceEvaluation,
    evaluate,
)
from plvo_eval.splits import DEVELOPMENT, HELD_OUT, twin_split
from plvo_eval.stage_drift import STAGES
from plvo_eval.tasks import BASELINE_SETTINGS, KISS_SETTING, KISS_SLAM_SETTING, TaskResult, load_poses

TABLES: tuple[tuple[str, str, Any, str], ...] = (  # (json key, title, getter of a RelativeError, format)
    ("t_err_pct", "Translation error [%] (KITTI devkit, 100-800 m)", lambda r: r.t_err_pct, "{:.2f}"),
    ("r_err_deg_per_m", "Rotation error [deg/m] (KITTI devkit, 100-800 m)", lambda r: r.r_err_deg_per_m, "{:.4f}"),
    ("short_t_err_pct", "Translation error [%] over 10/20/40 m, every frame a start", lambda r: r.t_err_pct, "{:.2f}"),
    ("short_r_err_deg_per_m", "Rotation error [deg/m] over 10/20/40 m", lambda r: r.r_err_deg_per_m, "{:.4f}"),
)
LABELS = {
    "full": "Ours (*)",
    "no_depth_priors": "Ours (-)",
    "no_scale_correction": "Ours (#)",
    "points_only": "Point-only",
    "tracker_only": "Tracker only",
    "no_scale_step": "No scale step",
    "no_deskew": "No deskew",
    "keyframe_ndt": "Keyframe NDT",
    "no_lidar_loops": "No lidar loops",
    KISS_SETTING: "KISS-ICP",
    KISS_SLAM_SETTING: "KISS-SLAM",
}


@dataclass(frozen=True)
class Report:
    """settings, sequences: column and row names; evaluations[setting]: the pooled Evaluation over the sequences
    that setting finished (None if none); cells[setting][sequence]: SequenceEvaluation or an error text;
    results: the TaskResults; poses[setting][sequence]: (gt, est) (N,4,4) each."""

    settings: tuple[str, ...]
    sequences: tuple[str, ...]
    evaluations: dict[str, Any]
    cells: dict[str, dict[str, SequenceEvaluation | str]]
    results: tuple[TaskResult, ...]
    poses: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]
    # split (plvo_eval.splits) -> setting -> pooled Evaluation over that split's sequences (None if none finished);
    # empty unless the rows hold twins of both splits
    split_evaluations: dict[str, dict[str, Any]] = field(default_factory=dict)


def _unique(values: Iterable[str]) -> tuple[str, ...]:
    return tuple(dict.fromkeys(values))


def build_report(results: Sequence[TaskResult]) -> Report:
    """TaskResults (any order) -> Report with every figure recomputed from the task folders."""
    settings = _unique(r.spec.setting for r in results)
    # plvo's settings first, then the lidar-only baselines in a fixed order
    settings = tuple(s for s in settings if s not in BASELINE_SETTINGS) + tuple(
        b for b in BASELINE_SETTINGS if b in settings)
    sequences = _unique(r.spec.source.name for r in results)
    groups = {sp: [q for q in sequences if twin_split(q) == sp] for sp in (DEVELOPMENT, HELD_OUT)}
    if all(groups.values()):  # development rows first, then the held-out ones, then the rest
        sequences = (*groups[DEVELOPMENT], *groups[HELD_OUT], *(q for q in sequences if twin_split(q) is None))
    else:
        groups = {}
    cells: dict[str, dict[str, Any]] = {s: {} for s in settings}
    poses: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {s: {} for s in settings}
    for r in results:
        name, setting = r.spec.source.name, r.spec.setting
        gt, est = load_poses(r) if r.ok else (None, None)
        if not r.ok:
            cells[setting][name] = f"failed: {r.error.splitlines()[0] if r.error else 'unknown error'}"
        elif gt is None or est is None:
            cells[setting][name] = "no ground truth"
        else:
            poses[setting][name] = (gt, est)
    evaluations = {}
    for setting in settings:
        pairs = {seq: poses[setting][seq] for seq in sequences if seq in poses[setting]}
        evaluation = evaluations[setting] = evaluate(pairs) if pairs else None
        if evaluation is not None:
            cells[setting].update({ev.name: ev for ev in evaluation.sequences})
    splits: dict[str, dict[str, Any]] = {}
    for split, seqs in groups.items():
        splits[split] = {}
        for setting in settings:
            pairs = {seq: poses[setting][seq] for seq in seqs if seq in poses[setting]}
            splits[split][setting] = evaluate(pairs) if pairs else None
    return Report(settings, sequences, evaluations, cells, tuple(results), poses, splits)


def _num(value: float) -> float | None:
    return None if value is None or not math.isfinite(value) else float(value)


def _rel(ev: SequenceEvaluation | Evaluation, key: str, aligned: bool = False) -> RelativeError:
    """The RelativeError a table's key reads: short or devkit segments, as they are or heading-aligned."""
    if key.startswith("short"):
        return ev.short_aligned if aligned else ev.short
    return ev.kitti_aligned if aligned else ev.kitti


def incomplete(report: Report) -> dict[str, list[str]]:
    """setting -> the report's sequences its pooled figures leave out (a failed run, no ground truth, no task);
    empty when they pool every sequence."""
    return {s: [q for q in report.sequences if not isinstance(report.cells[s].get(q), SequenceEvaluation)]
            for s in report.settings}


def table_values(report: Report, key: str, getter: Callable[[RelativeError], float], aligned: bool = False
                 ) -> dict[str, dict[str, float | None]]:
    """setting -> {sequence: value or None, "all": pooled, "mean": mean of the sequences' values}; aligned: of the
    heading-aligned errors."""
    out: dict[str, dict[str, float | None]] = {}
    for setting in report.settings:
        col: dict[str, float | None] = {}
        for seq in report.sequences:
            cell = report.cells[setting].get(seq)
            col[seq] = _num(getter(_rel(cell, key, aligned))) if isinstance(cell, SequenceEvaluation) else None
        ev = report.evaluations[setting]
        col["all"] = None if ev is None else _num(getter(_rel(ev, key, aligned)))
        for split, evs in report.split_evaluations.items():
            ev_split = evs[setting]
            col[f"all ({split})"] = None if ev_split is None else _num(getter(_rel(ev_split, key, aligned)))
        vals = [v for v in (col[s] for s in report.sequences) if v is not None]
        complete = len(vals) == len(report.sequences)
        col["mean"] = float(np.mean(vals)) if vals and complete else None
        out[setting] = col
    return out


def _cell_value(report: Report, setting: str, seq: str, attr: str) -> float | None:
    cell = report.cells[setting].get(seq)
    if not isinstance(cell, SequenceEvaluation):
        return None
    if attr == "final_drift_m":
        gt, est = report.poses[setting][seq]
        return float(np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]))
    return _num({"ate_m": cell.ate_se3.rmse_m, "ate_sim3_m": cell.ate_sim3.rmse_m}[attr])


def report_json(report: Report) -> dict[str, Any]:
    """The tables as one JSON object (stable keys; null where there is no figure)."""
    by_task = {(r.spec.setting, r.spec.source.name): r for r in report.results}
    data: dict[str, Any] = {
        "settings": list(report.settings),
        "labels": {s: LABELS.get(s, s) for s in report.settings},
        "sequences": list(report.sequences),
        "devkit_lengths_m": list(DEVKIT_LENGTHS),
        "short_lengths_m": list(SHORT_LENGTHS),
        # the sequences each setting's pooled ("all") figures leave out: they are over the others only
        "incomplete": incomplete(report),
    }
    for key, _title, getter, _fmt in TABLES:
        data[key] = table_values(report, key, getter)
    for attr in ("ate_m", "ate_sim3_m", "final_drift_m"):
        data[attr] = {s: {q: _cell_value(report, s, q, attr) for q in report.sequences} for s in report.settings}
    data["short_by_length_t_err_pct"] = _by_length(report, aligned=False)
    data["heading_aligned"] = heading_aligned_json(report)
    data["path_length_m"] = {q: _path_length(report, q) for q in report.sequences}
    closures = loop_closures(report)
    if closures:  # only with a setting that counts them: the other reports keep their keys
        data["loop_closures"] = closures
    if report.split_evaluations:
        data["splits"] = {split: [q for q in report.sequences if twin_split(q) == split]
                          for split in report.split_evaluations}
    plvo_loops, drift = _plvo_details(report)
    if plvo_loops:
        data["plvo_loops"] = plvo_loops
    if drift:
        data["stage_drift"] = drift
    data["tasks"] = {
        s: {
            q: {"status": t.status, "error": t.error, "fps": t.fps, "seconds": t.seconds, "folder": str(t.folder)}
            for q in report.sequences
            if (t := by_task.get((s, q))) is not None
        }
        for s in report.settings
    }
    return data


def _by_length(report: Report, aligned: bool) -> dict[str, dict[str, float | None]]:
    """setting -> short length -> translation error (%) of all sequences' segments of that length pooled."""
    return {s: {f"{e.length_m:g}": _num(e.t_err_pct) for e in _rel(ev, "short", aligned).per_length}
            if ev is not None else {} for s, ev in report.evaluations.items()}


def heading_aligned_json(report: Report) -> dict[str, Any]:
    """The second reading: "heading_offset_deg" (setting -> sequence -> the angle fitted to that run, null without
    one), and the tables of TABLES and "short_by_length_t_err_pct" with each run's heading offset taken out."""
    angles = {s: {q: _num(c.heading_offset_deg) if isinstance(c := report.cells[s].get(q), SequenceEvaluation)
                  else None for q in report.sequences} for s in report.settings}
    data: dict[str, Any] = {"heading_offset_deg": angles}
    for key, _title, getter, _fmt in TABLES:
        data[key] = table_values(report, key, getter, aligned=True)
    data["short_by_length_t_err_pct"] = _by_length(report, aligned=True)
    return data


def loop_closures(report: Report) -> dict[str, dict[str, dict[str, Any] | None]]:
    """setting -> sequence -> {"accepted": loop closures the run accepted, "local_maps": its local maps,
    "closures": [{reference_map, query_map, reference_frames, query_frames}, ...]}, None where the run failed; for the
    settings whose runs count their loop closures (KISS-SLAM), none for the others."""
    out: dict[str, dict[str, dict[str, Any] | None]] = {}
    for setting in report.settings:
        tasks = {r.spec.source.name: r for r in report.results if r.spec.setting == setting}
        if not any(r.spec.method == "kiss_slam" or "loop_closures" in r.details for r in tasks.values()):
            continue
        col: dict[str, dict[str, Any] | None] = {}
        for seq in report.sequences:
            task = tasks.get(seq)
            details = task.details if task is not None and task.ok else {}
            col[seq] = None if "loop_closures" not in details else {
                "accepted": int(details["loop_closures"]),
                "local_maps": details.get("local_maps"),
                "closures": list(details.get("closures", [])),
            }
        out[setting] = col
    return out


def _plvo_details(report: Report) -> tuple[dict[str, Any], dict[str, Any]]:
    """From plvo's runs' details: setting -> sequence -> {accepted, true, worst edge errors, loops} and setting ->
    sequence -> stage -> drift summary (plvo_eval.stage_drift); sequences without ground truth left out."""
    loops: dict[str, Any] = {}
    drift: dict[str, Any] = {}
    for r in report.results:
        d = r.details if r.ok else {}
        name, setting = r.spec.source.name, r.spec.setting
        if "loops" in d:
            edges = d["loops"]
            loops.setdefault(setting, {})[name] = {
                "accepted": len(edges), "true": sum(1 for e in edges if e["true"]),
                "max_edge_error_m": max((e["edge_error_m"] for e in edges), default=None),
                "max_edge_error_deg": max((e["edge_error_deg"] for e in edges), default=None),
                "loops": edges}
        if "stage_drift" in d:
            drift.setdefault(setting, {})[name] = d["stage_drift"]
    return loops, drift


def _plvo_loops_markdown(report: Report, loops: dict[str, Any]) -> list[str]:
    settings = [s for s in report.settings if s in loops]
    head = ["Seq."] + [LABELS.get(s, s) for s in settings]
    lines = ["**plvo's accepted loops: true / accepted** (true: the loop edge within 1 m and 2 deg of the ground "
             "truth's relative pose; in brackets the largest edge error, m / deg)", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for seq in report.sequences:
        cells = []
        for s in settings:
            c = loops[s].get(seq)
            if c is None:
                cells.append("-")
            elif c["accepted"]:
                cells.append(f"{c['true']} / {c['accepted']} ({c['max_edge_error_m']:.2f} / "
                             f"{c['max_edge_error_deg']:.2f})")
            else:
                cells.append("0 / 0")
        lines.append(f"| {seq} | " + " | ".join(cells) + " |")
    return lines + [""]


def _drift_markdown(report: Report, drift: dict[str, Any]) -> list[str]:
    """One table a plvo setting: rows the sequences, columns the stages, cells the heading lost over 100 m
    (deg) / the distance error over 100 m (%)."""
    lines: list[str] = []
    for setting in (s for s in report.settings if s in drift):
        lines += [f"**Where the heading and the scale go: {LABELS.get(setting, setting)}** (each keyframe step as "
                  "the stage left it against the ground truth; per 100 m of path: heading lost in deg / distance "
                  "error in %, means over 100 m stretches; plvo_eval.stage_drift)", "",
                  "| Seq. | " + " | ".join(STAGES) + " |", "|" + "---|" * (len(STAGES) + 1)]
        for seq in report.sequences:
            by_stage = drift[setting].get(seq)
            if by_stage is None:
                continue
            cells = []
            for stage in STAGES:
                v = by_stage.get(stage, {})
                yaw, scale = v.get("yaw_deg_per_100m"), v.get("scale_pct")
                ok = v.get("steps") and yaw is not None and scale is not None and math.isfinite(yaw)
                cells.append(f"{yaw:.3f} / {scale:.2f}" if ok else "-")
            lines.append(f"| {seq} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines


def _closures_markdown(report: Report, closures: dict[str, dict[str, dict[str, Any] | None]]) -> list[str]:
    """The loop closures table (a row a sequence, a column a setting that counts them) and the closed pairs."""
    settings = list(closures)
    head = ["Seq."] + [LABELS.get(s, s) for s in settings]
    lines = ["**Loop closures accepted** (KISS-SLAM: between its local maps of ~100 m of travel, each checked by ICP "
             "overlap; in brackets the run's local maps; frames are rows of the run's poses.txt)", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    pairs = []
    for seq in report.sequences:
        cells = []
        for s in settings:
            cell = closures[s][seq]
            cells.append("-" if cell is None else f"{cell['accepted']} ({cell['local_maps']})")
            for c in [] if cell is None else cell["closures"]:
                (r0, r1), (q0, q1) = c["reference_frames"], c["query_frames"]
                pairs.append(f"- {LABELS.get(s, s)} / {seq}: local map {c['query_map']} (frames {q0}-{q1}) to "
                             f"{c['reference_map']} (frames {r0}-{r1})")
        lines.append(f"| {seq} | " + " | ".join(cells) + " |")
    return lines + ([""] + pairs if pairs else []) + [""]


def _path_length(report: Report, seq: str) -> float | None:
    for setting in report.settings:
        if seq in report.poses[setting]:
            gt = report.poses[setting][seq][0]
            return float(np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)))
    return None


def _md_table(
    report: Report, title: str, values: dict[str, dict[str, float | None]], fmt: str,
    rows: Sequence[str] | None = None, first: str = "Seq.",
    pooled_rows: tuple[str, ...] = ("all",), missing: dict[str, list[str]] | None = None,
) -> list[str]:
    """One Markdown table; a pooled row's figure of a setting in `missing` (setting -> sequences it leaves out)
    carries a '*' and the table a footnote naming them."""
    missing = {s: q for s, q in (missing or {}).items() if q}
    head = [first] + [LABELS.get(s, s) for s in report.settings]
    lines = [f"**{title}**", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    marked = set()
    split_rows = tuple(f"all ({split})" for split in report.split_evaluations)
    for row in rows if rows is not None else (*report.sequences, "all", *split_rows, "mean"):
        cells = []
        for s in report.settings:
            value = values[s].get(row)
            star = row in pooled_rows and s in missing and value is not None
            marked |= {s} if star else set()
            cells.append("-" if value is None else fmt.format(value) + ("*" if star else ""))
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    for s in report.settings:
        if s in marked:
            lines += ["", f"\\* {LABELS.get(s, s)}: pooled without {', '.join(missing[s])} (no figure there: see the "
                          "failed runs), so over fewer sequences than the table's rows."]
    return lines + [""]


def pooled_label(report: Report, setting: str) -> str:
    """A setting's label for a figure of its pooled segments, naming the sequences they leave out."""
    left_out = incomplete(report)[setting]
    label = LABELS.get(setting, setting)
    return f"{label} (without {', '.join(left_out)})" if left_out else label


def _heading_aligned_markdown(report: Report, aligned: dict[str, Any], length_rows: list[str],
                              missing: dict[str, list[str]]) -> list[str]:
    """The fitted angles and the relative-error tables again with each run's heading offset taken out (the devkit
    ones only when some sequence has a devkit segment)."""
    lines = ["**With the heading offset taken out**: each run's estimate turned about the camera's vertical axis by "
             "the one angle that best maps its segments onto the truth's (plvo_eval.kitti_metric.fit_heading_offset)."
             " A real clip's truth can be turned against the sensors' frame (KITTI 04's by about 0.3 deg, raw drive "
             "0009's GPS/INS truth by about 1.45 deg), a floor of about that angle in radians under every system's "
             "error; the devkit reading above stays the one to compare with published figures.", ""]
    lines += _md_table(report, "Heading offset fitted [deg] (> 0: the truth runs right of the estimate)",
                       aligned["heading_offset_deg"], "{:.3f}", rows=report.sequences)
    has_devkit = any(v is not None for col in aligned["t_err_pct"].values() for v in col.values())
    for key, title, _getter, fmt in TABLES:
        if key.startswith("short") or has_devkit:
            lines += _md_table(report, f"{title}, heading offset taken out", aligned[key], fmt, missing=missing)
    lines += _md_table(report, "Translation error [%] by short length, all sequences pooled, heading offset taken "
                       "out", aligned["short_by_length_t_err_pct"], "{:.2f}", rows=length_rows, first="length [m]",
                       pooled_rows=tuple(length_rows), missing=missing)
    return lines


def report_markdown(report: Report, data: dict[str, Any] | None = None) -> str:
    """Table I and friends as Markdown (one table per figure, sequences as rows, settings as columns)."""
    data = data or report_json(report)
    lines = ["# Evaluation", ""]
    legend = ", ".join(f"{LABELS.get(s, s)} = `{s}`" for s in report.settings)
    lengths = ", ".join(f"{q}: {v:.1f} m" for q, v in data["path_length_m"].items() if v is not None)
    lines += [f"Settings: {legend}.", f"Ground-truth path lengths: {lengths}.", "",
              "`all`: every segment of every sequence averaged together (the devkit's figure); `mean`: mean of the "
              "sequences. `-`: no figure (a sequence shorter than 100 m has no devkit segment; a failed run).", ""]
    missing = data["incomplete"]
    for key, title, _getter, fmt in TABLES:
        lines += _md_table(report, title, data[key], fmt, missing=missing)
    by_length = data["short_by_length_t_err_pct"]
    rows = [f"{v:g}" for v in data["short_lengths_m"]]
    lines += _md_table(report, "Translation error [%] by short length, all sequences pooled", by_length, "{:.2f}",
                       rows=rows, first="length [m]", pooled_rows=tuple(rows), missing=missing)
    lines += _heading_aligned_markdown(report, data["heading_aligned"], rows, missing)
    for attr, title in (("ate_m", "ATE RMSE [m] after SE(3) alignment"), ("final_drift_m", "Final drift [m]")):
        lines += _md_table(report, title, data[attr], "{:.3f}", rows=report.sequences)
    if data.get("loop_closures"):
        lines += _closures_markdown(report, data["loop_closures"])
    if data.get("plvo_loops"):
        lines += _plvo_loops_markdown(report, data["plvo_loops"])
    if data.get("stage_drift"):
        lines += _drift_markdown(report, data["stage_drift"])
    if data.get("splits"):
        lines += ["Development set (the defaults were tuned on it): " + ", ".join(data["splits"][DEVELOPMENT])
                  + "; held out: " + ", ".join(data["splits"][HELD_OUT]) + " (plvo_eval.splits).", ""]
    failed = [(s, q, t["error"]) for s, col in data["tasks"].items() for q, t in col.items() if t["status"] != "ok"]
    if failed:
        lines += ["**Failed runs**", ""] + [f"- {s} / {q}: {e.splitlines()[0] if e else '?'}" for s, q, e in failed]
        lines.append("")
    prov = data.get("provenance")
    if prov:
        m = prov["machine"]
        rev = (prov["revision"] or "unknown")[:12] + ("+dirty" if prov["dirty"] else "")
        lines += [f"Revision {rev}, {prov.get('finished_utc', prov['started_utc'])}; {m['cpu_model']}, "
                  f"{m['cpu_count']} cores, {m['mem_total_mb']} MB, {m['os']}; load {prov['load_start'][0]:.2f} -> "
                  f"{prov.get('load_end', prov['load_start'])[0]:.2f}; `{prov['command_line']}`", ""]
    return "\n".join(lines)
