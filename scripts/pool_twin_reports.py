"""Pool the KITTI twins' rows of several `plvo eval run` reports into one Table I, as the devkit pools sequences.

Table I's twins are generated and run a few at a time (eleven take ~55 GB and hours on 2 cores), each batch writing
its own report.json. The devkit's pooled figure is the mean over every segment of every sequence, so a batch's
per-twin means are weighed by their segment counts, which depend only on the truth (KITTI's poses, which the twins
follow): 100-800 m segments a start every 10 frames for the devkit's t_err and r_err, 10/20/40 m segments from every
frame for the short error. The pooled figures of one report computed this way equal its own "all" rows.

    .venv/bin/python scripts/pool_twin_reports.py --kitti-poses ../shared/data/kitti/poses \
        docs/results/twins_realistic_0af3d75/report.json docs/results/twins_realistic_05_3cb39f7/report.json

A twin in several reports is taken from the last one given. Prints the pooled rows (development, held out, all) and
writes them as JSON with --out.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from plvo.data.trajectory import read_kitti_poses
from plvo_eval.kitti_metric import SHORT_LENGTHS, segment_errors
from plvo_eval.splits import DEVELOPMENT, HELD_OUT, twin_split

FIGURES = {"t_err_pct": "devkit", "r_err_deg_per_m": "devkit", "short_t_err_pct": "short"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reports", nargs="+", type=Path, help="report.json files of plvo eval run --twins")
    ap.add_argument("--kitti-poses", type=Path, required=True, help="KITTI's poses/NN.txt, the twins' truth")
    ap.add_argument("--out", type=Path, help="write the pooled figures as JSON")
    args = ap.parse_args()

    rows: dict[str, dict[str, dict[str, float]]] = {}  # figure -> system -> twin -> value
    systems: list[str] = []
    for path in args.reports:
        report = json.loads(path.read_text())
        for figure in FIGURES:
            for system, values in report[figure].items():
                if system not in systems:
                    systems.append(system)
                for label, value in values.items():
                    if twin_split(label) is not None:
                        rows.setdefault(figure, {}).setdefault(system, {})[label] = value
    twins = sorted({t for by_system in rows["t_err_pct"].values() for t in by_system})
    counts = {}
    for twin in twins:
        truth = read_kitti_poses(args.kitti_poses / f"{twin[len('twin'):]}.txt")
        counts[twin] = {"devkit": len(segment_errors(truth, truth).length),
                        "short": len(segment_errors(truth, truth, SHORT_LENGTHS, 1).length)}
    groups = {DEVELOPMENT: [t for t in twins if twin_split(t) == DEVELOPMENT],
              HELD_OUT: [t for t in twins if twin_split(t) == HELD_OUT], "all": twins}
    pooled: dict[str, dict[str, dict[str, float]]] = {}
    for group, members in groups.items():
        for figure, kind in FIGURES.items():
            for system in systems:
                have = [t for t in members if t in rows[figure].get(system, {})]
                if not have:
                    continue
                n = sum(counts[t][kind] for t in have)
                value = sum(rows[figure][system][t] * counts[t][kind] for t in have) / n
                pooled.setdefault(group, {}).setdefault(figure, {})[system] = value
    print("twins: " + ", ".join(twins))
    for group, figures in pooled.items():
        print(f"{group} ({', '.join(t[len('twin'):] for t in groups[group])}):")
        for figure, by_system in figures.items():
            print(f"  {figure}: " + " / ".join(f"{s} {v:.5f}" for s, v in by_system.items()))
    if args.out is not None:
        args.out.write_text(json.dumps({"twins": twins, "segments": counts, "pooled": pooled,
                                        "reports": [str(p) for p in args.reports]}, indent=1) + "\n")


if __name__ == "__main__":
    main()
