"""Where real frames cost each system, stage by stage: a real clip's per-stage statistics beside its twin's.

Both sides are plvo_eval.stage_runs.SideResult (plvo and KISS-ICP run on one sequence, with their statistics and
accuracy). Each statistic is compared by its `value` (plvo_eval.stage_stats.describe: the median of a distribution,
the mean of a share, a run's own figure): the ratio twin / real, flagged outside BAND (0.8-1.25: the twin within
25 % of the real clip). A signed figure (a bias, the signed scale correction) is shown without a ratio: its
magnitude is compared in a statistic of its own. A statistic that is 0 on both sides is equal (ratio 1); one that
is 0 or missing on one side only is flagged without a ratio. Shares within one percentage point (SHARE_FLOOR) of
each other are not flagged, whatever their ratio. The accuracy (short-segment errors over 10 / 20 / 40 m,
as they are and with the heading offset taken out where the metric gives it) is compared likewise, flagged outside
ACCURACY_BAND (0.75-1.33, real / twin within 0.75-1.33 either way).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from plvo_eval.stage_runs import SideResult
from plvo_eval.stage_stats import DISTRIBUTION, SHARE, SIGNED

BAND = (0.8, 1.25)
# Shares closer than this (one percentage point) are not flagged: a reason that 1 keypoint in 10000 has is noise
SHARE_FLOOR = 0.01
ACCURACY_BAND = (0.75, 1.0 / 0.75)
SYSTEMS = {"plvo": "plvo", "kiss": "KISS-ICP"}


def ratio(real: float | None, twin: float | None, signed: bool = False) -> float | None:
    """twin / real, 1 when both are 0, None when signed, either is missing or real alone is 0."""
    if signed or real is None or twin is None:
        return None
    if real == 0:
        return 1.0 if twin == 0 else None
    return twin / real


def flagged(real: float | None, twin: float | None, r: float | None, band: tuple[float, float],
            kind: str = DISTRIBUTION) -> bool:
    """Whether a statistic stands out: its ratio outside band, or a value on one side only or 0 on one side only;
    never a signed figure, nor a share whose two values are within SHARE_FLOOR of each other."""
    if kind == SIGNED:
        return False
    if kind == SHARE and real is not None and twin is not None and abs(twin - real) < SHARE_FLOOR:
        return False
    if r is None:  # a value on one side only, or real 0 and twin not
        return not (real is None and twin is None)
    return not band[0] <= r <= band[1]


def compare(real: Mapping[str, Mapping[str, Any]], twin: Mapping[str, Mapping[str, Any]],
            band: tuple[float, float] = BAND) -> list[dict[str, Any]]:
    """Two runs' statistics (name -> describe entry) -> one row a statistic (in real's order, then twin's own):
    name, stage, unit, kind, real and twin entries, ratio twin / real, flagged."""
    rows = []
    for name in [*real, *(k for k in twin if k not in real)]:
        a, b = real.get(name), twin.get(name)
        meta = a if a is not None else b
        assert meta is not None
        signed = meta["kind"] == SIGNED
        va, vb = (None if e is None else e["value"] for e in (a, b))
        r = ratio(va, vb, signed)
        rows.append({"name": name, "stage": meta["stage"], "unit": meta["unit"], "kind": meta["kind"],
                     "real": a, "twin": b, "ratio": r, "flagged": flagged(va, vb, r, band, meta["kind"])})
    return rows


def compare_accuracy(real: SideResult, twin: SideResult) -> list[dict[str, Any]]:
    """Each system's short-segment errors (%), by length and reading (as they are / heading offset taken out),
    real beside twin -> rows: system, reading, length, real, twin, ratio, flagged (ACCURACY_BAND)."""
    rows = []
    for system in SYSTEMS:
        a, b = real.accuracy.get(system), twin.accuracy.get(system)
        if not a or not b:
            continue
        for reading, key in (("as is", "t_err_pct"), ("heading offset out", "aligned_t_err_pct")):
            if a.get(key) is None or b.get(key) is None:
                continue
            for length in a[key]:
                va, vb = a[key][length], b[key].get(length)
                if va is None and vb is None:  # no segment of this length on either side
                    continue
                r = ratio(va, vb)
                rows.append({"system": system, "reading": reading, "length_m": length, "real": va, "twin": vb,
                             "ratio": r, "flagged": flagged(va, vb, r, ACCURACY_BAND)})
    return rows


def stage_report(real: SideResult, twin: SideResult) -> dict[str, Any]:
    """The report as JSON-able data: both sides, the accuracy rows, and per system the statistic rows."""
    return {"band": list(BAND), "accuracy_band": [round(v, 4) for v in ACCURACY_BAND],
            "real": real.to_json(), "twin": twin.to_json(), "accuracy": compare_accuracy(real, twin),
            "plvo": compare(real.plvo, twin.plvo), "kiss": compare(real.kiss, twin.kiss)}


def standing_out(rows: list[dict[str, Any]], k: int = 8) -> list[dict[str, Any]]:
    """The flagged rows, the farthest from 1 first (log of the ratio; one-sided rows last)."""
    def distance(row: dict[str, Any]) -> float:
        r = row["ratio"]
        return abs(math.log(r)) if r is not None and r > 0 else -1.0
    return sorted((r for r in rows if r["flagged"]), key=distance, reverse=True)[:k]


# ---- markdown --------------------------------------------------------------------------------------------------


def _num(v: float | None) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    a = abs(v)
    if a != 0 and (a >= 1e5 or a < 1e-3):
        return f"{v:.3g}"
    return f"{v:.4g}" if a < 100 else f"{v:.0f}"


def _cell(entry: Mapping[str, Any] | None) -> str:
    if entry is None:
        return "-"
    return f"{_num(entry['value'])} (n {entry['n']})"


def _ratio_cell(row: Mapping[str, Any]) -> str:
    text = "signed" if row["kind"] == SIGNED else _num(row["ratio"])
    return f"**{text}**" if row["flagged"] else text


def _source_line(side: Mapping[str, Any]) -> str:
    s = side["source"]
    frames = f", frames {s['frames']}" if s.get("frames") else ""
    return f"`{s['root']}` sequence `{s['sequence']}`{frames}: {side['n_frames']} frames"


def report_markdown(data: Mapping[str, Any], command: str = "") -> str:
    """stage_report's data -> report.md: the sources, the accuracy, what stands out, the tables per system."""
    lo, hi = data["band"]
    lines = ["# Stage by stage: real clip and twin", ""]
    if command:
        lines += [f"Command: `{command}`", ""]
    lines += [f"- real: {_source_line(data['real'])}", f"- twin: {_source_line(data['twin'])}", "",
              f"Each statistic's figure is the median of a distribution or the mean of a share (n: how many values), "
              f"a run's own figure for the drifts (n: the steps it stands on). Flagged (bold): twin / real outside "
              f"{lo:g}-{hi:g}, or a value (or a non-zero one) on one side only; shares within "
              f"{100 * SHARE_FLOOR:g} percentage point of each other are not flagged; signed figures have no ratio.",
              ""]
    acc = data["accuracy"]
    if acc:
        alo, ahi = data["accuracy_band"]
        lines += [f"## Accuracy: translation error over short segments (%, every frame a start; flagged outside "
                  f"{alo:g}-{ahi:g})", "", "| system | reading | length m | real | twin | twin / real |",
                  "|---|---|---:|---:|---:|---:|"]
        for r in acc:
            rc = _num(r["ratio"])
            lines.append(f"| {SYSTEMS[r['system']]} | {r['reading']} | {r['length_m']} | {_num(r['real'])} | "
                         f"{_num(r['twin'])} | {f'**{rc}**' if r['flagged'] else rc} |")
        offsets = []
        for system, name in SYSTEMS.items():
            a = data["real"]["accuracy"].get(system, {})
            b = data["twin"]["accuracy"].get(system, {})
            if a.get("heading_offset_deg") is not None:
                offsets.append(f"{name} {_num(a['heading_offset_deg'])} deg real, "
                               f"{_num(b.get('heading_offset_deg'))} deg twin")
        if offsets:
            lines += ["", "Heading offsets taken out: " + "; ".join(offsets) + "."]
        lines.append("")
    lines += _kiss_ways(data)
    lines += _shared(data)
    lines += ["## What stands out", ""]
    for system, name in SYSTEMS.items():
        top = standing_out(data[system])
        if not top:
            lines.append(f"- {name}: every statistic within {lo:g}-{hi:g}.")
            continue
        parts = [f"{r['name']} {_num(_value(r['real']))} -> {_num(_value(r['twin']))}"
                 + (f" (x{_num(r['ratio'])})" if r["ratio"] is not None else "") for r in top]
        lines.append(f"- {name}, flagged {sum(r['flagged'] for r in data[system])} of {len(data[system])}, "
                     f"farthest first: " + "; ".join(parts) + ".")
    lines.append("")
    for system, name in SYSTEMS.items():
        lines += [f"## {name}", "", "| stage | statistic | unit | real | twin | twin / real |",
                  "|---|---|---|---:|---:|---:|"]
        for r in data[system]:
            lines.append(f"| {r['stage']} | {r['name']} | {r['unit']} | {_cell(r['real'])} | {_cell(r['twin'])} | "
                         f"{_ratio_cell(r)} |")
        lines.append("")
    return "\n".join(lines)


def _shared(data: Mapping[str, Any]) -> list[str]:
    """The table of what plvo's and KISS-ICP's segment errors share on each side (plvo_eval.shared_error)."""
    rows = [(side, length, v) for side in ("real", "twin") for length, v in (data[side].get("shared") or {}).items()]
    if not rows:
        return []
    lines = ["## What plvo's and KISS-ICP's errors share", "",
             "Per segment length: the correlation of the two systems' segment errors and the rms of their shared part "
             "by axis (x right, y down, z ahead; % of the length, the heading offset taken out), and each system's "
             "own error (rms over segments, the shared part taken out) beside its whole one. Two independent "
             "systems share only what neither made: the truth's own errors, or something both read in the scans "
             "(plvo_eval.shared_error).", "",
             "| side | length m | correlation x / y / z | shared x / y / z | plvo own / whole | KISS-ICP own / whole |",
             "|---|---:|---|---|---|---|"]
    for side, length, v in rows:
        corr = " / ".join(_num(c) for c in v["correlation"])
        shared = " / ".join(_num(c) for c in v["shared_rms"])
        lines.append(f"| {side} | {length} | {corr} | {shared} | {_num(v['own_a_norm'])} / {_num(v['total_a_norm'])} "
                     f"| {_num(v['own_b_norm'])} / {_num(v['total_b_norm'])} |")
    return [*lines, ""]


_WAY_STATS = ("kiss_plane_residual_m", "kiss_correction_m", "drift_final_yaw_deg_per_100m",
              "drift_final_scale_bias_pct")


def _kiss_ways(data: Mapping[str, Any]) -> list[str]:
    """A table of KISS-ICP's runs both ways (deskewed and not) on a side whose scans are raw sweeps, if any."""
    sides = [(side, data[side]) for side in ("real", "twin") if len(data[side].get("kiss_ways", {})) > 1]
    if not sides:
        return []
    lines = ["## KISS-ICP on raw sweeps, deskewed and not", "",
             "Compared above: the way `plvo eval run` reports, the one closer to the truth. Errors in % (heading "
             "offset taken out where the metric gives it).", "",
             "| side | way | reported | error 10 / 20 / 40 m | " + " | ".join(_WAY_STATS) + " |",
             "|---|---|---|---|" + "---:|" * len(_WAY_STATS)]
    for side, d in sides:
        for way, run in d["kiss_ways"].items():
            acc = run.get("accuracy") or {}
            errors = acc.get("aligned_t_err_pct") or acc.get("t_err_pct") or {}
            stats = [_num(_value(run["stats"].get(k))) for k in _WAY_STATS]
            lines.append(f"| {side} | {way} | {'yes' if way == d['kiss_way'] else ''} | "
                         f"{' / '.join(_num(v) for v in errors.values()) or '-'} | " + " | ".join(stats) + " |")
    return [*lines, ""]


def _value(entry: Mapping[str, Any] | None) -> float | None:
    return None if entry is None else entry["value"]
